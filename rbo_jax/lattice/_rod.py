r"""Bodies that also translate: rods and chains of links made of rigid body oscillators.

A :class:`Rod` is a chain of $N + 1$ rigid bodies $i = 0\dots N$ (body 0 at the base). Every
body has a turn $\theta_i$ with the right form (4.55)–(4.56) of its rotation, and a position
$r_i$ of its centre with Newton's law $m_i\ddot r_i = F_i$. Neighbours $(a, b) = (s, s+1)$ are
coupled at points $a_s$ of body $a$ and $b_s$ of body $b$ (body-frame offsets from the centres)
through two strains:

* the relative turn $\varphi_s = \mathrm{turn\_vector}(Q_a^T Q_b)$ (bending and twist), as in
  every lattice (:mod:`._lattice`);
* the gap between the attachment points seen in the **mid-frame** $Q_m = Q_a\,Q(\varphi_s/2)$,
  less its rest value $g^0_s$:

  $$\tilde g_s = Q_m^T\,(r_b + Q_b\,b_s - r_a - Q_a\,a_s) - g^0_s.$$

  For a rod's segment the attachment points are the centres and $g^0 = h\,k$, so
  $\tilde g/h = Q_m^T(r_b - r_a)/h - k$ is the shear and stretch strain $\varepsilon$; for a
  hinge of two links they are the ends of the links and $g^0 = 0$.

The mid-frame is the rotation half-way along the geodesic from $Q_a$ to $Q_b$; it is the same
seen from either end ($Q_b\,Q(-\varphi/2) = Q_a\,Q(\varphi/2)$), so the strains are symmetric
under the exchange of the two bodies (with $\varphi\to-\varphi$, $\tilde g\to -\tilde g$ for a
symmetric pair) and objective: a rigid motion $Q_a, Q_b \to R\,Q_a, R\,Q_b$,
$r \to R\,r + c$ leaves $\varphi$ and $\tilde g$ unchanged. It is the interpolation of the
rotation at the middle of an element whose strains Crisfield and Jelenić showed to be objective
(Crisfield & Jelenić 1999, Proc. R. Soc. Lond. A 455, 1125–1147; the discrete Cosserat rods of
Simo & Vu-Quoc 1986 take the same strain measures).

The energy of a coupling is quadratic in its strains,
$W_s = \tfrac12\,\varphi_s\cdot K^\varphi_s\varphi_s + \tfrac12\,\tilde g_s\cdot K^g_s
\tilde g_s$ with diagonal stiffnesses in the mid-frame (a rod's segment of length $h$:
$K^\varphi = \mathrm{diag}(EI, EI, GJ)/h$ and $K^g = \mathrm{diag}(\kappa GA, \kappa GA, EA)/h$,
i.e. $W = h\,[\tfrac12\kappa\cdot B\kappa + \tfrac12\varepsilon\cdot S\varepsilon]$ with the
curvature $\kappa = \varphi/h$). Kelvin–Voigt damping adds $\eta\,K\dot s$ to every stress
resultant $K s$. Bodies may sit on a foundation of their turn, as every rigid body oscillator
(a rod on an elastic foundation).

The rod of :func:`rod` puts its bodies on the nodes $z_i = i\,h$ of the centreline (body 0, the
base, at the origin): every segment between two nodes is one coupling, whose strains are those
at its middle (second order in $h$), a body carries the mass and rotary inertia of half of each
of its segments, and a tip load acts on the last body with no lever arm.
:func:`pendulum` builds a chain of links with hinge springs (Ziegler's pendulum) as the same
object: point masses at the ends of rigid links, the hinges stiff couplings of the gaps.

Base conditions: ``"clamped"`` (body 0 held in position and turn), ``"pinned"`` (held in
position, free to turn), ``"free"``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._validation import FINITE, NONNEGATIVE, POSITIVE, _is_traced, checks_status
from ..foundations import AbstractFoundation, ZeroFoundation
from ..kinematics import turn_tensor
from ._rod_loads import as_rod_loads, real_array

__all__ = ["BASES", "Rod", "RodState", "circular_rod", "pendulum", "rod"]

BASES = ("clamped", "pinned", "free")
E3 = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------------------------
# Parameters: concrete values are checked now, traced ones are taken as they are.
# --------------------------------------------------------------------------------------------


def _checked(x, name: str, owner: str, *, low: float = 0.0, strict: bool = True):
    """``x`` with every entry > ``low`` (or >= when not ``strict``) and finite, or a
    ``ValueError`` naming ``name``; traced values pass (:func:`rbo_jax.lattice.simulate`
    checks them, :meth:`Rod.parameter_checks`)."""
    if _is_traced(x):
        return x
    a = np.asarray(x)
    ok = np.all(np.isfinite(a)) and (np.all(a > low) if strict else np.all(a >= low))
    if not ok:
        op = ">" if strict else ">="
        raise ValueError(f"{owner}: {name} must be finite and {op} {low}, got {a.tolist()!r}.")
    return x


def _per_segment(x, name: str, n: int, owner: str, *, strict: bool = True):
    """A constant per unit length: a scalar or one value per segment (shape ``(n,)``), as an
    ``(n,)`` array, checked."""
    x = _checked(real_array(x, name, owner), name, owner, strict=strict)
    shape = tuple(np.shape(x))
    if shape not in ((), (n,)):
        raise ValueError(
            f"{owner}: {name} must be a scalar or one value per body (shape ({n},)), got shape "
            f"{shape}."
        )
    return jnp.broadcast_to(jnp.asarray(x), (n,)) if _is_traced(x) else np.broadcast_to(x, (n,))


def _xp(*xs):
    return jnp if any(_is_traced(x) for x in xs) else np


# --------------------------------------------------------------------------------------------
# The model.
# --------------------------------------------------------------------------------------------


class Rod(eqx.Module):
    r"""A chain of $N + 1$ bodies that turn and translate, coupled by energies of the relative
    turn and of the gap in the mid-frame (module docstring). Build one with :func:`rod`,
    :func:`circular_rod` or :func:`pendulum`.

    Fields (every float leaf may be traced: vmap over a stiffness, grad with respect to a mass):
    per body ``mass`` (N+1,), ``inertia`` (N+1, 3, 3) (body frame), ``share`` (N+1,) (length
    carried: distributed loads and the foundation); per coupling ``turn_stiffness``,
    ``gap_stiffness`` (N, 3) (diagonals in the mid-frame), ``turn_damping``, ``gap_damping``
    (N,) (Kelvin–Voigt times, s), ``attach_a``, ``attach_b``, ``rest_gap`` (N, 3); ``foundation``
    (an energy of every body's turn per unit length, or ``None``); ``loads``; ``base_position``,
    ``base_turn`` (3,) (the held values of the base body); static ``base``.
    """

    mass: Float[Array, " B"]
    inertia: Float[Array, "B 3 3"]
    share: Float[Array, " B"]
    turn_stiffness: Float[Array, "S 3"]
    gap_stiffness: Float[Array, "S 3"]
    turn_damping: Float[Array, " S"]
    gap_damping: Float[Array, " S"]
    attach_a: Float[Array, "S 3"]
    attach_b: Float[Array, "S 3"]
    rest_gap: Float[Array, "S 3"]
    foundation: AbstractFoundation | None
    loads: tuple
    base_position: Float[Array, "3"]
    base_turn: Float[Array, "3"]
    base: str = eqx.field(static=True)

    def __init__(
        self,
        *,
        mass,
        inertia,
        share,
        turn_stiffness,
        gap_stiffness,
        turn_damping,
        gap_damping,
        attach_a,
        attach_b,
        rest_gap,
        foundation=None,
        loads=(),
        base="clamped",
        base_position=(0.0, 0.0, 0.0),
        base_turn=(0.0, 0.0, 0.0),
    ):
        if base not in BASES:
            raise ValueError(f"rod: base must be one of {BASES}, got {base!r}.")
        if foundation is not None and not isinstance(foundation, AbstractFoundation):
            raise TypeError(
                "rod: foundation must be an rbo_jax foundation of the bodies' turns (e.g. "
                f"QuadraticFoundation(c, d, k)) or None, got {type(foundation).__name__}."
            )
        if isinstance(foundation, ZeroFoundation):
            foundation = None
        # the fields one by one (a loop over names would hide them from type checkers)
        self.mass = mass
        self.inertia = inertia
        self.share = share
        self.turn_stiffness = turn_stiffness
        self.gap_stiffness = gap_stiffness
        self.turn_damping = turn_damping
        self.gap_damping = gap_damping
        self.attach_a = attach_a
        self.attach_b = attach_b
        self.rest_gap = rest_gap
        self.foundation = foundation
        self.base = base
        self.base_position = real_array(base_position, "base_position", "rod")
        self.base_turn = real_array(base_turn, "base_turn", "rod")
        nb = int(np.shape(mass)[0])
        shapes = {
            "inertia": (nb, 3, 3),
            "share": (nb,),
            "turn_stiffness": (nb - 1, 3),
            "gap_stiffness": (nb - 1, 3),
            "turn_damping": (nb - 1,),
            "gap_damping": (nb - 1,),
            "attach_a": (nb - 1, 3),
            "attach_b": (nb - 1, 3),
            "rest_gap": (nb - 1, 3),
            "base_position": (3,),
            "base_turn": (3,),
        }
        for name, shape in shapes.items():
            if tuple(np.shape(getattr(self, name))) != shape:
                raise ValueError(
                    f"Rod: {name} must have shape {shape} for {nb} bodies, got "
                    f"{tuple(np.shape(getattr(self, name)))}."
                )
        self.loads = as_rod_loads(loads)
        for load in self.loads:
            load.check(self)

    @property
    def n_bodies(self) -> int:
        """N + 1: the bodies, the base included."""
        return int(np.shape(self.mass)[0])

    @property
    def n(self) -> int:
        """N: the couplings (segments or links); the bodies past the base."""
        return self.n_bodies - 1

    def free_masks(self):
        """``(turn (N+1,), position (N+1,))`` NumPy booleans: which bodies' turns and positions
        move (the base's follow ``base``)."""
        turn = np.ones(self.n_bodies, bool)
        pos = np.ones(self.n_bodies, bool)
        if self.base in ("clamped", "pinned"):
            pos[0] = False
        if self.base == "clamped":
            turn[0] = False
        return turn, pos

    def parameter_checks(self) -> list:
        """``(valid, message)`` pairs of the rod's own requirements, as the constructors check
        concrete values (:func:`rod`, :func:`circular_rod`, :func:`pendulum`): every float
        finite, masses, rotary inertias and stiffnesses > 0, damping times and lengths >= 0;
        and the foundation's. Values that were traced at construction are checked here, by the
        solvers that use the rod (:meth:`parameter_status`)."""
        leaves = [
            x
            for x in jax.tree_util.tree_leaves(self)
            if jnp.issubdtype(jnp.result_type(x), jnp.inexact)
        ]
        finite = jnp.all(jnp.stack([jnp.all(FINITE.holds(x)) for x in leaves]))
        diagonal = jnp.diagonal(self.inertia, axis1=-2, axis2=-1)
        damping = jnp.concatenate([self.turn_damping, self.gap_damping])
        P, N = POSITIVE, NONNEGATIVE
        checks = [
            (finite, "rod: a parameter is NaN or infinite."),
            (
                jnp.all(P.holds(self.mass)),
                f"rod: mass (and tip_mass) must give every body a mass {P.text}.",
            ),
            (jnp.all(P.holds(diagonal)), f"rod: rotary must be {P.text}."),
            (jnp.all(P.holds(self.turn_stiffness)), f"rod: bending and torsion must be {P.text}."),
            (jnp.all(P.holds(self.gap_stiffness)), f"rod: shear and stretch must be {P.text}."),
            (jnp.all(N.holds(damping)), f"rod: damping and shear_damping must be {N.text}."),
            (jnp.all(N.holds(self.share)), f"rod: length must be {P.text}."),
        ]
        if self.foundation is not None:
            checks += self.foundation.parameter_checks()
        return checks

    def parameter_status(self):
        """``(ok, which, messages)`` of :meth:`parameter_checks`, as
        :meth:`rbo_jax.RigidBodyOscillator.parameter_status`: whether every check holds, the
        index of the first that fails and every message (static)."""
        return checks_status(self.parameter_checks())

    def with_loads(self, loads) -> Rod:
        """The same rod under other loads."""
        loads = as_rod_loads(loads)
        for load in loads:
            load.check(self)
        return eqx.tree_at(lambda r: r.loads, self, loads)

    def straight(self) -> RodState:
        """The reference state at rest: every body turned as the base, the centres at the base
        plus the rest gaps (a straight rod along the base's axis)."""
        return _straight(self)

    # The protocol of rbo_jax.bifurcation._interface.model_solver: hopf_point and continue_hopf
    # of a model_fn returning a Rod come here (bifurcation does not import lattice). The solvers
    # are taken from this package's public namespace, loaded on first use as every public name
    # is (_lazy): the module that defines them imports this one.
    @staticmethod
    def rbo_hopf_point(*args, **kwargs):
        """:func:`rbo_jax.lattice.rod_hopf_point` (what :func:`rbo_jax.hopf_point` calls)."""
        from . import rod_hopf_point  # noqa: PLC0415

        return rod_hopf_point(*args, **kwargs)

    @staticmethod
    def rbo_continue_hopf(*args, **kwargs):
        """:func:`rbo_jax.lattice.rod_continue_hopf` (what :func:`rbo_jax.continue_hopf`
        calls)."""
        from . import rod_continue_hopf  # noqa: PLC0415

        return rod_continue_hopf(*args, **kwargs)


def _straight(rod: Rod) -> RodState:
    Q0 = turn_tensor(jnp.asarray(rod.base_turn))
    a, b, g0 = (jnp.asarray(x) for x in (rod.attach_a, rod.attach_b, rod.rest_gap))
    # r_b = r_a + Q0 (a + g0 - b) for every coupling, the turns all equal to the base's
    steps = (a + g0 - b) @ Q0.T
    base = jnp.asarray(rod.base_position)
    r = jnp.concatenate([base[None], base[None] + jnp.cumsum(steps, axis=0)])
    theta = jnp.broadcast_to(jnp.asarray(rod.base_turn), r.shape)
    z = jnp.zeros_like(r)
    return RodState(theta, r, z, z)


class RodState(eqx.Module):
    r"""The state of a rod: per body (N+1, base first) the turn-vector ``theta``, the position
    ``r``, the right (body-frame) angular velocity ``Omega`` and the velocity ``v``, each
    ``(..., N+1, 3)``. ``centreline``: the positions of the N+1 nodes from the base to the tip
    (the bodies' centres for :func:`rod`)."""

    theta: Float[Array, "... B 3"]
    r: Float[Array, "... B 3"]
    Omega: Float[Array, "... B 3"]
    v: Float[Array, "... B 3"]

    @property
    def centreline(self):
        return self.r

    @property
    def tip(self):
        """The position of the last body, ``(..., 3)``."""
        return self.r[..., -1, :]

    @staticmethod
    def at_rest(theta, r) -> RodState:
        z = jnp.zeros_like(jnp.asarray(r))
        return RodState(jnp.asarray(theta), jnp.asarray(r), z, z)


# --------------------------------------------------------------------------------------------
# Constructors.
# --------------------------------------------------------------------------------------------


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
    xp = _xp(L, EI, GJ, kGA, EA, rhoA, rhoI, rhoJ, eta, eta_g, M_tip)
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
    xp = _xp(m, ls, c, ct, eta)
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
