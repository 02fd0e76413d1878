r"""The flutter system of a rod (:mod:`._rod_hopf`): the matrix $A$ of the linearisation at
the equilibrium and its derivatives, the residual and the Jacobian of the Hopf and collision
systems, the least-squares Newton step, and the start from the eigenvalues at the guess (all
traceable: they run in the solve's ``lax.while_loop``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ._rod import Rod, RodState
from ._rod_dynamics import _free_index, linearize
from ._rod_statics import solve_equilibrium


class Static(NamedTuple):
    """What the compiled pieces are specialised to (hashable)."""

    model_fn: Callable
    parameter: str
    kind: str
    steps: int


class Options(NamedTuple):
    """The solver's settings (static: Python numbers)."""

    rtol: float
    atol: float
    max_steps: int
    cluster: float
    frequency: float | None
    multiplicity: int


# --------------------------------------------------------------------------------------------
# The system.
# --------------------------------------------------------------------------------------------


def _rod_at(static: Static, P, others) -> Rod:
    rod = static.model_fn(**{**others, static.parameter: P})
    if not isinstance(rod, Rod):
        raise TypeError(f"model_fn must return a Rod here, got {type(rod).__name__}.")
    return rod


def _sizes(static: Static, guess, others):
    """``(m, n_bodies)``: the order of $A$ and the number of bodies (static)."""
    rod = _rod_at(static, guess, others)
    it, ip = _free_index(rod)
    return 6 * (len(it) + len(ip)), rod.n_bodies


def _matrices(static: Static, P, others, count: int, scale, exact: bool = False):
    r"""$A$ at the equilibrium $x$ of $q = (P, p)$ (the load and the flattened ``others``),
    its derivatives $\partial_jA$ in the first ``count`` entries of $q$ (``(count, m, m)``),
    whether the equilibrium was found (and $A$ is finite), and $x$.

    $\partial_jA$ is the central difference of the linearisation along the equilibrium's
    tangent, $[A(q + he_j, x + h\,\partial_jx) - A(q - he_j, x - h\,\partial_jx)]/2h$, with
    $\partial_jx$ by forward mode (the implicit function theorem of :mod:`._rod_statics`) and
    $h = \epsilon^{1/3}|q_j|$ (``scale`` for a zero load, 1 for a zero constant): second order
    in $h$, $\sim\epsilon^{2/3}$ relative ($10^{-10}$ in float64) for the smooth dependence
    on the load and the constants. One equilibrium and one linearisation traced (vmapped over
    the $2\,$``count``$ + 1$ points): forward mode through the linearisation instead (a second
    derivative of the forces) took 2-3 times as long to compile (:mod:`._rod_hopf`). With
    ``exact``, that forward mode all the same (for the implicit derivatives, where a difference
    loses the soft modes to the rounding of the stiff rows)."""
    flat, unravel = ravel_pytree(others)
    q = jnp.concatenate([P[None], flat.astype(P.dtype)])

    def equilibrium(q):
        sol = solve_equilibrium(_rod_at(static, q[0], unravel(q[1:])), steps=static.steps)
        return (sol.state.theta, sol.state.r), (sol.ok, sol.state)

    E = jnp.eye(q.size, dtype=q.dtype)[:count]

    def along(e):
        return jax.jvp(equilibrium, (q,), (e,), has_aux=True)

    if count == 1:  # no batching of the equilibrium's loops to trace
        (theta, r), (d_theta, d_r), (ok, state) = along(E[0])
        d_theta, d_r = d_theta[None], d_r[None]
    else:
        (theta, r), (d_theta, d_r), (ok, state) = jax.vmap(along, out_axes=(None, 0, None))(E)

    def matrix(dq, dth, dr):
        rod = _rod_at(static, (q + dq)[0], unravel((q + dq)[1:]))
        return linearize(rod, RodState.at_rest(theta + dth, r + dr))

    if exact:  # forward mode through the linearisation along the tangents
        zero = (jnp.zeros_like(q), jnp.zeros_like(theta), jnp.zeros_like(r))

        def derivative(e, dth, dr):
            return jax.jvp(matrix, zero, (e, dth, dr))

        A, dA = jax.vmap(derivative, out_axes=(None, 0))(E, d_theta, d_r)
        return A, dA, ok & jnp.all(jnp.isfinite(A)), state

    fallback = jnp.ones_like(q).at[0].set(scale)
    h = (jnp.finfo(q.dtype).eps ** (1 / 3) * jnp.where(q != 0, jnp.abs(q), fallback))[:count]

    def points(x, d):  # x, then x + h d_j, then x - h d_j
        step = h.reshape((-1,) + (1,) * (d.ndim - 1)) * d
        return jnp.concatenate([x[None], x[None] + step, x[None] - step])

    A = jax.vmap(matrix)(points(jnp.zeros_like(q), E), points(jnp.zeros_like(theta), d_theta),
                         points(jnp.zeros_like(r), d_r))  # fmt: skip
    ok = ok & jnp.all(jnp.isfinite(A))
    dA = (A[1 : count + 1] - A[count + 1 :]) / (2 * h[:, None, None])
    return A[0], dA, ok, state


def _real(M):
    """The real matrix of the complex-linear map ``M`` on ``[Re z, Im z]``."""
    return jnp.block([[M.real, -M.imag], [M.imag, M.real]])


def _times_i(z):
    """$i z$ (no implicit promotion of a real ``z``)."""
    return jax.lax.complex(-jnp.imag(z), jnp.real(z))


def _split(z):
    return jnp.concatenate([z.real, z.imag])


def _unknowns(kind: str, y, m: int):
    """``(v, u, omega, P)`` from the real vector ``y`` (``u`` is ``None`` for Hopf)."""
    v = jax.lax.complex(y[:m], y[m : 2 * m])
    u = jax.lax.complex(y[2 * m : 3 * m], y[3 * m : 4 * m]) if kind == "collision" else None
    return v, u, y[-2], y[-1]


def _residual_of(kind, A, y, C):
    """The residual $F$ (real) of the module docstring's system at ``A``."""
    m = A.shape[0]
    v, u, omega, _ = _unknowns(kind, y, m)
    M = A.astype(v.dtype) - _times_i(omega) * jnp.eye(m, dtype=v.dtype)
    e1 = jnp.zeros(C.shape[1], v.dtype).at[0].set(1.0)
    if kind == "hopf":
        return jnp.concatenate([_split(M @ v), _split(C.conj().T @ v - e1)])
    return jnp.concatenate(
        [_split(M @ v), _split(M @ u - v), _split(C.conj().T @ v - e1), _split(C.conj().T @ u)]
    )


def _jacobian_of(kind, A, A_P, y, C):
    """The Jacobian of :func:`_residual_of` in ``y`` (columns: ``v``, [``u``], omega, P),
    real, with $\\partial_PA$ = ``A_P``."""
    m = A.shape[0]
    v, u, omega, _ = _unknowns(kind, y, m)
    M = A.astype(v.dtype) - _times_i(omega) * jnp.eye(m, dtype=v.dtype)
    Ch = C.conj().T
    dv_P = A_P.astype(v.dtype) @ v
    if kind == "hopf":
        top = jnp.concatenate([_real(M), _split(-_times_i(v))[:, None], _split(dv_P)[:, None]], 1)
        bottom = jnp.concatenate([_real(Ch), jnp.zeros((2 * Ch.shape[0], 2), A.dtype)], 1)
        return jnp.concatenate([top, bottom], 0)
    du_P = A_P.astype(v.dtype) @ u
    Z, E = jnp.zeros_like(M), jnp.eye(m, dtype=v.dtype)
    Zc, zk = jnp.zeros_like(Ch), jnp.zeros((2 * Ch.shape[0], 2), A.dtype)
    rows = [
        [_real(M), _real(Z), _split(-_times_i(v))[:, None], _split(dv_P)[:, None]],
        [_real(-E), _real(M), _split(-_times_i(u))[:, None], _split(du_P)[:, None]],
        [_real(Ch), _real(Zc), zk],
        [_real(Zc), _real(Ch), zk],
    ]
    return jnp.concatenate([jnp.concatenate(r, 1) for r in rows], 0)


def _equilibrated(J):
    """The row norms of ``J`` (1 for a zero row: the normalisation of an unused column of
    ``C``)."""
    scale = jnp.linalg.norm(J, axis=1)
    return jnp.where(scale > 0, scale, 1.0)


def _newton_step(kind, A, A_P, y, C):
    """The least-squares Newton step at ``y`` (rows equilibrated, QR) and the residual's max
    norm."""
    F = _residual_of(kind, A, y, C)
    J = _jacobian_of(kind, A, A_P, y, C)
    scale = _equilibrated(J)
    Q, R = jnp.linalg.qr(J / scale[:, None])
    dy = jax.scipy.linalg.solve_triangular(R, -(Q.T @ (F / scale)))
    return dy, jnp.max(jnp.abs(F / scale))


# --------------------------------------------------------------------------------------------
# The start: from the eigenvalues at the guess.
# --------------------------------------------------------------------------------------------


def _oscillatory(p):
    return p.imag > 1e-9 * jnp.max(jnp.abs(p))


def _lowest_two(p, cluster):
    """Indices of one eigenvalue of each of the two lowest distinct frequencies (imaginary
    parts > 0), and whether each exists."""
    osc = _oscillatory(p)
    order = jnp.argsort(jnp.where(osc, p.imag, jnp.inf))
    first = order[0]
    distinct = osc[order] & (jnp.abs(p[order] - p[first]) > cluster * jnp.abs(p[first]))
    return first, order[jnp.argmax(distinct)], osc[first], jnp.any(distinct)


def _cluster(p, V, lam, cluster, k_max):
    """The eigenvectors of the eigenvalues within ``cluster`` × $|\\lambda|$ of ``lam`` (the
    first ``k_max`` of them, in index order, then zero columns) and how many there are."""
    member = jnp.abs(p - lam) <= cluster * jnp.maximum(jnp.abs(lam), 1e-300)
    columns = jnp.argsort(jnp.where(member, 0, 1))[:k_max]  # stable: members first
    return V[:, columns], jnp.sum(member)


def _orthonormal(W, used):
    """An orthonormal basis of the ``used`` columns of ``W`` (QR), zero in the others."""
    Q, _ = jnp.linalg.qr(jnp.where(used, W, 0))
    return jnp.where(used, Q, 0)


def _start_hopf(p, V, P0, cluster, k_max, frequency=None):
    """``(y0, C, found, fits)``: the pair nearest ``frequency`` if given, else of the two lowest
    frequencies the one with the larger real part (a rod's fast shear, stretch, twist and hinge
    modes may be undamped, their real parts zero: they are not followed). ``found`` is false
    without an oscillatory pair, ``fits`` where its multiplicity exceeds ``k_max``."""
    osc = _oscillatory(p)
    if frequency is not None:
        index = jnp.argmin(jnp.where(osc, jnp.abs(p.imag - frequency), jnp.inf))
    else:
        first, second, _, two = _lowest_two(p, cluster)
        index = jnp.where(two & (p[second].real > p[first].real), second, first)
    lam = p[index]
    W, count = _cluster(p, V, lam, cluster, k_max)
    C = _orthonormal(W, jnp.arange(k_max) < count)
    v = C[:, 0]
    y = jnp.concatenate([v.real, v.imag, jnp.stack([lam.imag, P0])])
    return y, C, jnp.any(osc), count <= k_max


def _start_collision(p, V, P0, cluster, k_max):
    """``(y0, C, found, fits)`` of the Jordan chain (module docstring); ``found`` is false
    without two distinct oscillatory eigenvalues, ``fits`` where their common multiplicity
    exceeds ``k_max``."""
    first, second, _, two = _lowest_two(p, cluster)
    lam1, lam2 = p[first], p[second]
    W1, n1 = _cluster(p, V, lam1, cluster, k_max)
    W2, n2 = _cluster(p, V, lam2, cluster, k_max)
    k = jnp.minimum(n1, n2)
    used = jnp.arange(k_max) < k
    W1, W2 = jnp.where(used, W1, 0), jnp.where(used, W2, 0)
    C = _orthonormal(W1, used)
    e1 = jnp.zeros(k_max, C.dtype).at[0].set(1.0)
    square = used[:, None] & used[None, :]

    def normalised(W):  # the combination of W's columns with C^H v = e1
        G = jnp.where(square, C.conj().T @ W, jnp.eye(k_max, dtype=C.dtype))
        return W @ jnp.linalg.solve(G, e1)

    v1, v2 = normalised(W1), normalised(W2)
    v, u = 0.5 * (v1 + v2), (v1 - v2) / (lam1 - lam2)
    omega = 0.5 * (lam1 + lam2).imag
    y = jnp.concatenate([v.real, v.imag, u.real, u.imag, jnp.stack([omega, P0])])
    return y, C, two, k <= k_max


def _start(static: Static, options: Options, A, P0):
    """``(y0, C, found, fits)`` from the eigenvalues and eigenvectors of ``A`` at the guess."""
    p, V = jnp.linalg.eig(A)
    finite = jnp.all(jnp.isfinite(p))
    p, V = jnp.where(finite, p, 0), jnp.where(finite, V, 0)
    k = options.multiplicity
    if static.kind == "hopf":
        y, C, found, fits = _start_hopf(p, V, P0, options.cluster, k, options.frequency)
    else:
        y, C, found, fits = _start_collision(p, V, P0, options.cluster, k)
    return y, C, found & finite, fits
