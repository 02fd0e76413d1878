r"""A structure-preserving integrator for conservative lattices: a Lie-group splitting.

The lattice without loads is a Hamiltonian system on $(T^*SO(3))^N$ with
$H = \sum_i \tfrac12\,\Pi_i\cdot A_i^{-1}\cdot\Pi_i + U(\theta_1, \dots, \theta_N)$,
$\Pi_i = A_i\cdot\Omega_i$ the body-frame kinetic moment (4.44). It splits into flows that are
solved exactly:

- the **kick** of the potential, turns fixed: $\dot\Pi_i = -Z(\theta_i)\cdot\partial U/\partial
  \theta_i$ — the elastic part of (4.55) (foundations and couplings,
  :func:`._field.body_moments`), constant over the substep;
- the **free rotations** about the principal axes $d_k$ of $A_i$ (eigenvalues $a_k$), one
  kinetic term $T_k = (d_k\cdot\Pi)^2/(2a_k)$ at a time: $\Omega = (d_k\cdot\Pi/a_k)\,d_k$ is
  constant, the body turns by $\alpha = \tau\,d_k\cdot\Pi/a_k$ about $d_k$,
  $P \to P\cdot Q(\alpha d_k)$, and $\Pi \to Q(-\alpha d_k)\cdot\Pi$ (the $\Pi\times\Omega$ of
  (4.55)).

One step of size $h$ is the symmetric (Strang) composition
$K_{h/2}\,T_{1,h/2}\,T_{2,h/2}\,T_{3,h}\,T_{2,h/2}\,T_{1,h/2}\,K_{h/2}$: second order,
symplectic and time-reversible, so the energy error stays bounded (it oscillates, it does not
drift) over any number of steps; each flow conserves the total kinetic moment where $U$ is
invariant under a common rotation (Kelvin's medium). The turn $P_i$ is kept as a unit
quaternion; the turn-vector is its principal logarithm continued from the previous step (the
branch $\theta + 2\pi m\,\theta/|\theta|$ nearest to it, so plane rotations go on past
$|\theta| = 2\pi$), re-centred off the plane near a singular sphere as in
:mod:`._integrate`. One energy gradient per step (the last kick's is the next step's first).

Loads (friction, follower and dead moments) make the system non-Hamiltonian or need their own
flows: a lattice with loads is refused here; use the DOP853 or diffrax paths.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import lax

from ..kinematics import (
    cross3,
    dot3,
    log_quaternion,
    matvec3,
    quaternion_of,
    quaternion_product,
)
from ..models.lattice import Lattice, body_moments
from ..models.rigid_body import inverse3
from ._recentre import recentre

__all__ = ["split"]

TWO_PI = 2.0 * math.pi


def _body_values(lattice: Lattice, fn):
    """``fn(body)`` for one body, or for every site (outputs with the site axis last)."""
    if not lattice.per_site:
        return fn(lattice.body)
    return jax.vmap(fn, in_axes=(lattice.body_axes(),), out_axes=-1)(lattice.site_bodies())


def _continue(theta_p, theta_old):
    r"""The branch $\theta_p + 2\pi m\,\hat n$ of the principal turn-vector $\theta_p$ nearest
    to ``theta_old`` (one body; along the axis of ``theta_old`` where $\theta_p = 0$)."""
    n2 = dot3(theta_p, theta_p)
    tiny = n2 < 1e-24
    o2 = dot3(theta_old, theta_old)
    axis = jnp.where(
        tiny,
        theta_old / jnp.sqrt(jnp.where(o2 > 0, o2, 1.0)),
        theta_p / jnp.sqrt(jnp.where(tiny, 1.0, n2)),
    )
    along = jnp.sqrt(jnp.where(tiny, 0.0, n2))
    m = jnp.round((dot3(axis, theta_old) - along) / TWO_PI)
    return theta_p + (TWO_PI * m) * axis


def _rotate(v, axis, angle):
    """Q(angle·axis)·v for a unit axis (Rodrigues' formula (4.3))."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return c * v + s * cross3(axis, v) + (1.0 - c) * dot3(axis, v) * axis


def split(lattice: Lattice, theta0, Omega0, ts, dt: float, recenter: bool, recenter_margin: float):
    """Samples at ``ts`` from ``(theta0, Omega0)`` (``(3, N)`` each) with steps of at most
    ``dt`` (every interval between samples in equal steps): ``(samples (T, N, 6), turns (T, N),
    steps)``."""
    a, d = _body_values(lattice, lambda b: jnp.linalg.eigh(b.inertia))
    inertia = _body_values(lattice, lambda b: b.inertia)
    inverse = _body_values(lattice, lambda b: inverse3(b.inertia))
    per_site = lattice.per_site

    def bodies(fn, body_args, state_args):
        """``fn(*body_args, *state_args)`` for every body (site axis last everywhere)."""
        b_axes = tuple(jnp.ndim(x) - 1 if per_site else None for x in body_args)
        s_axes = tuple(jnp.ndim(x) - 1 for x in state_args)
        return jax.vmap(fn, in_axes=b_axes + s_axes, out_axes=-1)(*body_args, *state_args)

    def torque(theta):
        return body_moments(lattice, theta)

    def omega(Pi):
        return bodies(matvec3, (inverse,), (Pi,))

    def free(k, tau, q, Pi):
        """The exact flow of T_k over tau: the turn about the principal axis d_k."""

        def one(a_, d_, w, v, P):
            axis = d_[:, k]
            alpha = tau * dot3(axis, P) / a_[k]
            half = 0.5 * alpha
            w, v = quaternion_product((w, v), (jnp.cos(half), jnp.sin(half) * axis))
            return w, v, _rotate(P, axis, -alpha)

        w, v, Pi = bodies(one, (a, d), (q[0], q[1], Pi))
        return (w, v), Pi

    def step(carry, h):
        q, theta, Pi, tau, turns = carry
        Pi = Pi + (0.5 * h) * tau
        for k, f in ((0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5)):
            q, Pi = free(k, f * h, q, Pi)
        theta_p = bodies(log_quaternion, (), (q[0], q[1]))
        theta = bodies(_continue, (), (theta_p, theta))
        if recenter:
            theta, k = recentre(theta, omega(Pi), recenter_margin)
            turns = turns + k
        tau = torque(theta)
        return (q, theta, Pi + (0.5 * h) * tau, tau, turns)

    Pi0 = bodies(matvec3, (inertia,), (Omega0,))
    q0 = bodies(quaternion_of, (), (theta0,))
    turns0 = jnp.zeros(theta0.shape[1], jnp.int32)
    carry0 = (q0, theta0, Pi0, torque(theta0), turns0)

    def interval(carry, t_pair):
        t_a, t_b = t_pair
        span = t_b - t_a
        n = jnp.maximum(jnp.ceil(span / dt - 1e-9), 1.0)
        h = span / n
        carry = lax.fori_loop(0, n.astype(jnp.int32), lambda i, c: step(c, h), carry)
        _, theta, Pi, _, turns = carry
        return carry, (jnp.concatenate([theta, omega(Pi)]).T, turns, n.astype(jnp.int32))

    first = jnp.concatenate([theta0, Omega0]).T
    _, (samples, turns, steps) = lax.scan(interval, carry0, (ts[:-1], ts[1:]))
    samples = jnp.concatenate([first[None], samples])
    turns = jnp.concatenate([turns0[None], turns])
    return samples, turns, jnp.sum(steps)
