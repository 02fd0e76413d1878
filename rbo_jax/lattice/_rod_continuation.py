r"""Pseudo-arclength continuation of rod equilibria in a load, through limit points.

The equilibria $R(x, \lambda) = 0$ of ``rod_fn(λ)`` (the balance of forces and moments of
every body, :mod:`._rod_statics`) form a curve in the unknowns $u = (x, \lambda)$, $x$ the turn
increments $\delta_i$ and displacements $d_i$ of the bodies. Keller's pseudo-arclength method
follows it as :func:`rbo_jax.continue_equilibria` follows a single body's: from a point $u_k$
with unit tangent $\tau_k$, the predictor $u_k + s\,\tau_k$ is corrected by Newton's method on

$$
R(x, \lambda) = 0, \qquad \langle \tau_k, u - u_k \rangle = s,
$$

so a limit point (fold) of $\lambda$, where $J = \partial R/\partial x$ is singular, is passed.
The inner product weighs a turn by 1, a displacement by $1/\ell$ ($\ell$ the rod's size) and the
load by $1/\lambda_s$ (``load_scale``). Each Newton step solves the bordered system

$$
\begin{pmatrix} J & R_\lambda \\ \tau_x^T W & \tau_\lambda w_\lambda \end{pmatrix}
\begin{pmatrix} \delta x \\ \delta\lambda \end{pmatrix} = -\begin{pmatrix} R \\ c \end{pmatrix}
$$

by two block-tridiagonal solves with the rod's Jacobian (:mod:`._banded`, O(N)):
$J a = -R$ and $J b = R_\lambda$, then $\delta\lambda = (-c - \langle\tau_x, a\rangle)/
(\tau_\lambda w_\lambda - \langle\tau_x, b\rangle)$, $\delta x = a - \delta\lambda\,b$ (Keller's
bordering algorithm). The same two solves give the new tangent, $t = (-b, 1)\,t_\lambda$
oriented along $\tau_k$, and the sign of the bordered determinant
$\det J\,(\tau_\lambda w_\lambda - \langle\tau_x, b\rangle)$ (the branch-point test), $\det J$
from the pivots of the block elimination. Turns are updated by composition (4.5), as in the
static solve. Folds, branch points and changes of the number of unstable oscillatory modes are
detected and folds located as in :func:`rbo_jax.continue_equilibria`
(:mod:`rbo_jax.bifurcation._equilibria`); stability at every point from the eigenvalues of
:func:`rbo_jax.lattice.linearize`.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._programs import jit
from ..bifurcation._equilibria import _detect, _refine_folds
from ..kinematics import turn_tensor
from ._banded import _factor, tridiagonal_jacobian, tridiagonal_solve
from ._rod import Rod, RodState
from ._rod_dynamics import linearize
from ._rod_statics import _apply, _residual, solve_equilibrium

__all__ = ["RodBranch", "continue_equilibrium"]


class RodBranch(eqx.Module):
    r"""A branch of rod equilibria from :func:`continue_equilibrium`, over its points in the
    order of the arclength: ``loads`` (P,), ``states`` (a :class:`RodState` at rest with a
    leading axis of P), ``eigenvalues`` (P, 12N: :func:`rbo_jax.lattice.spectrum` at every point;
    empty with ``spectra=False``), ``special`` (tuples ``(kind, load, index)``: ``"fold"`` (a
    limit point of the load, located by the parabola through three points), ``"branch_point"``
    or ``"hopf"``, ``index`` the point before it) and ``stop_reason``."""

    loads: np.ndarray
    states: RodState
    eigenvalues: np.ndarray
    special: tuple = eqx.field(static=True)
    stop_reason: str = eqx.field(static=True)

    @property
    def tip(self):
        """The tip positions, ``(P, 3)``."""
        return self.states.r[:, -1, :]

    @property
    def spectral_abscissa(self):
        """``max Re p`` at every point, ``(P,)`` (NaN without spectra)."""
        if self.eigenvalues.shape[-1] == 0:
            return np.full(self.loads.shape, np.nan)
        return np.max(self.eigenvalues.real, axis=1)

    @property
    def stable(self):
        r"""Every $\mathrm{Re}\,p < 0$, to $10^{-9}$ of the largest $|p|$ (Lyapunov's first
        method; a conservative rod without damping sits on the border: see ``neutral``)."""
        scale = np.maximum(np.max(np.abs(self.eigenvalues), axis=1), 1e-300)
        return self.spectral_abscissa < -1e-9 * scale

    @property
    def neutral(self):
        r"""No eigenvalue with $\mathrm{Re}\,p > 10^{-9}\max|p|$: stable in the linear sense
        of an undamped conservative rod (its spectrum lies on the imaginary axis)."""
        scale = np.maximum(np.max(np.abs(self.eigenvalues), axis=1), 1e-300)
        return self.spectral_abscissa <= 1e-9 * scale

    @property
    def folds(self):
        """The loads of the folds (limit points), in the order met."""
        return np.array([s[1] for s in self.special if s[0] == "fold"], dtype=float)


def _inner(tx, tl, x, lam, w, wl):
    return jnp.sum(tx * x * w**2) + tl * lam * wl**2


def _linear_parts(rod_fn, theta, r, lam):
    """``R``, the blocks of ``J`` and ``R_lambda`` at the point ``(theta, r, lam)``."""
    x0 = jnp.zeros(theta.shape[:-1] + (6,), theta.dtype)
    rod = rod_fn(lam)
    fn = lambda x: _residual(rod, theta, r, x, 1.0)  # noqa: E731
    R = fn(x0)
    blocks = tridiagonal_jacobian(fn, x0)
    one = jnp.ones_like(lam)
    _, R_lam = jax.jvp(lambda q: _residual(rod_fn(q), theta, r, x0, 1.0), (lam,), (one,))
    return R, blocks, R_lam


def _bordered(blocks, R, R_lam):
    """``a = -J^{-1} R``, ``b = J^{-1} R_lambda`` (one factorisation, two right-hand sides) and
    the sign of ``det J`` from the pivots of the block elimination."""
    a, b = jax.vmap(lambda rhs: tridiagonal_solve(*blocks, rhs))(jnp.stack([-R, R_lam]))
    Dp, _ = _factor(*blocks)
    sign = jnp.prod(jnp.linalg.slogdet(Dp)[0])
    return a, b, sign


def _step(rod_fn, theta0, r0, lam0, tau_x, tau_l, s, w, wl, tol, max_newton, spectra):
    """Predictor, Newton corrector on the bordered system (module docstring), the new tangent,
    the branch-point test and the spectrum. The loop's last evaluation (at the point whose
    correction is below ``tol``) gives the tangent and the test."""
    theta, r = _apply(theta0, r0, s * tau_x)
    zero_x = jnp.zeros_like(tau_x)
    inf = jnp.asarray(jnp.inf, r.dtype)
    init = (theta, r, lam0 + s * tau_l, s * tau_x, s * tau_l, 0, inf, zero_x, jnp.ones_like(inf))

    def cond(c):
        return (c[6] > tol) & (c[5] < max_newton)

    def body(c):
        theta, r, lam, Dx, Dl, k = c[:6]
        R, blocks, R_lam = _linear_parts(rod_fn, theta, r, lam)
        a, b, sign = _bordered(blocks, R, R_lam)
        gap = _inner(tau_x, tau_l, Dx + a, Dl, w, wl) - s
        dl = -gap / (tau_l * wl**2 - jnp.sum(tau_x * b * w**2))
        dx = a - dl * b
        theta, r = _apply(theta, r, dx)
        size = jnp.maximum(jnp.max(jnp.abs(dx * w)), jnp.abs(dl * wl))
        size = jnp.where(jnp.isfinite(size), size, jnp.inf)
        return theta, r, lam + dl, Dx + dx, Dl + dl, k + 1, size, b, sign

    theta, r, lam, _, _, k, size, b, sign = jax.lax.while_loop(cond, body, init)
    pivot = tau_l * wl**2 - jnp.sum(tau_x * b * w**2)
    t_l = 1.0 / pivot
    t_x = -t_l * b
    norm = jnp.sqrt(_inner(t_x, t_l, t_x, t_l, w, wl))
    ok = (size <= tol) & jnp.all(jnp.isfinite(r)) & jnp.all(jnp.isfinite(theta))
    p = jnp.zeros((0,), jnp.complex64 if theta.dtype == jnp.float32 else jnp.complex128)
    if spectra:
        p = jnp.linalg.eigvals(linearize(rod_fn(lam), RodState.at_rest(theta, r)))
    return theta, r, lam, ok, k, t_x / norm, t_l / norm, sign * jnp.sign(pivot), p


_step_program = jit(_step, fast_compile=True)


def continue_equilibrium(
    rod_fn: Callable[..., Rod],
    start: float,
    stop: float,
    *,
    guess: RodState | None = None,
    steps: int = 1,
    ds: float = 0.05,
    ds_min: float = 1e-6,
    ds_max: float = 0.2,
    max_points: int = 500,
    tol: float = 1e-10,
    load_scale: float | None = None,
    spectra: bool = True,
) -> RodBranch:
    r"""Follow the equilibria of ``rod_fn(λ)`` (a :class:`Rod` for every load value λ, traced:
    build load vectors with ``jnp.stack``) from λ = ``start`` towards ``stop`` by
    pseudo-arclength continuation (module docstring), through limit points of λ.

    The first equilibrium is :func:`rbo_jax.lattice.solve_equilibrium`'s from ``guess`` in
    ``steps`` load steps. The arclength step, in the weighted norm of turns, displacements over
    the rod's size and loads over ``load_scale`` (default ``max(|start|, |stop|)``), starts at
    ``ds``, grows ×1.5 (up to ``ds_max``) after corrections of at most three Newton steps and
    halves after failed ones; the run stops when λ passes ``stop``, after ``max_points``
    points, or when the step falls below ``ds_min``. ``tol``: Newton stops when no weighted
    correction exceeds it. ``spectra``: the eigenvalues at every point (12N of them, a dense
    eigenvalue problem per point), needed for the stability and the Hopf test.

    Returns a :class:`RodBranch`. Not differentiable (a loop in Python around compiled steps).
    """
    if not callable(rod_fn):
        raise TypeError(f"continue_equilibrium: rod_fn must be callable, got {type(rod_fn)}.")
    if not (ds > 0 and ds_min > 0 and ds_max >= ds):
        raise ValueError(
            f"continue_equilibrium: need 0 < ds <= ds_max and ds_min > 0, got ds={ds}, "
            f"ds_max={ds_max}, ds_min={ds_min}."
        )
    if not (np.isfinite(start) and np.isfinite(stop)) or start == stop:
        raise ValueError(
            f"continue_equilibrium: start and stop must be finite and differ, got {start}, {stop}."
        )
    if int(max_points) < 2:
        raise ValueError(f"continue_equilibrium: max_points must be >= 2, got {max_points}.")
    scale = max(abs(start), abs(stop)) if load_scale is None else float(load_scale)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"continue_equilibrium: load_scale must be > 0, got {load_scale}.")
    rod0 = rod_fn(jnp.asarray(float(start)))
    if not isinstance(rod0, Rod):
        raise TypeError(f"continue_equilibrium: rod_fn must return a Rod, got {type(rod0)}.")
    sol = solve_equilibrium(rod0, guess, steps=steps)
    if not bool(sol.ok):
        raise ValueError(
            f"continue_equilibrium: no equilibrium at the load {start} ({sol.status})."
        )
    return _follow(rod_fn, sol.state, float(start), float(stop), scale, ds, ds_min, ds_max,
                   int(max_points), float(tol), bool(spectra))  # fmt: skip


def _follow(rod_fn, state, start, stop, scale, ds, ds_min, ds_max, max_points, tol, spectra):
    """The loop of :func:`continue_equilibrium` around the compiled steps."""
    theta, r = jnp.asarray(state.theta), jnp.asarray(state.r)
    tol = max(tol, 100 * float(jnp.finfo(theta.dtype).eps))  # as the static solve's floor
    size = max(float(jnp.max(jnp.abs(r))), 1.0)
    w = jnp.asarray([[1.0, 1.0, 1.0] + [1.0 / size] * 3], theta.dtype)  # (1, 6)
    wl = jnp.asarray(1.0 / scale, theta.dtype)
    direction = 1.0 if stop > start else -1.0

    def step(theta, r, lam, tx, tl, s):
        return _step_program(rod_fn, theta, r, lam, tx, tl, jnp.asarray(s, theta.dtype), w, wl,
                             tol, 20, spectra)  # fmt: skip

    # the first tangent: a corrector at s = 0 with the load held (tau = the load direction)
    zeros = jnp.zeros(theta.shape[:-1] + (6,), theta.dtype)
    lam0 = jnp.asarray(start, theta.dtype)
    theta, r, lam, _, _, tx, tl, bp, p = step(theta, r, lam0, zeros, direction * scale, 0.0)
    rows, special, points = [], [], []

    def keep(theta, r, lam, tl, p):
        # turn-tensors, not turn-vectors, for the chords: a turn-vector jumps where it wraps
        Q = jax.vmap(turn_tensor)(theta)
        flat = jnp.concatenate([jnp.ravel(Q), jnp.ravel(r) / size, jnp.ravel(lam)])
        rows.append((np.asarray(flat), np.asarray(p)))
        points.append((np.asarray(theta), np.asarray(r), float(lam)))

    keep(theta, r, lam, tl, p)
    reason = "max_points"
    while len(rows) < max_points:
        out = step(theta, r, lam, tx, tl, ds)
        if not bool(out[3]):
            ds *= 0.5
            if ds < ds_min:
                reason = "step size below ds_min"
                break
            continue
        theta_n, r_n, lam_n, _, k, tx_n, tl_n, bp_n, p_n = out
        u, v = np.array([float(lam)]), np.array([float(lam_n)])
        p0, p1 = (rows[-1][1], np.asarray(p_n)) if spectra else (np.ones(1), np.ones(1))
        _detect(special, len(rows) - 1, u, v, np.array([float(tl)]), np.array([float(tl_n)]),
                float(bp), float(bp_n), p0, p1)  # fmt: skip
        theta, r, lam, tx, tl, bp, p = theta_n, r_n, lam_n, tx_n, tl_n, bp_n, p_n
        keep(theta, r, lam, tl, p)
        ds = min(ds * 1.5, ds_max) if int(k) <= 3 else ds
        if direction * (float(lam) - stop) >= 0:
            reason = "reached stop"
            break
    _refine_folds(special, rows)
    states = RodState.at_rest(np.stack([q[0] for q in points]), np.stack([q[1] for q in points]))
    return RodBranch(
        loads=np.array([q[2] for q in points]),
        states=states,
        eigenvalues=np.stack([row[1] for row in rows]),
        special=tuple(special),
        stop_reason=reason,
    )
