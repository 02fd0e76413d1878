r"""Branch switching at a Hopf point onto the family of limit cycles, and its pseudo-arclength
continuation in the parameter.

Unknowns $u = (x_0, T, \alpha)$ (initial state, period, parameter); equations

$$\varphi_T(x_0; \alpha) - x_0 = 0,\qquad g\cdot(x_0 - x_{ref}) = 0,\qquad
  \tau\cdot(u - u_k) = s,$$

with the phase vector $g = F(x_{ref}; \alpha_k)$ at the previous orbit's initial state and the
unit secant $\tau$ of the last two points. Newton's method uses the exact Jacobian
$\big(M - E,\ F(\varphi_T),\ \partial_\alpha\varphi_T\big)$ from one forward-mode pass through
:func:`rbo_jax.fast_simulate` (7 tangents: the state and α).

**Branch switching.** At the Hopf point $(x_H, \alpha_H)$ with eigenvector $q$ the cycles are
$x(t) \approx x_H + 2r\,\mathrm{Re}(e^{i\omega t}q)$, $\alpha - \alpha_H = O(r^2)$, $T \approx
2\pi/\omega$: the first predictor steps by ``amplitude`` along $\mathrm{Re}\,q$ from the Hopf
point with tangent $(\mathrm{Re}\,q/|\mathrm{Re}\,q|, 0, 0)$.

Along the branch: the Floquet multipliers (stable if every nontrivial one has $|\mu| < 1$) and the
**amplitude** $\max_t|\theta(t) - \bar\theta|$ over 64 equally spaced samples of one period
($\bar\theta$ their mean).

**Special points** (:mod:`._cycle_special`): folds of cycles (the parameter component of the
branch's tangent, the null vector of $(M - E,\ F(\varphi_T),\ \partial_\alpha\varphi_T;\
g^T, 0, 0)$, changes sign; located by :func:`rbo_jax.bifurcation.fold_of_cycles`, Newton's
method on the minimally augmented shooting system, :mod:`._cycle_fold`), period doubling (a
real multiplier through $-1$) and Neimark–Sacker points (a complex pair through $|\mu| = 1$).
The pseudo-arclength corrector passes folds: past a fold of a hard (subcritical, $\ell_1 > 0$)
Hopf point the family continues as large stable cycles.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .._callables import canonical
from .._programs import jit
from ..continuation import Steps, follow
from ..ensemble import fast_simulate
from ..models.rigid_body import RigidBodyOscillator
from ._cycle_fold import fold_of_cycles
from ._cycle_special import detect, fold_guess
from ._field import flat_field
from ._hopf import HopfPoint
from ._models import rigid_model as _build
from ._models import with_value as _point
from ._orbit import OrbitStatus, _sorted, flow, shooting_newton

__all__ = ["continue_limit_cycles"]

N_SAMPLES = 64


def _system(model_fn, parameter, others, solver, u, g, x_ref, tau, u_k, s):
    x, T, alpha = u[:6], u[6], u[7]

    def phi(z):
        model = _build(model_fn, _point(others, parameter, z[6]))
        xT, ok = flow(model, z[:6], T, **solver)
        return xT, (xT, ok)

    D, (xT, ok) = jax.jacfwd(phi, has_aux=True)(jnp.concatenate([x, alpha[None]]))
    F = flat_field(_build(model_fn, _point(others, parameter, alpha)))
    r = jnp.concatenate([xT - x, (g @ (x - x_ref))[None], (tau @ (u - u_k) - s)[None]])
    top = jnp.concatenate([D[:, :6] - jnp.eye(6), F(xT)[:, None], D[:, 6:]], axis=1)
    A = jnp.concatenate([top, jnp.concatenate([g, jnp.zeros(2)])[None], tau[None]])
    return r, A, D[:, :6], ok


@functools.partial(jit, small=True)
def _correct(model_fn, parameter, others, solver, u_k, tau, s, x_ref, alpha_ref, tol, max_newton):
    """Newton's corrector from the predictor ``u_k + s tau``. Returns the cycle, its status code
    (:class:`OrbitStatus`), Newton's steps, the multipliers, the amplitude and the unit tangent
    of the branch at the cycle (the null vector of the 7×8 shooting Jacobian, along ``tau``)."""
    g = flat_field(_build(model_fn, _point(others, parameter, alpha_ref)))(x_ref)
    g = g / jnp.linalg.norm(g)

    def system(u):
        return _system(model_fn, parameter, others, solver, u, g, x_ref, tau, u_k, s)

    u, k, _, res, ok, A = shooting_newton(system, u_k + s * tau, tol, max_newton, step_tol=False)
    model = _build(model_fn, _point(others, parameter, u[7]))
    # N_SAMPLES equally spaced samples of one period (t = T, a repeat of t = 0, left out)
    ts = jnp.linspace(0.0, 1.0, N_SAMPLES + 1) * jnp.where(u[6] > 0, u[6], 1.0)
    theta = fast_simulate(model, u[:3], u[3:6], ts, throw=False, **solver).theta[:-1]
    amplitude = jnp.max(jnp.linalg.norm(theta - jnp.mean(theta, axis=0, keepdims=True), axis=1))
    S = OrbitStatus
    status = S.where(res <= tol, S.successful, S.not_converged)
    status = S.where(ok, status, S.solve_failed)
    status = S.where(u[6] > 0, status, S.nonpositive_period)
    tangent = jnp.linalg.solve(A, jnp.zeros(8).at[7].set(1.0))  # A's last row: tau
    tangent = tangent / jnp.linalg.norm(tangent)
    M = A[:6, :6] + jnp.eye(6)
    return u, enum.code(status), k, _sorted(jnp.linalg.eigvals(M)), amplitude, tangent


def continue_limit_cycles(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    hopf: HopfPoint,
    *,
    amplitude: float = 1e-2,
    ds_max: float = 0.1,
    max_points: int = 30,
    bounds: tuple[float, float] = (-np.inf, np.inf),
    tol: float = 1e-9,
    rtol: float = 1e-11,
    atol: float = 1e-11,
    locate_folds: bool = True,
    progress: bool = False,
):
    r"""The family of limit cycles born at ``hopf`` (a :class:`rbo_jax.bifurcation.HopfPoint`
    of ``model_fn`` in ``parameter``, with the other entries ``params``), continued by
    pseudo-arclength (module docstring) through folds, with its special points.

    ``amplitude`` is the first step from the Hopf point (in the state norm) and the initial
    arclength step; steps grow ×1.5 up to ``ds_max`` after easy corrections and halve after
    failed ones (large cycles, amplitudes of a radian and more, want ``ds_max`` of 0.3–1: the
    arclength is measured in $(x_0, T, \alpha)$). The run stops after ``max_points`` cycles,
    when the parameter leaves ``bounds``, or when the step falls below ``amplitude``/1000 (the
    stop reason names the last failure: Newton's, or the integration's, e.g. a cycle reaching
    the singular sphere $|\theta| = 2\pi$ of (4.11)). ``tol``: Newton's tolerance on the
    shooting residual; ``rtol``, ``atol``: :func:`rbo_jax.fast_simulate`'s. ``locate_folds``:
    refine detected folds by :func:`rbo_jax.bifurcation.fold_of_cycles` (otherwise the linear
    zero of the tangent's parameter component).

    **Returns** an :class:`xarray.Dataset` over ``point`` (the Hopf point first: amplitude 0,
    NaN multipliers, ``stable`` False; the cycles are ``point`` 1 onwards):
    ``parameter``, ``period``, ``amplitude`` ($\max_t|\theta - \bar\theta|$), ``theta0``,
    ``Omega0`` (component), ``multipliers`` (index; sorted by decreasing modulus),
    ``trivial_multiplier_error`` ($|\mu_{trivial} - 1|$) and ``stable``; over ``special``
    (as :func:`rbo_jax.continue_equilibria`): ``special_type`` (``"fold"``,
    ``"period_doubling"``, ``"neimark_sacker"``), ``special_value`` (the parameter) and
    ``special_index`` (the cycle before it); ``attrs["stop_reason"]``.
    """
    import xarray as xr

    if not bool(hopf.ok):
        raise ValueError("continue_limit_cycles needs a successful Hopf point (hopf.ok).")
    others = {
        str(k): jnp.asarray(v, dtype=jnp.result_type(float))
        for k, v in params.items()
        if k != parameter
    }
    solver = dict(rtol=float(rtol), atol=float(atol), max_steps=100_000)
    model_fn = canonical(model_fn)  # a new but identical function: the same program
    correct = functools.partial(_correct, model_fn, parameter, others, solver)
    steps = dict(s=float(amplitude), ds_max=float(ds_max), tol=float(tol), bounds=bounds)
    rows, reason = _march(correct, hopf, steps, max_points, progress)
    special = detect([(u, t, _nontrivial(mu)) for u, mu, _, t in rows])
    if locate_folds:
        _locate_folds(special, rows, model_fn, others, parameter, solver, float(tol))
    return _dataset(xr, parameter, rows, special, reason)


class _Cycle(NamedTuple):
    """A point of the branch: the cycle ``u``, its multipliers, amplitude and tangent, and the
    direction ``tau`` of the next predictor (the secant of the last two points)."""

    u: jax.Array
    multipliers: jax.Array
    amplitude: float
    tangent: jax.Array
    tau: jax.Array


def _march(correct, hopf, steps, max_points, progress):
    """The branch by the one continuation loop (:func:`rbo_jax.continuation.follow`): its
    points and the stop reason."""
    x_h = jnp.concatenate([hopf.theta, jnp.zeros(3)])
    d = jnp.real(hopf.eigenvector)
    tau = jnp.concatenate([d / jnp.linalg.norm(d), jnp.zeros(2)])
    first = _Cycle(jnp.concatenate([x_h, jnp.stack([hopf.period, hopf.value])]),
                   jnp.full(6, jnp.nan + 0j), 0.0, tau, tau)  # fmt: skip
    failures = []

    def advance(point, ds):
        # the phase condition's reference: the predicted state off the Hopf point, else the cycle
        x_ref = point.u[:6] + (ds * point.tau[:6] if point is first else 0.0)
        u, code, k, mu, amp, tangent = correct(
            point.u, point.tau, jnp.asarray(ds), x_ref, point.u[7], steps["tol"], 12
        )
        if int(code) != int(np.asarray(enum.code(OrbitStatus.successful))):
            failures.append(enum.name(enum.from_code(OrbitStatus, code)))
            return None, 0
        return _Cycle(
            u, mu, float(amp), tangent, (u - point.u) / jnp.linalg.norm(u - point.u)
        ), int(k)

    def accept(points, new):
        inside = steps["bounds"][0] <= float(new.u[7]) <= steps["bounds"][1]
        return True, None if inside else "left bounds"

    s = steps["s"]
    points, reason = follow(advance, first, Steps(s, s * 1e-3, steps["ds_max"]),
                            max_points=max_points, accept=accept, progress=progress,
                            desc="limit cycles")  # fmt: skip
    if reason == "step size below ds_min":
        reason = f"step size below amplitude/1000 (last correction: {failures[-1]})"
    return [(p.u, p.multipliers, p.amplitude, p.tangent) for p in points], reason


def _locate_folds(special, rows, model_fn, others, parameter, solver, tol):
    """Each detected fold refined by :func:`fold_of_cycles` from the interpolated cycle (kept
    at the interpolated value where Newton's method fails)."""
    for i, (kind, value, index) in enumerate(special):
        if kind != "fold":
            continue
        y = fold_guess([(u, t, None) for u, _, _, t in rows], index)
        guess = {"theta0": y[:3], "Omega0": y[3:6], "period": y[6], parameter: y[7]}
        fold = fold_of_cycles(model_fn, others, parameter, guess, tol=tol, **solver)
        if bool(fold.ok):
            special[i] = (kind, float(fold.value), index)


def _nontrivial(mu):
    """The multipliers without the one nearest 1 (NumPy)."""
    mu = np.asarray(mu)
    return np.delete(mu, np.argmin(np.abs(mu - 1.0))) if np.all(np.isfinite(mu)) else mu[1:]


def _dataset(xr, parameter, rows, special, reason):
    U = np.stack([np.asarray(u) for u, _, _, _ in rows])
    mu = np.stack([np.asarray(m) for _, m, _, _ in rows])
    trivial = np.array([np.min(np.abs(m - 1.0)) for m in mu])
    others = np.array([np.max(np.abs(_nontrivial(m))) for m in mu])
    return xr.Dataset(
        {
            parameter: ("point", U[:, 7]),
            "period": ("point", U[:, 6]),
            "amplitude": ("point", np.array([a for _, _, a, _ in rows])),
            "theta0": (("point", "component"), U[:, :3]),
            "Omega0": (("point", "component"), U[:, 3:6]),
            "multipliers": (("point", "index"), mu),
            "trivial_multiplier_error": ("point", trivial),
            "stable": ("point", others < 1.0),
            "special_type": ("special", np.array([s[0] for s in special], dtype=str)),
            "special_value": ("special", np.array([s[1] for s in special], dtype=float)),
            "special_index": ("special", np.array([s[2] for s in special], dtype=int)),
        },
        coords={"component": ["x", "y", "z"], "index": np.arange(6)},
        attrs={"parameter": parameter, "stop_reason": reason},
    )
