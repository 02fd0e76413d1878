r"""Pseudo-arclength continuation of equilibria in one parameter, with fold, branch-point and
Hopf detection.

The branch $G(\theta, \alpha) = \dot\Omega(\theta, 0; \alpha) = 0$ (the moment balance (4.61)
written with the right form (4.56)) is followed in $u = (\theta, \alpha)$ by Keller's
pseudo-arclength method: from a point $u_k$ with unit tangent $\tau_k$ (the null vector of
$G_u$, oriented), the predictor $u_k + s\,\tau_k$ is corrected by Newton's method on
$G(u) = 0$, $\tau_k\cdot(u - u_k) = s$, so folds in $\alpha$ are passed. Along the branch:

- **fold**: the $\alpha$-component of the tangent changes sign;
- **branch point**: $\det\begin{pmatrix}G_u\\\tau^T\end{pmatrix}$ changes sign;
- **Hopf point**: the number of eigenvalues (4.63)–(4.67) with $\mathrm{Re}\,p > 0$ and
  $\mathrm{Im}\,p \ne 0$ changes; the point is then located exactly by
  :func:`rbo_jax.hopf_point` started from the last point before the change.

Branch points are located by linear interpolation of their test function between the two points
that bracket them (error $O(s^2)$), folds by the vertex of the parabola $\alpha(\sigma)$ through
three points around them (error $O(s^3)$).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .._programs import jit
from ..kinematics import _as_vector
from ..model import RigidBodyOscillator
from ..stability import solve_equilibrium
from ._field import flat_field
from ._hopf import _point, canonical, hopf_point
from ._system import _build

__all__ = ["continue_equilibria"]


def _derivatives(model_fn, parameter, others, t):
    r"""$u = (\theta, \alpha) \mapsto (G(u), G_u(u), J(u))$: the moment balance, its 3×4
    Jacobian and the 6×6 linearization (4.63)–(4.67), from one forward-mode pass of the vector
    field over $(\theta, \Omega, \alpha)$ (one traced copy of it)."""

    def F(z):
        return flat_field(_build(model_fn, _point(others, parameter, z[6])), t)(z[:6])

    def at(u):
        z = jnp.concatenate([u[:3], jnp.zeros(3, u.dtype), u[3:]])
        D, f = jax.jacfwd(lambda z: (F(z), F(z)), has_aux=True)(z)
        return f[3:], jnp.concatenate([D[3:, :3], D[3:, 6:]], axis=1), D[:, :6]

    return at


def _tangent(Gu, tau_prev):
    """The unit null vector of the 3×4 ``Gu``, oriented along ``tau_prev``; and the determinant
    of the bordered matrix (the branch-point test function)."""
    A = jnp.concatenate([Gu, tau_prev[None, :]])
    tau = jnp.linalg.solve(A, jnp.array([0.0, 0.0, 0.0, 1.0]))
    tau = tau / jnp.linalg.norm(tau)
    return tau, jnp.linalg.det(jnp.concatenate([Gu, tau[None, :]]))


@functools.partial(jit, small=True)
def _step(model_fn, parameter, t, others, u, tau, s, tol, max_newton):
    """Predictor, Newton corrector, new tangent and spectrum. The loop's last evaluation (at the
    point whose correction is below ``tol``) gives the tangent and the spectrum."""
    at = _derivatives(model_fn, parameter, others, t)
    u_pred = u + s * tau

    def cond(carry):
        return ~carry[2]

    def body(carry):
        v, k, _, _, _, _ = carry
        G, Gu, J = at(v)
        r = jnp.concatenate([G, (tau @ (v - u_pred))[None]])
        delta = jnp.linalg.solve(jnp.concatenate([Gu, tau[None, :]]), -r)
        size = jnp.maximum(jnp.max(jnp.abs(delta)), jnp.max(jnp.abs(r)))
        size = jnp.where(jnp.isfinite(size), size, jnp.inf)
        done = (size <= tol) | (k + 1 >= max_newton)
        return v + delta, k + 1, done, size, Gu, J

    init = (u_pred, 0, False, jnp.asarray(jnp.inf), jnp.zeros((3, 4)), jnp.zeros((6, 6)))
    v, k, _, size, Gu, J = jax.lax.while_loop(cond, body, init)
    converged = (size <= tol) & jnp.all(jnp.isfinite(v))
    tau_new, bp = _tangent(Gu, tau)
    p = jnp.linalg.eigvals(J)
    return v, converged, k, tau_new, bp, p


def _counts(p, rtol=1e-9):
    tol = rtol * max(float(np.max(np.abs(p))), 1e-300)
    unstable = np.real(p) > tol
    oscillatory = np.abs(np.imag(p)) > tol
    return int(np.sum(unstable & oscillatory)), int(np.sum(unstable))


def continue_equilibria(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    start: float,
    stop: float,
    *,
    theta_guess=None,
    ds: float = 0.02,
    ds_min: float = 1e-6,
    ds_max: float = 0.1,
    max_points: int = 500,
    tol: float = 1e-10,
    locate_hopf: bool = True,
    t=0.0,
    progress: bool = False,
):
    r"""Follow the equilibria of ``model_fn(**params, parameter=α)`` from α = ``start`` towards
    ``stop`` by pseudo-arclength continuation (module docstring), detecting folds, branch points
    and Hopf points.

    The first equilibrium is Newton's (:func:`rbo_jax.solve_equilibrium`) from ``theta_guess``
    (default 0). The arclength step starts at ``ds``, grows ×1.5 (up to ``ds_max``) after easy
    corrections and halves after failed ones; the run stops when α passes ``stop``, after
    ``max_points`` points, or when the step falls below ``ds_min``.

    **Returns** an :class:`xarray.Dataset` over ``point``: ``parameter`` (α), ``theta``
    (component), ``eigenvalues`` (mode), ``spectral_abscissa``, ``stable`` (every Re p < 0), and
    over ``special``: ``special_type`` (``"fold"``, ``"branch_point"``, ``"hopf"``),
    ``special_value`` (α), ``special_index`` (the point before it), and for Hopf points
    ``special_frequency`` and ``special_first_lyapunov`` (from :func:`rbo_jax.hopf_point`;
    NaN otherwise). ``attrs["stop_reason"]`` says why the run ended.
    """
    import xarray as xr

    others = {
        str(k): jnp.asarray(v, dtype=jnp.result_type(float))
        for k, v in params.items()
        if k != parameter
    }
    guess = jnp.zeros(3) if theta_guess is None else _as_vector(theta_guess, "theta_guess")
    if not (ds > 0 and ds_min > 0 and ds_max >= ds):
        raise ValueError(f"need 0 < ds <= ds_max and ds_min > 0, got {ds}, {ds_max}, {ds_min}.")
    sol = solve_equilibrium(_build(model_fn, _point(others, parameter, jnp.asarray(start))), guess)
    if not bool(sol.ok):
        raise ValueError(
            f"no equilibrium found at {parameter} = {start} from theta_guess: "
            f"{sol.status.__class__.__name__}.{_name(sol.status)}."
        )
    u = jnp.concatenate([sol.theta, jnp.asarray([start], dtype=sol.theta.dtype)])
    direction = 1.0 if stop >= start else -1.0
    model_fn = canonical(model_fn)  # a new but identical function: the same program
    u, _, _, tau, bp, p = _step(
        model_fn,
        parameter,
        t,
        others,
        u,
        jnp.array([0.0, 0.0, 0.0, direction]),
        jnp.asarray(0.0),
        tol,
        20,
    )
    rows, special = [(u, p)], []
    reason = "max_points"
    bar = _progress(progress, max_points)
    while len(rows) < max_points:
        v, ok, k, tau_new, bp_new, p_new = _step(
            model_fn, parameter, t, others, u, tau, jnp.asarray(ds), tol, 20
        )
        if not bool(ok):
            ds *= 0.5
            if ds < ds_min:
                reason = "step size below ds_min"
                break
            continue
        _detect(special, len(rows) - 1, u, v, tau, tau_new, bp, bp_new, p, p_new)
        u, tau, bp, p = v, tau_new, bp_new, p_new
        rows.append((u, p))
        bar.update(1)
        ds = min(ds * 1.5, ds_max) if int(k) <= 3 else ds
        if direction * (float(u[3]) - stop) >= 0:
            reason = "reached stop"
            break
    bar.close()
    _refine_folds(special, rows)
    if locate_hopf:
        _locate_hopf(special, rows, model_fn, others, parameter)
    return _dataset(xr, parameter, rows, special, reason)


def _name(item):
    from .. import _enumeration as enum

    return enum.name(item)


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress(progress, total):
    if not progress:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="equilibria", unit="point")


def _detect(special, index, u, v, tau, tau_new, bp, bp_new, p, p_new):
    """Folds, branch points and Hopf points between the points ``u`` and ``v`` (the parameter
    last, as the tangents ``tau``; also the rods' :func:`rbo_jax.lattice.continue_equilibrium`)."""

    def interpolate(f0, f1):
        w = float(f0 / (f0 - f1))
        return float(u[-1] + w * (v[-1] - u[-1]))

    if float(tau[-1]) * float(tau_new[-1]) < 0:
        special.append(("fold", interpolate(tau[-1], tau_new[-1]), index))
    if float(bp) * float(bp_new) < 0:
        special.append(("branch_point", interpolate(bp, bp_new), index))
    if _counts(np.asarray(p))[0] != _counts(np.asarray(p_new))[0]:
        special.append(("hopf", float(0.5 * (u[-1] + v[-1])), index))


def _refine_folds(special, rows):
    """A fold's parameter as the vertex of the parabola alpha(sigma) through three points of
    the branch around it (sigma the arclength along their chords; the parameter the last entry of
    every point): error O(s^3)."""
    for i, (kind, value, index) in enumerate(special):
        lo = max(index - 1, 0)
        if kind != "fold" or lo + 3 > len(rows):
            continue
        U = np.stack([np.asarray(rows[j][0]) for j in range(lo, lo + 3)])
        sigma = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(U, axis=0), axis=1))])
        a, b, c = np.polyfit(sigma, U[:, -1], 2)
        if a != 0 and sigma[0] <= -b / (2 * a) <= sigma[-1]:
            special[i] = (kind, float(c - b * b / (4 * a)), index)


def _locate_hopf(special, rows, model_fn, others, parameter):
    for i, (kind, value, index) in enumerate(special):
        if kind != "hopf":
            continue
        u = rows[index][0]
        h = hopf_point(model_fn, others, parameter, u[3], theta_guess=u[:3])
        extra = (float(h.frequency), float(h.first_lyapunov)) if bool(h.ok) else (np.nan, np.nan)
        special[i] = (kind, float(h.value) if bool(h.ok) else value, index) + extra


def _dataset(xr, parameter, rows, special, reason):
    U = np.stack([np.asarray(u) for u, _ in rows])
    P = np.stack([np.sort_complex(np.asarray(p)) for _, p in rows])
    abscissa = np.max(P.real, axis=1)
    scale = np.maximum(np.max(np.abs(P), axis=1), 1e-300)
    special = [s + (np.nan, np.nan) if len(s) == 3 else s for s in special]
    ds = xr.Dataset(
        {
            parameter: ("point", U[:, 3]),
            "theta": (("point", "component"), U[:, :3]),
            "eigenvalues": (("point", "mode"), P),
            "spectral_abscissa": ("point", abscissa),
            "stable": ("point", abscissa < -1e-9 * scale),
            "special_type": ("special", np.array([s[0] for s in special], dtype=str)),
            "special_value": ("special", np.array([s[1] for s in special], dtype=float)),
            "special_index": ("special", np.array([s[2] for s in special], dtype=int)),
            "special_frequency": ("special", np.array([s[3] for s in special], dtype=float)),
            "special_first_lyapunov": ("special", np.array([s[4] for s in special], dtype=float)),
        },
        coords={"component": ["x", "y", "z"], "mode": np.arange(6)},
        attrs={"parameter": parameter, "stop_reason": reason},
    )
    return ds
