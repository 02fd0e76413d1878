r"""Strains, energies, forces and the equations of motion of a rod (:mod:`._rod`).

Arrays are body-major: ``(N+1, 3)`` per body, ``(N, 3)`` per coupling. Turns are handled as
turn-tensors (batched 3×3 products: few operations to compile and differentiate twice); a body's
turn is $Q(\theta_i)\cdot Q(\delta_i)$, the turn-vector of the state
composed with a **local increment** $\delta_i$ in the body's frame. Every force and moment is
the derivative of the total energy with respect to the increments and displacements at zero
(reverse-mode autodiff through the strains):

$$M_i = -Z(\delta_i)\cdot\frac{\partial U}{\partial\delta_i}, \qquad
  F_i = -\frac{\partial U}{\partial r_i},$$

which at $\delta = 0$ ($Z(0) = E$) is the body-frame moment of (4.55) without $Z(\theta_i)$:
no singular sphere $|\theta| = 2\pi k$ enters the forces, only the kinematic equation
$\dot\theta = Z^T(\theta)\cdot\Omega$ (4.14). Equilibria and linearisations use the same
function at $\delta \ne 0$ (the increments are their unknowns: a Newton step or a perturbation
turns every body about its own frame, as the Lie-group linearisation does).

With Kelvin–Voigt damping the stress of a coupling is $\sigma = K(s + \eta\dot s)$, the strain
rate $\dot s$ the forward-mode derivative of the strains along the velocities
$(\dot\delta, \dot r) = (Z^T(\delta)\cdot\Omega, v)$; its virtual work gives the damping forces
and moments the same way.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..._elementary import horner
from ..._validation import is_traced
from ...kinematics import (
    ATANC,
    X2_SWITCH,
    Turn,
    cross3,
    integrating_tensor_inv,
    solve3,
    turn_tensor,
    turn_vector,
)
from ._loads import DistributedForce, Gravity, Motion, TipForce
from ._state import RodState

__all__ = [
    "body_forces",
    "first_order",
    "free_increments",
    "free_index",
    "static_residual",
    "coupling_energy",
    "energy",
    "kinetic_energy",
    "kinetic_moment",
    "potential_energy",
    "rates",
    "strains",
]


def tensors(theta):
    r"""The turn-tensors $Q(\theta_i)$ (4.3) of rows of turn-vectors, ``(B, 3, 3)``."""
    return jax.vmap(turn_tensor)(theta)


def composed(theta, delta):
    r"""$Q(\theta_i)\cdot Q(\delta_i)$, ``(B, 3, 3)``."""
    return jnp.einsum("bij,bjk->bik", tensors(theta), tensors(delta))


def rotate(Q, x, back: bool = False):
    r"""$Q_i\cdot x_i$ (or $Q_i^T\cdot x_i$) for rows."""
    return jnp.einsum("bji,bj->bi" if back else "bij,bj->bi", Q, x)


def log_unit(w, v):
    r"""The principal turn-vector of unit quaternions with $w > 0$ (rows):
    $2\,\mathrm{atan2}(|v|, w)/|v|\cdot v$, by the series of $\arctan(x)/x$ near the identity
    (double where: exact values and derivatives at 0)."""
    s2 = jnp.sum(v * v, axis=-1)
    small = s2 < X2_SWITCH * w * w
    w_safe = jnp.where(small, w, 1.0)
    series = horner(ATANC, jnp.where(small, s2, 0.0) / (w_safe * w_safe)) / w_safe
    s_safe = jnp.sqrt(jnp.where(small, 1.0, s2))
    closed = jnp.arctan2(s_safe, w) / s_safe
    return 2.0 * jnp.where(small, series, closed)[..., None] * v


def _quaternion_of(R):
    r"""The unit quaternion $(w > 0, v)$ of rotations $R$ turning by less than $\pi$
    ($1 + \mathrm{tr}\,R > 0$; NaN otherwise, reported by the solvers)."""
    w = 0.5 * jnp.sqrt(1.0 + R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2])
    v = jnp.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)
    return w, v / (4.0 * w[:, None])


def matrix_of(w, v):
    r"""The rotation of unit quaternions $(w, v)$: $(w^2 - v^2)E + 2vv^T + 2w\,v\times$."""
    vx = jnp.stack(
        [
            jnp.stack([0.0 * w, -v[:, 2], v[:, 1]], -1),
            jnp.stack([v[:, 2], 0.0 * w, -v[:, 0]], -1),
            jnp.stack([-v[:, 1], v[:, 0], 0.0 * w], -1),
        ],
        1,
    )
    diag = (w * w - jnp.sum(v * v, -1))[:, None, None] * jnp.eye(3, dtype=w.dtype)[None]
    return diag + 2.0 * v[:, :, None] * v[:, None, :] + 2.0 * w[:, None, None] * vx


def attached(x) -> bool:
    """Whether attachment offsets may be nonzero (traced, or concrete and nonzero; ``None``:
    known to be zero before tracing, see :func:`._rod_verlet.verlet`)."""
    if x is None:
        return False
    return is_traced(x) or bool(np.any(np.asarray(x) != 0))


def rest_turns(rod, t=0.0):
    """The couplings' rest relative turns ``(N, 3)`` at time ``t`` from the loads that actuate
    them (:class:`._actuation.RestCurvature`), or ``None``."""
    rest = [x for x in (load.rest_turns(rod, t) for load in rod.loads) if x is not None]
    return sum(rest[1:], rest[0]) if rest else None


def strains(rod, Q, r, t=0.0):
    r"""``(phi, gap)``, each ``(N, 3)``: the relative turn $\varphi_s$ of every coupling (less
    its rest value at time ``t``, :func:`rest_turns`: zero unless actuated) and its gap
    $\tilde g_s$ in the mid-frame less the rest gap (module docstring of :mod:`._rod`), from
    the turn-tensors ``Q`` (N+1, 3, 3) and positions ``r``. The relative turns of neighbours
    must stay below $\pi$ (a rod's segments, a pendulum's hinges)."""
    Qa, Qb = Q[:-1], Q[1:]
    w, v = _quaternion_of(jnp.einsum("sji,sjk->sik", Qa, Qb))
    phi = log_unit(w, v)
    c = 1.0 / jnp.sqrt(2.0 * (1.0 + w))  # the half turn: (1 + w, v) normalised
    mid = jnp.einsum("sij,sjk->sik", Qa, matrix_of(c * (1.0 + w), c[:, None] * v))
    gap = r[1:] - r[:-1]
    if attached(rod.attach_b):
        gap = gap + rotate(Qb, jnp.asarray(rod.attach_b))
    if attached(rod.attach_a):
        gap = gap - rotate(Qa, jnp.asarray(rod.attach_a))
    rest = rest_turns(rod, t)
    if rest is not None:
        phi = phi - rest
    return phi, rotate(mid, gap, back=True) - jnp.asarray(rod.rest_gap)


def coupling_energy(rod, q, r, t=0.0):
    r"""$\sum_s \tfrac12\varphi_s\cdot K^\varphi_s\varphi_s + \tfrac12\tilde g_s\cdot K^g_s
    \tilde g_s$ (at time ``t``: an actuated rest curvature)."""
    phi, gap = strains(rod, q, r, t)
    Kp, Kg = jnp.asarray(rod.turn_stiffness), jnp.asarray(rod.gap_stiffness)
    return 0.5 * jnp.sum(Kp * phi * phi) + 0.5 * jnp.sum(Kg * gap * gap)


def _free(rod):
    turn, pos = rod.free_masks()
    return jnp.asarray(turn, float), jnp.asarray(pos, float)


def site_energy(rod, q):
    r"""$\sum_i \ell_i\,U(\theta_i)$ of the bodies' foundation ($\ell_i$ their shares of the
    length), 0 without one."""
    if rod.foundation is None:
        return jnp.zeros((), q.dtype)
    theta = jax.vmap(turn_vector)(q)
    U = jax.vmap(rod.foundation.energy)(theta)
    return jnp.sum(jnp.asarray(rod.share) * U * _free(rod)[0])


def _load_potential(rod, r):
    """The potential of the dead forces (gravity, distributed dead forces, dead tip forces). A
    dead moment (:class:`TipMoment` with ``follower=False``) has none in general: it is not in
    the energy."""
    V = jnp.zeros((), r.dtype)
    for load in rod.loads:
        if isinstance(load, Gravity):
            V = V - jnp.sum(jnp.asarray(rod.mass)[:, None] * r * jnp.asarray(load.g)[None, :])
        elif isinstance(load, DistributedForce):
            V = V - jnp.sum(jnp.asarray(rod.share)[:, None] * r * jnp.asarray(load.q)[None, :])
        elif isinstance(load, TipForce) and not load.follower:
            V = V - jnp.dot(jnp.asarray(load.force), r[load.body % rod.n_bodies])
    return V


def _external(rod, q, scale, at):
    """World forces and body moments of the loads, ``(N+1, 3)`` each, at the motion ``at``
    (:class:`._loads.Motion`)."""
    F = jnp.zeros((rod.n_bodies, 3), q.dtype)
    M = jnp.zeros_like(F)

    def turn(i, x, back):
        return q[i].T @ x if back else q[i] @ x

    for load in rod.loads:
        f, m = load.forces(rod, turn, scale, at)
        F, M = F + f, M + m
    return F, M


def body_forces(rod, theta, r, delta, d, Omega=None, v=None, scale=1.0, t=0.0):
    r"""``(M, F)``: the body-frame moment and the world force on every body, ``(N+1, 3)`` each,
    at the turns $Q(\theta_i)Q(\delta_i)$ and positions $r_i + d_i$ moving with the angular
    velocities $\Omega_i$ and velocities $v_i$ (``None``: at rest, no damping traced): the
    couplings (elastic and Kelvin–Voigt), the foundation, and the loads times ``scale`` at time
    ``t``. Zero on the held coordinates of the base.

    Computed as :func:`forces_tangent` at the composed turn-tensors $Q(\theta_i)Q(\delta_i)$:
    the moment about a body's own frame at its turn is $-Z(\delta_i)\cdot\partial U/\partial
    \delta_i$ of the module docstring, and $\Omega_i$ is the angular velocity in that frame, so
    both are :func:`forces_at` to rounding at every $\delta$ (5e-15 of the largest moment at
    |δ| ~ 0.5, damped rod on a foundation under follower, dead and gravity loads), their
    derivatives too. A smaller program than :func:`forces_at`'s: the equilibrium's and the
    spectrum's programs compile faster (benchmarks/README.md, History)."""
    return forces_tangent(rod, composed(theta, delta), r + d, Omega, v, scale, t)


def forces_at(rod, Q, r, delta, d, Omega=None, v=None, scale=1.0, t=0.0):
    r""":func:`body_forces` at the turn-tensors ``Q`` (N+1, 3, 3) instead of turn-vectors, by
    the module docstring's definition (the energy through $Q\cdot Q(\delta)$, moments through
    $Z(\delta)$): the reference of :func:`forces_tangent` (tested) and of the force timings of
    benchmarks/bench_rod.py."""

    def composed_q(delta):
        return jnp.einsum("bij,bjk->bik", Q, tensors(delta))

    def strain_of(delta, d):
        return strains(rod, composed_q(delta), r + d, t)

    (phi, gap), pull = jax.vjp(strain_of, delta, d)
    Kp, Kg = jnp.asarray(rod.turn_stiffness), jnp.asarray(rod.gap_stiffness)
    if Omega is not None:
        rate = (jax.vmap(lambda de, Om: Turn(de).ZT(Om))(delta, Omega), v)
        phi_dot, gap_dot = jax.jvp(strain_of, (delta, d), rate)[1]
        phi = phi + jnp.asarray(rod.turn_damping)[:, None] * phi_dot
        gap = gap + jnp.asarray(rod.gap_damping)[:, None] * gap_dot
    G_delta, G_d = pull((Kp * phi, Kg * gap))
    if rod.foundation is not None:
        G_delta = G_delta + jax.grad(lambda de: site_energy(rod, composed_q(de)))(delta)
    q = composed_q(delta)
    F_ex, M_ex = _external(rod, q, scale, Motion(q, r + d, Omega, v, t))
    M = -jax.vmap(lambda de, g: Turn(de).Z(g))(delta, G_delta) + M_ex
    F = -G_d + F_ex
    turn, pos = _free(rod)
    return M * turn[:, None], F * pos[:, None]


def _skew(x):
    r"""$x\times$ by rows, ``(B, 3, 3)``."""
    z = jnp.zeros_like(x[:, 0])
    return jnp.stack(
        [
            jnp.stack([z, -x[:, 2], x[:, 1]], -1),
            jnp.stack([x[:, 2], z, -x[:, 0]], -1),
            jnp.stack([-x[:, 1], x[:, 0], z], -1),
        ],
        1,
    )


def forces_tangent(rod, Q, r, Omega=None, v=None, scale=1.0, t=0.0):
    r""":func:`forces_at` at zero increments ($\delta = d = 0$), the fast path of the explicit
    integrator (:mod:`._rod_verlet`): the forces are first derivatives at $\delta = 0$, where
    $Q\cdot Q(\delta)$ and $Q\cdot(E + \delta\times)$ have the same tangent and
    $Z(0) = Z^T(0) = E$, so the increments enter linearly (no turn-tensor series, no $Z$); equal
    to :func:`forces_at` to rounding (tested)."""

    def strain_of(delta, d):
        return strains(rod, Q + jnp.einsum("bij,bjk->bik", Q, _skew(delta)), r + d, t)

    z = jnp.zeros_like(r)
    (phi, gap), pull = jax.vjp(strain_of, z, z)
    Kp, Kg = jnp.asarray(rod.turn_stiffness), jnp.asarray(rod.gap_stiffness)
    if Omega is not None:
        phi_dot, gap_dot = jax.jvp(strain_of, (z, z), (Omega, v))[1]
        phi = phi + jnp.asarray(rod.turn_damping)[:, None] * phi_dot
        gap = gap + jnp.asarray(rod.gap_damping)[:, None] * gap_dot
    G_delta, G_d = pull((Kp * phi, Kg * gap))
    if rod.foundation is not None:
        grow = jax.grad(lambda de: site_energy(rod, Q + jnp.einsum("bij,bjk->bik", Q, _skew(de))))
        G_delta = G_delta + grow(z)
    F_ex, M_ex = _external(rod, Q, scale, Motion(Q, r, Omega, v, t))
    turn, pos = _free(rod)
    return (M_ex - G_delta) * turn[:, None], (F_ex - G_d) * pos[:, None]


def rates(rod, state: RodState, scale=1.0, t=0.0, damped: bool = True) -> RodState:
    r"""The time derivative of a state: $\dot\theta = Z^T(\theta)\cdot\Omega$ (4.14),
    $\dot r = v$, $A\cdot\dot\Omega = M - \Omega\times A\cdot\Omega$ (4.55), $m\dot v = F$; the
    held coordinates of the base stay; the loads and the rest curvature at time ``t``. The
    forces by :func:`forces_tangent` (those of
    :func:`body_forces` at zero increments, to rounding): a smaller program than through
    $Q(\delta)$ and $Z(\delta)$ at $\delta = 0$, whose diffrax solves compile and run faster
    (benchmarks/bench_rod.py; figures: benchmarks/README.md, History). ``damped=False``
    (static, for a rod known before tracing to have no Kelvin–Voigt damping and no load that
    reads the velocities) leaves the velocities out of the forces: a smaller program."""
    velocities = (state.Omega, state.v) if damped else (None, None)
    M, F = forces_tangent(rod, tensors(state.theta), state.r, *velocities, scale, t)
    A = jnp.asarray(rod.inertia)
    AOm = jnp.einsum("bij,bj->bi", A, state.Omega)
    Omega_dot = solve3(A, M - cross3(state.Omega.T, AOm.T).T)
    v_dot = F / jnp.asarray(rod.mass)[:, None]
    theta_dot = jax.vmap(lambda th, Om: Turn(th).ZT(Om))(state.theta, state.Omega)
    turn, pos = _free(rod)
    return RodState(
        theta_dot * turn[:, None],
        state.v * pos[:, None],
        Omega_dot * turn[:, None],
        v_dot * pos[:, None],
    )


def kinetic_energy(rod, state: RodState):
    r"""$\sum_i \tfrac12\,\Omega_i\cdot A_i\cdot\Omega_i + \tfrac12 m_i v_i^2$."""
    A = jnp.asarray(rod.inertia)
    rot = 0.5 * jnp.einsum("bi,bij,bj->", state.Omega, A, state.Omega)
    return rot + 0.5 * jnp.sum(jnp.asarray(rod.mass) * jnp.sum(state.v**2, axis=-1))


def potential_energy(rod, state: RodState, t=0.0):
    """The couplings' energy (their rest curvature at time ``t``), the foundation's and the
    potential of gravity and dead forces."""
    q = tensors(state.theta)
    U = coupling_energy(rod, q, state.r, t) + site_energy(rod, q)
    return U + _load_potential(rod, state.r)


def energy(rod, state: RodState, t=0.0):
    """Kinetic plus potential energy (at time ``t``): conserved without damping, follower
    loads, dead moments, actuation and friction."""
    return kinetic_energy(rod, state) + potential_energy(rod, state, t)


def kinetic_moment(rod, state: RodState):
    r"""$\sum_i r_i\times m_i v_i + Q(\theta_i)\cdot A_i\cdot\Omega_i$ (4.44) about the origin:
    conserved by a free rod without loads (the couplings are internal)."""
    A = jnp.asarray(rod.inertia)
    spin = rotate(tensors(state.theta), jnp.einsum("bij,bj->bi", A, state.Omega))
    orbital = cross3(state.r.T, (jnp.asarray(rod.mass)[:, None] * state.v).T).T
    return jnp.sum(spin + orbital, axis=0)


# --------------------------------------------------------------------------------------------
# What the analyses need (rbo_jax.mechanics.AbstractMechanics): the balance at rest in the
# increments, and the first-order equations over the free coordinates.
# --------------------------------------------------------------------------------------------


def static_residual(rod, theta, r, x, scale=1.0):
    r"""The moment and force balance of every body at the increments ``x`` (N+1, 6): turns
    $Q(\theta_i)Q(\delta_i)$, positions $r_i + d_i$, loads times ``scale``. On the held
    coordinates of the base their distance from the held values, $d_0 + r_0 - r_{base}$ and
    $\delta_0 + Z^{-T}(\theta_0)(\theta_0 - \theta_{base})$ (zero there; and so the base's
    position and turn are parameters that the implicit derivatives see)."""
    M, F = body_forces(rod, theta, r, x[:, :3], x[:, 3:], scale=scale)
    turn, pos = rod.free_masks()
    fixed_t = jnp.asarray(~turn, x.dtype)[:, None]
    fixed_p = jnp.asarray(~pos, x.dtype)[:, None]
    to_turn = integrating_tensor_inv(theta[0]).T @ (theta[0] - jnp.asarray(rod.base_turn))
    to_pos = r[0] - jnp.asarray(rod.base_position)
    held_t = x[:, :3] + jnp.zeros_like(x[:, :3]).at[0].set(to_turn)
    held_p = x[:, 3:] + jnp.zeros_like(x[:, 3:]).at[0].set(to_pos)
    return jnp.concatenate([M + fixed_t * held_t, F + fixed_p * held_p], axis=1)


def free_index(rod):
    """The bodies whose turns move and those whose positions move (NumPy index arrays)."""
    turn, pos = rod.free_masks()
    return np.flatnonzero(turn), np.flatnonzero(pos)


def free_increments(rod, q):
    """The blocks ``(N+1, 6)`` of the free increments ``q = [delta, d]`` (:func:`first_order`'s
    order), zero on the held coordinates."""
    it, ip = free_index(rod)
    nt = 3 * len(it)
    x = jnp.zeros((rod.n_bodies, 6), q.dtype)
    x = x.at[it, :3].set(q[:nt].reshape(-1, 3))
    return x.at[ip, 3:].set(q[nt:].reshape(-1, 3))


def first_order(rod, theta, r):
    r"""``F(x)``: the first-order system about the configuration ``(theta, r)``, over
    $x = [\delta, d, \Omega, v]$ of the bodies that move (the base's held coordinates left
    out): $\dot\delta = Z^T(\delta)\cdot\Omega$, $\dot d = v$,
    $A\cdot\dot\Omega = M - \Omega\times A\cdot\Omega$ (4.55), $m\,\dot v = F$, the forces
    of :func:`body_forces` (elastic, Kelvin–Voigt, foundation, loads) at the turns
    $Q(\theta_i)Q(\delta_i)$ and positions $r_i + d_i$."""
    it, ip = free_index(rod)
    theta, r = jnp.asarray(theta), jnp.asarray(r)
    nt, npos = 3 * len(it), 3 * len(ip)
    A = jnp.asarray(rod.inertia)
    m = jnp.asarray(rod.mass)

    def F(x):
        delta = jnp.zeros_like(theta).at[it].set(x[:nt].reshape(-1, 3))
        d = jnp.zeros_like(r).at[ip].set(x[nt : nt + npos].reshape(-1, 3))
        Om = jnp.zeros_like(theta).at[it].set(x[nt + npos : 2 * nt + npos].reshape(-1, 3))
        v = jnp.zeros_like(r).at[ip].set(x[2 * nt + npos :].reshape(-1, 3))
        M, Fo = body_forces(rod, theta, r, delta, d, Om, v)
        AOm = jnp.einsum("bij,bj->bi", A, Om)
        Om_dot = jnp.linalg.solve(A, (M - jnp.cross(Om, AOm))[..., None])[..., 0]
        delta_dot = jax.vmap(lambda de, w: Turn(de).ZT(w))(delta, Om)
        v_dot = Fo / m[:, None]
        return jnp.concatenate(
            [delta_dot[it].ravel(), v[ip].ravel(), Om_dot[it].ravel(), v_dot[ip].ravel()]
        )

    return F
