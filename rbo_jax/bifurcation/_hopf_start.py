r"""The start of a flutter solve (:mod:`._hopf_system`) from the eigenvalues at the guess.

**Start.** The equilibrium at the guess (:func:`rbo_jax.solve_equilibrium`'s Newton method;
its configuration is the chart of the solve), then the eigenvalues of $J$ there: for
``"hopf"`` the pair nearest ``frequency`` if given, else the pair with the largest real part
among those that move with the parameter: the eigenvalues of $J$ at the parameter moved by
$10^{-4}\max(|\alpha_0|, 1)$ (at the same configuration) are matched to the first ones, and a
pair whose real part stays on the imaginary axis in both (:func:`rbo_jax.classify`'s tolerance:
a stiff mode without damping, which never crosses) is not followed; for ``"collision"`` the
two lowest distinct frequencies $\lambda_1$, $\lambda_2$ of the upper half plane, with
eigenvectors scaled to $C^Hv_j = e_1$, then $i\omega = (\lambda_1 + \lambda_2)/2$,
$v = (v_1 + v_2)/2$, $u = (v_1 - v_2)/(\lambda_1 - \lambda_2)$ (the chain up to
$O((\lambda_1 - \lambda_2)^2)$).
Eigenvalues within ``cluster`` × $|\lambda|$ of each other are one eigenvalue.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..stability import unstable_roots
from ._hopf_system import Layout, Spec

__all__ = ["SHIFT", "start"]

SHIFT = 1e-4  # the move of the parameter, relative, at which the followed pair is told apart


def _oscillatory(p):
    return jnp.imag(p) > 1e-9 * jnp.max(jnp.abs(p))


def _cluster(p, V, lam, cluster, k_max):
    r"""The eigenvectors of the eigenvalues within ``cluster`` × $|\\lambda|$ of ``lam`` (the
    first ``k_max`` of them, in index order, then zero columns) and how many there are."""
    member = jnp.abs(p - lam) <= cluster * jnp.abs(lam)
    columns = jnp.argsort(jnp.where(member, 0, 1))[:k_max]  # stable: members first
    return V[:, columns], jnp.sum(member)


def _orthonormal(W, used):
    """An orthonormal basis of the ``used`` columns of ``W`` (QR), zero in the others."""
    Q, _ = jnp.linalg.qr(jnp.where(used, W, 0))
    return jnp.where(used, Q, 0)


def _lowest_two(p, cluster):
    """Indices of one eigenvalue of each of the two lowest distinct frequencies (imaginary
    parts > 0), and whether the second exists."""
    osc = _oscillatory(p)
    order = jnp.argsort(jnp.where(osc, jnp.imag(p), jnp.inf))
    first = order[0]
    distinct = osc[order] & (jnp.abs(p[order] - p[first]) > cluster * jnp.abs(p[first]))
    return first, order[jnp.argmax(distinct)], jnp.any(distinct)


def _off_axis(p):
    return unstable_roots(p) | unstable_roots(-p)


def _start_hopf(spec: Spec, p, V, shifted=None, frequency=None):
    """``(omega, v, C, found, count)`` of the followed pair (module docstring); ``shifted``:
    the eigenvalues at the moved parameter; ``frequency``: the given one (``by_frequency``)."""
    osc = _oscillatory(p)
    if spec.by_frequency:
        index = jnp.argmin(jnp.where(osc, jnp.abs(jnp.imag(p) - frequency), jnp.inf))
    else:
        moves = osc
        if shifted is not None:  # the nearest of the moved eigenvalues to each
            nearest = shifted[jnp.argmin(jnp.abs(p[:, None] - shifted[None, :]), axis=1)]
            moves = osc & (_off_axis(p) | _off_axis(nearest))
        score = jnp.where(jnp.any(moves), jnp.where(moves, jnp.real(p), -jnp.inf),
                          jnp.where(osc, jnp.real(p), -jnp.inf))  # fmt: skip
        index = jnp.argmax(score)
    lam = p[index]
    W, count = _cluster(p, V, lam, spec.cluster, spec.multiplicity)
    C = _orthonormal(W, jnp.arange(spec.multiplicity) < count)
    return jnp.imag(lam), C[:, 0], None, C, jnp.any(osc), count


def _start_collision(spec: Spec, p, V):
    """``(omega, v, u, C, found, count)`` of the Jordan chain (module docstring)."""
    k_max = spec.multiplicity
    first, second, two = _lowest_two(p, spec.cluster)
    lam1, lam2 = p[first], p[second]
    W1, n1 = _cluster(p, V, lam1, spec.cluster, k_max)
    W2, n2 = _cluster(p, V, lam2, spec.cluster, k_max)
    k = jnp.minimum(n1, n2)
    used = jnp.arange(k_max) < k
    W1, W2 = jnp.where(used, W1, 0), jnp.where(used, W2, 0)
    C = _orthonormal(W1, used)
    e1 = jnp.zeros(k_max, C.dtype).at[0].set(1.0)
    square = used[:, None] & used[None, :]

    def normalised(W):  # the combination of W's columns with C^H v = e1
        G = jnp.where(square, jnp.conj(C).T @ W, jnp.eye(k_max, dtype=C.dtype))
        return W @ jnp.linalg.solve(G, e1)

    v1, v2 = normalised(W1), normalised(W2)
    v, chain = 0.5 * (v1 + v2), (v1 - v2) / (lam1 - lam2)
    return 0.5 * jnp.imag(lam1 + lam2), v, chain, C, two, k


def start(spec: Spec, layout: Layout, J, alpha, shifted=None, frequency=None):
    """``(u0, C, found, fits)`` from the eigenvalues of ``J`` at the equilibrium of the
    guess (``shifted``: those at the moved parameter, for a Hopf pair; ``frequency``: the one
    to follow, for a spec ``by_frequency``)."""
    p, V = jnp.linalg.eig(J)
    finite = jnp.all(jnp.isfinite(p))
    p, V = jnp.where(finite, p, 0), jnp.where(finite, V, 0)
    if spec.kind == "hopf":
        omega, v, chain, C, found, count = _start_hopf(spec, p, V, shifted, frequency)
    else:
        omega, v, chain, C, found, count = _start_collision(spec, p, V)
    q = jnp.zeros(layout.m, J.dtype)
    u = layout.pack(q, alpha, omega, v, chain)
    return u, C, found & finite, count <= spec.multiplicity
