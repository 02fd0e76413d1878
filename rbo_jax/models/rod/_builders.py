"""Rods and chains of links from their physical description: :func:`rod` (a straight rod of
constants per unit length), :func:`circular_rod` (from a material and a circular section, as
PyElastica builds one) and :func:`pendulum` (rigid links with point masses and hinge springs:
Ziegler's pendulum). Each returns a :class:`rbo_jax.lattice.Rod`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..._validation import array_namespace
from ...foundations import AbstractFoundation
from ._loads import real_array
from ._rod import E3, Rod, _checked, _per_segment

__all__ = ["circular_rod", "pendulum", "rod"]


def _lumped(per_segment, h, xp):
    """Half of every segment's ``per_segment * h`` to each of its two end bodies: ``(N+1,)``."""
    seg = per_segment * h
    z = xp.zeros((1,), dtype=seg.dtype)
    return 0.5 * (xp.concatenate([seg, z]) + xp.concatenate([z, seg]))


def _diag3(a, b, c, xp):
    return xp.stack([a, b, c], axis=-1)


def rod(
    n: int,
    length,
    *,
    bending,
    torsion,
    shear,
    stretch,
    mass,
    rotary,
    damping=0.0,
    loads=(),
    base: str = "clamped",
    foundation: AbstractFoundation | None = None,
    tip_mass=0.0,
    shear_damping=None,
) -> Rod:
    r"""A straight rod of ``n`` bodies along $k = e_3$ (plus the base body at the origin, clamped
    by default): nodes $z_i = i\,L/n$, $i = 0\dots n$.

    **Arguments** (constants per unit length, each a scalar or one value per segment, shape
    ``(n,)``, segment $i$ between bodies $i-1$ and $i$: a tapered rod):

    - `bending` $EI$, `torsion` $GJ$, `shear` $\kappa GA$, `stretch` $EA$;
    - `mass` $\rho A$; `rotary` $\rho I$, the rotary inertia per length about a transverse axis
      (the polar one is $2\rho I$), or a pair ``(rho_I, rho_J)`` given as a Python tuple
      (a per-segment pair: shape ``(n, 2)``);
    - `damping`: Kelvin–Voigt time $\eta$ (s): every stress resultant $K s$ gains
      $\eta K\dot s$; `shear_damping`: another time for the shear and stretch resultants
      (default `damping`; 0 damps bending and twist only, the internal damping of Bolotin's
      Beck column: a stiff shear or stretch with a small rotary inertia makes the damped
      spectrum badly conditioned, see :func:`rbo_jax.lattice.critical_load`);
    - `loads`: :class:`TipForce`, :class:`TipMoment`, :class:`Gravity`,
      :class:`DistributedForce`;
    - `base`: ``"clamped"``, ``"pinned"`` or ``"free"``;
    - `foundation`: an energy of every body's turn per unit length (a rod on an elastic
      foundation of rigid body oscillators);
    - `tip_mass`: a point mass added to the tip body (Pflüger's column: Beck's column with a
      tip mass), no rotary inertia of its own.

    Every float may be traced (``jax.vmap`` over ``bending``, ``jax.grad`` with respect to
    ``shear``).
    """
    owner = "rod"
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"rod: n must be an integer, got {n!r}.")
    n = int(n)
    if n < 2:
        raise ValueError(f"rod: n must be >= 2 bodies past the base, got {n}.")
    L = _checked(real_array(length, "length", owner), "length", owner)
    if np.shape(L) != ():
        raise ValueError(f"rod: length must be a scalar, got shape {np.shape(L)}.")
    EI = _per_segment(bending, "bending", n, owner)
    GJ = _per_segment(torsion, "torsion", n, owner)
    kGA = _per_segment(shear, "shear", n, owner)
    EA = _per_segment(stretch, "stretch", n, owner)
    rhoA = _per_segment(mass, "mass", n, owner)
    if isinstance(rotary, tuple) and len(rotary) == 2:
        rhoI = _per_segment(rotary[0], "rotary", n, owner)
        rhoJ = _per_segment(rotary[1], "rotary (polar)", n, owner)
    else:
        rot = _checked(real_array(rotary, "rotary", owner), "rotary", owner)
        if tuple(np.shape(rot)) == (n, 2):
            rhoI, rhoJ = rot[:, 0], rot[:, 1]
        else:
            rhoI = _per_segment(rot, "rotary", n, owner)
            rhoJ = 2.0 * rhoI
    eta = _per_segment(damping, "damping", n, owner, strict=False)
    eta_g = (
        eta
        if shear_damping is None
        else _per_segment(shear_damping, "shear_damping", n, owner, strict=False)
    )
    M_tip = _checked(real_array(tip_mass, "tip_mass", owner), "tip_mass", owner, strict=False)
    if np.shape(M_tip) != ():
        raise ValueError(f"rod: tip_mass must be a scalar, got shape {np.shape(M_tip)}.")
    xp = array_namespace(L, EI, GJ, kGA, EA, rhoA, rhoI, rhoJ, eta, eta_g, M_tip)
    h = L / n
    m = _lumped(rhoA, h, xp)
    m = m + M_tip * xp.asarray(np.arange(n + 1) == n, dtype=m.dtype)
    Jt, Jp = _lumped(rhoI, h, xp), _lumped(rhoJ, h, xp)
    inertia = _diag3(Jt, Jt, Jp, xp)[:, :, None] * xp.eye(3)[None]
    share = _lumped(xp.ones(n, dtype=m.dtype), h, xp)
    zeros = xp.zeros((n, 3), dtype=m.dtype)
    return Rod(
        mass=m,
        inertia=inertia,
        share=share,
        turn_stiffness=_diag3(EI, EI, GJ, xp) / h,
        gap_stiffness=_diag3(kGA, kGA, EA, xp) / h,
        turn_damping=eta,
        gap_damping=eta_g,
        attach_a=zeros,
        attach_b=zeros,
        rest_gap=xp.broadcast_to(h * xp.asarray(E3, dtype=m.dtype), (n, 3)) + zeros,
        foundation=foundation,
        loads=loads,
        base=base,
    )


def circular_rod(
    n: int,
    length,
    *,
    radius,
    density,
    youngs_modulus,
    shear_modulus=None,
    poisson_ratio: float = 0.5,
    shear_coefficient=27.0 / 28.0,
    damping=0.0,
    loads=(),
    base: str = "clamped",
    foundation=None,
) -> Rod:
    r"""A rod of circular cross-section from its material, as PyElastica's ``CosseratRod.
    straight_rod`` takes it: $A = \pi r^2$, $I = \pi r^4/4$, $J = 2I$; $EI$, $GJ = G\cdot 2I$,
    $\kappa GA$ and $EA$; $\rho A$ and $\rho I$. ``shear_modulus`` defaults to
    $G = E/(2(1 + \nu))$ with ``poisson_ratio`` $\nu = 0.5$ (PyElastica's default);
    ``shear_coefficient`` is the factor PyElastica multiplies $GA$ by, $27/28$ by default (its
    ``alpha_c`` in PyElastica 1.0's ``straight_rod``), so that ``shear`` $= \tfrac{27}{28} GA$ as
    PyElastica's; Timoshenko's shear coefficient of a solid circle is
    $\kappa = 6(1+\nu)/(7 + 6\nu)$ (0.9 at $\nu = 1/2$): pass it to compare with other
    Timoshenko beams."""
    owner = "circular_rod"
    r = _checked(real_array(radius, "radius", owner), "radius", owner)
    rho = _checked(real_array(density, "density", owner), "density", owner)
    E = _checked(real_array(youngs_modulus, "youngs_modulus", owner), "youngs_modulus", owner)
    if shear_modulus is None:
        G = E / (2.0 * (1.0 + poisson_ratio))
    else:
        G = _checked(real_array(shear_modulus, "shear_modulus", owner), "shear_modulus", owner)
    kappa = _checked(
        real_array(shear_coefficient, "shear_coefficient", owner), "shear_coefficient", owner
    )
    A = math.pi * r**2
    I = math.pi * r**4 / 4.0  # noqa: E741 - the second moment of area
    return rod(
        n,
        length,
        bending=E * I,
        torsion=G * 2.0 * I,
        shear=kappa * G * A,
        stretch=E * A,
        mass=rho * A,
        rotary=(rho * I, rho * 2.0 * I),
        damping=damping,
        loads=loads,
        base=base,
        foundation=foundation,
    )


def pendulum(
    masses: Sequence,
    lengths: Sequence,
    stiffness: Sequence,
    *,
    damping=0.0,
    loads=(),
    torsion=None,
    rotary: float = 1e-6,
    penalty: float = 1e6,
) -> Rod:
    r"""A chain of rigid massless links with point masses at their ends and hinge springs, the
    base hinge at the origin (Ziegler's pendulum: ``pendulum([2 m, m], [l, l], [c, c])``).

    Body $i \ge 1$ is the point mass ``masses[i-1]`` at the end of link $i$ (length
    ``lengths[i-1]``), turning with the link; hinge $i$ joins the end of link $i-1$ (the base
    for $i = 1$) to the start of link $i$, $-l_i\,k$ in body $i$'s frame, with the rotational
    spring ``stiffness[i-1]`` (about both transverse axes; about the axis ``torsion``, default
    the same) and a hinge damper ``damping`` × stiffness (Kelvin–Voigt on the relative turn
    only). The hinges are stiff couplings of the gap, ``penalty`` × stiffness / l², and a point
    mass carries a small rotary inertia ``rotary`` × m l²: the rigid pendulum is their limit,
    approached to O(1/penalty) and O(rotary) (tested).
    """
    owner = "pendulum"
    m = _checked(real_array(masses, "masses", owner), "masses", owner)
    ls = _checked(real_array(lengths, "lengths", owner), "lengths", owner)
    c = _checked(real_array(stiffness, "stiffness", owner), "stiffness", owner)
    n = int(np.shape(m)[0]) if np.ndim(m) == 1 else 0
    if n < 1 or np.shape(ls) != (n,) or np.shape(c) != (n,):
        raise ValueError(
            f"pendulum: masses, lengths and stiffness need one value per link, got shapes "
            f"{np.shape(m)}, {np.shape(ls)}, {np.shape(c)}."
        )
    ct = c if torsion is None else _per_segment(torsion, "torsion", n, owner)
    eta = _per_segment(damping, "damping", n, owner, strict=False)
    xp = array_namespace(m, ls, c, ct, eta)
    z1 = xp.zeros((1,), dtype=m.dtype)
    mass = xp.concatenate([z1 + 1.0, m])  # the base body never moves
    J = rotary * mass * xp.concatenate([z1 + 1.0, ls]) ** 2
    inertia = J[:, None, None] * xp.eye(3)[None]
    k = xp.asarray(E3, dtype=m.dtype)
    zeros = xp.zeros((n, 3), dtype=m.dtype)
    Kg = penalty * c / ls**2
    return Rod(
        mass=mass,
        inertia=inertia,
        share=xp.concatenate([z1, ls]),
        turn_stiffness=_diag3(c, c, ct, xp),
        gap_stiffness=_diag3(Kg, Kg, Kg, xp),
        turn_damping=eta,
        gap_damping=xp.zeros((n,), dtype=m.dtype),
        attach_a=zeros,
        attach_b=-ls[:, None] * k[None, :],
        rest_gap=zeros,
        foundation=None,
        loads=loads,
        base="clamped",
    )
