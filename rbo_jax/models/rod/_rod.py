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

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._validation import FINITE, NONNEGATIVE, POSITIVE, checks_status, is_traced
from ...foundations import AbstractFoundation, ZeroFoundation
from ...kinematics import compose, turn_tensor
from ...mechanics import AbstractMechanics, EquilibriumStatus
from . import _field
from ._loads import as_rod_loads, real_array
from ._state import RodState

__all__ = ["BASES", "E3", "Rod"]

BASES = ("clamped", "pinned", "free")
E3 = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------------------------
# Parameters: concrete values are checked now, traced ones are taken as they are.
# --------------------------------------------------------------------------------------------


def _checked(x, name: str, owner: str, *, low: float = 0.0, strict: bool = True):
    """``x`` with every entry > ``low`` (or >= when not ``strict``) and finite, or a
    ``ValueError`` naming ``name``; traced values pass (:func:`rbo_jax.lattice.simulate`
    checks them, :meth:`Rod.parameter_checks`)."""
    if is_traced(x):
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
    return jnp.broadcast_to(jnp.asarray(x), (n,)) if is_traced(x) else np.broadcast_to(x, (n,))


def _foundation(foundation):
    """The foundation of a rod: an rbo_jax foundation of the bodies' turns, or ``None``."""
    if foundation is not None and not isinstance(foundation, AbstractFoundation):
        raise TypeError(
            "rod: foundation must be an rbo_jax foundation of the bodies' turns (e.g. "
            f"QuadraticFoundation(c, d, k)) or None, got {type(foundation).__name__}."
        )
    return None if isinstance(foundation, ZeroFoundation) else foundation


# --------------------------------------------------------------------------------------------
# The model.
# --------------------------------------------------------------------------------------------


class Rod(AbstractMechanics):
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
    foundation: AbstractFoundation | None = eqx.field(default=None, converter=_foundation)
    loads: tuple = eqx.field(default=(), converter=as_rod_loads)
    base_position: Float[Array, "3"] = eqx.field(
        default=(0.0, 0.0, 0.0), converter=functools.partial(real_array, name="base_position")
    )
    base_turn: Float[Array, "3"] = eqx.field(
        default=(0.0, 0.0, 0.0), converter=functools.partial(real_array, name="base_turn")
    )
    base: str = eqx.field(static=True, default="clamped", kw_only=True)

    def __check_init__(self):
        if self.base not in BASES:
            raise ValueError(f"rod: base must be one of {BASES}, got {self.base!r}.")
        nb = int(np.shape(self.mass)[0])
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

    # ---- the mechanics (rbo_jax.mechanics.AbstractMechanics) --------------------------------

    def rest(self) -> RodState:
        """The straight rod at rest (:meth:`straight`)."""
        return self.straight()

    def configuration(self, guess, name: str = "guess") -> RodState:
        """``guess`` (a :class:`RodState`; ``None``: the straight rod) at rest, checked."""
        if guess is None:
            return self.straight()
        if not isinstance(guess, RodState):
            raise TypeError(f"{name} must be a RodState, got {type(guess).__name__}.")
        shape = (self.n_bodies, 3)
        if tuple(np.shape(guess.theta)) != shape or tuple(np.shape(guess.r)) != shape:
            raise ValueError(
                f"{name} must have theta and r of shape {shape} (one row per body, the base "
                f"first), got {np.shape(guess.theta)} and {np.shape(guess.r)}."
            )
        return RodState.at_rest(guess.theta, guess.r)

    def block_shape(self) -> tuple[int, int]:
        """One block per body: its turn increment and displacement, ``(N+1, 6)``."""
        return (self.n_bodies, 6)

    def retract(self, state: RodState, x) -> RodState:
        r"""Turns composed, $\theta_i \leftarrow \mathrm{compose}(\theta_i, \delta_i)$ (4.5),
        so that a turn-vector never grows past $\pi$; positions added."""
        theta = jax.vmap(compose)(state.theta, x[:, :3])
        return RodState.at_rest(theta, state.r + x[:, 3:])

    def increment_scale(self, state: RodState):
        """Turns by 1, displacements by the rod's size (its largest coordinate, at least 1)."""
        size = jnp.maximum(jnp.max(jnp.abs(state.r)), 1.0)
        one = jnp.ones_like(state.r)
        return jnp.concatenate([one, size * one], axis=1)

    def static_residual(self, t, state: RodState, x, load_scale=1.0):
        """The moment and force balance of every body (:func:`._field.static_residual`)."""
        return _field.static_residual(self, state.theta, state.r, x, load_scale)

    def structure(self) -> str:
        """Every body is coupled to its neighbours only: ``"tridiagonal"``."""
        return "tridiagonal"

    def configuration_status(self, state: RodState, singular_tol: float = 1e-6):
        """Every configuration is admissible (the turns are composed: no singular sphere)."""
        return EquilibriumStatus.successful

    def free_size(self) -> int:
        """3 per free turn and 3 per free position."""
        turn, pos = self.free_masks()
        return 3 * int(turn.sum() + pos.sum())

    def free_increments(self, q):
        """``[delta, d]`` of the bodies that move into ``(N+1, 6)`` blocks, zero on the held
        coordinates of the base."""
        return _field.free_increments(self, q)

    def field(self, t, state: RodState, *, throw: bool = False):
        """The rod's first-order equations in the increments at ``state``
        (:func:`._field.first_order`)."""
        return _field.first_order(self, state.theta, state.r)

    def depends_on_velocity(self) -> bool:
        """Whether the rod has Kelvin–Voigt damping (a traced damping counts as damped)."""
        leaves = (self.turn_damping, self.gap_damping)
        if not all(isinstance(x, (np.ndarray, jax.Array)) for x in leaves):
            return True  # traced abstractly: its value unknown
        if any(is_traced(x) for x in leaves):
            return True
        return bool(any(np.any(np.asarray(x) != 0) for x in leaves))

    def state_at_rest(self, state: RodState) -> RodState:
        """The state itself (at rest)."""
        return state


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
