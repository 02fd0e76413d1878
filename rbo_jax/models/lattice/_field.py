r"""Energies, forces and the equations of motion of a lattice, on component-major arrays.

Every function here takes the turn-vectors and angular velocities of all bodies as ``(3, N)``
arrays (component first: each component a contiguous ``(N,)`` array, so that per-body code
``jax.vmap``-ed over the last axis is element-wise code over the bodies).

The coupling energy is evaluated through unit quaternions: $q_i$ of every body once, the
relative turn of an edge $\varphi_{ij}$ from $\bar q_i q_j$ (the quaternion of
$Q^T(\theta_i)\cdot Q(\theta_j)$) by the principal logarithm of
:func:`rbo_jax.kinematics.compose` — exact, with finite derivatives, at $\varphi = 0$. Its
gradient with respect to every $\theta_i$ is reverse-mode automatic differentiation of the sum:
on a grid the neighbours are ``jnp.roll``s (their transposes are rolls back), on an edge list
gathers (their transposes are segment sums).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._elementary import sin_cos
from ...kinematics import (
    Turn,
    log_quaternion,
    matvec3,
    quaternion_of,
    quaternion_product,
    stored,
)
from ..rigid_body import RightForm


def _per_body(fn, *args, in_axes=None):
    """``fn`` over the bodies: ``jax.vmap`` over the last axis of each ``(3, N)`` argument (or
    the leading axis, per ``in_axes``)."""
    axes = tuple(jnp.ndim(a) - 1 for a in args) if in_axes is None else in_axes
    return jax.vmap(fn, in_axes=axes, out_axes=-1)(*args)


def _quaternions(theta):
    """``(w (N,), v (3, N))``: the unit quaternion of every body's turn (kept, not recomputed
    in every consumer: :func:`rbo_jax.kinematics.stored`)."""
    w, v = _per_body(lambda th: quaternion_of(th, sin_cos), theta)
    return stored(w), stored(v)


def _relative(qi, qj):
    """The principal relative turn-vectors ``(3, E)`` of pairs of quaternions (i to j, in i's
    frame): log of conj(q_i)·q_j."""
    (wi, vi), (wj, vj) = qi, qj

    def one(wi, vi, wj, vj):
        return log_quaternion(*quaternion_product((wi, -vi), (wj, vj)))

    return stored(jax.vmap(one, in_axes=(0, 1, 0, 1), out_axes=1)(wi, vi, wj, vj))


def _pairs(lattice, theta):
    """The relative turns of every coupled pair and their weights (1, or 0 for the pairs that a
    free end leaves out of a grid's stencil): ``[(phi (3, M), weight (M,) or None), ...]``, one
    entry per axis of a grid, one for an edge list."""
    w, v = _quaternions(theta)
    if not lattice.is_grid:
        i, j = lattice.edges[:, 0], lattice.edges[:, 1]
        return [(_relative((w[i], v[:, i]), (w[j], v[:, j])), None)]
    shape = lattice.shape
    wg, vg = jnp.reshape(w, shape), jnp.reshape(v, (3,) + shape)
    out = []
    for axis, periodic in enumerate(lattice.periodic):
        wn = jnp.roll(wg, -1, axis=axis)
        vn = jnp.roll(vg, -1, axis=axis + 1)
        phi = _relative(
            (jnp.ravel(wg), jnp.reshape(vg, (3, -1))), (jnp.ravel(wn), jnp.reshape(vn, (3, -1)))
        )
        weight = None
        if not periodic:  # the pair (last, first) along this axis is not coupled
            idx = jnp.arange(shape[axis]).reshape((-1,) + (1,) * (len(shape) - axis - 1))
            weight = jnp.ravel(jnp.broadcast_to(idx < shape[axis] - 1, shape)).astype(phi.dtype)
        out.append((phi, weight))
    return out


def relative_turns(lattice, theta):
    r"""The relative turn-vectors $\varphi_{ij}$ of the coupled pairs: for a grid a list with one
    ``(3, N)`` array per axis (site $i$ to its next neighbour along the axis; the wrapped pair of
    a free end included, with weight 0 in the energy), for an edge list one ``(3, E)`` array."""
    return [phi for phi, _ in _pairs(lattice, theta)]


def coupling_energy(lattice, theta):
    r"""$\sum_{(i,j)} W(\varphi_{ij})$, every coupled pair once."""
    total = jnp.zeros((), theta.dtype)
    for phi, weight in _pairs(lattice, theta):
        Wk = _per_body(lattice.coupling.energy, phi)
        total = total + jnp.sum(Wk if weight is None else Wk * weight)
    return total


def _sites(lattice, fn, *args):
    """``fn(body, *args_i)`` for every site (per-site bodies or one body): ``(..., N)``."""
    axes = (lattice.body_axes(),) + tuple(jnp.ndim(a) - 1 for a in args)
    return jax.vmap(fn, in_axes=axes, out_axes=-1)(lattice.site_bodies(), *args)


def site_energy(lattice, theta):
    r"""$\sum_i U_i(\theta_i) + V_i(\theta_i)$: the foundations and potential loads (4.52)."""
    return jnp.sum(_sites(lattice, lambda b, th: b.potential_energy(th), theta))


def total_energy(lattice, theta, Omega):
    r"""$\sum_i \tfrac12\Omega_i\cdot A_i\cdot\Omega_i + U$: conserved without friction and
    non-potential loads ((4.78) summed over the bodies)."""
    kinetic = jnp.sum(_sites(lattice, lambda b, Om: b.kinetic_energy(Om), Omega))
    return kinetic + site_energy(lattice, theta) + coupling_energy(lattice, theta)


def coupling_moments(lattice, theta):
    r"""The body-frame moments of the couplings on every body, ``(3, N)``: the potential moment
    (4.23) of the relative turn. Body $j$ turned by $\varphi_{ij}$ from body $i$ is a body on a
    foundation of energy $W$ fixed to body $i$: the moment on it is $-Z^T(\varphi)\cdot
    dW/d\varphi$ in body $i$'s frame (4.46), that is $-Z(\varphi)\cdot dW/d\varphi$ in its own
    ($Q^T(\varphi)\cdot Z^T(\varphi) = Z(\varphi)$, (4.13)); body $i$ takes the opposite moment,
    $Z^T(\varphi)\cdot dW/d\varphi$ in its frame (a couple that depends on the relative turn
    only is internal: the total kinetic moment is kept). The same moments as
    $-Z(\theta_i)\cdot\partial U_W/\partial\theta_i$ of the coupling energy (tested), without
    differentiating the quaternion logarithm."""

    def per_pair(phi):
        turn = Turn(phi)
        g = lattice.coupling.gradient(phi)
        return turn.ZT(g), -turn.Z(g)  # on i, on j (each in its own frame)

    total = jnp.zeros_like(theta)
    pairs = _pairs(lattice, theta)
    if not lattice.is_grid:
        on_i, on_j = _per_body(per_pair, pairs[0][0])
        i, j = lattice.edges[:, 0], lattice.edges[:, 1]
        n = theta.shape[1]
        seg = jax.vmap(
            lambda x, idx: jax.ops.segment_sum(x, idx, num_segments=n), in_axes=(0, None)
        )
        return seg(on_i, i) + seg(on_j, j)
    shape = lattice.shape
    for axis, (phi, weight) in enumerate(pairs):
        on_i, on_j = _per_body(per_pair, phi)
        if weight is not None:
            on_i, on_j = on_i * weight[None, :], on_j * weight[None, :]
        # the pair (site, next along the axis): on_j acts on the next site
        on_j = jnp.roll(jnp.reshape(on_j, (3,) + shape), 1, axis=axis + 1)
        total = total + on_i + jnp.reshape(on_j, (3, -1))
    return total


def chain_moments(lattice, theta, weight):
    r"""The coupling moments of an **open** chain segment of $E$ bodies, ``(3, E)``: the pair
    $(p, p+1)$ coupled with ``weight[p]`` (0 or 1; the entry of the last body is its wrap pair,
    given weight 0 by the caller). The arithmetic of :func:`coupling_moments` on a chain (the
    moment on body $p$ is $0 + w_p\,\text{on}_i(\varphi_{p,p+1}) + w_{p-1}\,\text{on}_j(
    \varphi_{p-1,p})$): on the inner bodies of a segment cut from a chain (:mod:`._halo`) the
    values are the whole chain's bit for bit (a weight of 1 and the added zero are exact)."""

    def per_pair(phi):
        turn = Turn(phi)
        g = lattice.coupling.gradient(phi)
        return turn.ZT(g), -turn.Z(g)

    w, v = _quaternions(theta)
    phi = _relative((w, v), (jnp.roll(w, -1), jnp.roll(v, -1, axis=1)))
    on_i, on_j = _per_body(per_pair, phi)
    on_i, on_j = on_i * weight[None, :], on_j * weight[None, :]
    return jnp.zeros_like(theta) + on_i + jnp.roll(on_j, 1, axis=1)


def energy_gradient(lattice, theta):
    r"""$\partial U/\partial\theta_i$ for every body, ``(3, N)``: each foundation's own gradient
    (closed forms where it has them) plus the reverse-mode gradient of the coupling energy."""
    own = _sites(lattice, lambda b, th: b.foundation.gradient(th), theta)
    return own + jax.grad(coupling_energy, argnums=1)(lattice, theta)


def right_forms(lattice, throw: bool = False) -> RightForm:
    """Every body's :class:`rbo_jax.RightForm` ($A^{-1}$ computed once): per-site leaves with a
    leading axis N, or one for all."""
    if not lattice.per_site:
        return lattice.body.right_form(throw)
    return jax.vmap(lambda b: b.right_form(throw), in_axes=(lattice.body_axes(),))(
        lattice.site_bodies()
    )


def rates(lattice, forms: RightForm, t, theta, Omega, moments=None, load_scale=None):
    r"""$(\dot\theta, \dot\Omega)$ of every body, ``(3, N)`` each: (4.55)–(4.56) with each
    foundation's gradient and the couplings' moments (:func:`coupling_moments`, or the given
    ``moments``), which together are $-Z(\theta_i)\cdot\partial U/\partial\theta_i$ of the
    total energy."""
    if moments is None:
        moments = coupling_moments(lattice, theta)
    axes = jax.tree_util.tree_map(
        lambda x: 0 if lattice.per_site and eqx.is_array(x) else None, forms
    )

    def one(f, th, Om, m):
        return f.rates(t, th, Om, f.model.foundation.gradient(th), m, load_scale)

    return jax.vmap(one, in_axes=(axes, 1, 1, 1), out_axes=(1, 1))(forms, theta, Omega, moments)


def body_moments(lattice, theta):
    r"""The body-frame moments of the foundations and couplings on every body, ``(3, N)``:
    $-Z(\theta_i)\cdot dU_i/d\theta_i$ plus :func:`coupling_moments` (no loads)."""
    own = _sites(lattice, lambda b, th: -Turn(th).Z(b.foundation.gradient(th)), theta)
    return own + coupling_moments(lattice, theta)


def kinetic_moment(lattice, theta, Omega):
    r"""The total kinetic moment $\sum_i Q(\theta_i)\cdot A_i\cdot\Omega_i$ (4.44), conserved
    when no foundation and no load acts (Kelvin's medium: the couplings are internal)."""

    def one(b, th, Om):
        return Turn(th).rotate(matvec3(b.inertia, Om))

    return jnp.sum(_sites(lattice, one, theta, Omega), axis=-1)
