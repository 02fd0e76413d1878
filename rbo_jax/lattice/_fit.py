r"""Fitting the constants of a lattice or a rod by least squares: a lattice's stiffnesses to a
measured dispersion curve or to a recorded space-time field of turn-vectors, a rod's to its
measured eigenvalues (frequencies and decay rates) or to a measured trajectory of one body.

Every fit runs through one implementation (:func:`least_squares`). The constants are named and
positive (a stiffness, an inertia, a damping time) and are fitted as their logarithms. One
compiled program returns the residuals and their forward-mode Jacobian: through the eigenvalues of
the Bloch matrix (:func:`rbo_jax.lattice.dispersion`) or of a rod's linearisation (and through the
Newton solve of its equilibrium, by the implicit function theorem, when it is loaded), or through
the motion (the lattice's DOP853 loop of :func:`rbo_jax.lattice.simulate`, or diffrax; one tangent
per constant). The Levenberg–Marquardt iteration of :func:`rbo_jax.fit`
(:func:`rbo_jax.solvers.run_least_squares`) runs on the host around it. The standard errors are
Gauss–Newton's, $s^2 (J^TJ)^{-1}$ with $s^2$ the residual variance, carried to each constant by
the delta method, $\sigma_p = p\,\sigma_{\log p}$
(:func:`rbo_jax.solvers.gauss_newton_covariance`, as :func:`rbo_jax.fit`'s).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import tree_map

from .._programs import jit
from ..models.rod import RodState
from ..solvers import gauss_newton_covariance, run_least_squares, value_and_jacfwd
from ..stability import linearize, solve_equilibrium
from ._dispersion import bloch_blocks, dispersion
from ._rod_dynamics import _solve
from ._simulate import simulate

__all__ = ["LatticeFit", "RodFit", "fit_dispersion", "fit_field", "fit_spectrum", "fit_trajectory"]


class LatticeFit(eqx.Module):
    """The result of a fit of a lattice's or a rod's constants (:func:`fit_dispersion`,
    :func:`fit_field`, :func:`fit_spectrum`, :func:`fit_trajectory`; :class:`RodFit` is this
    class): ``params`` and ``stderr`` (name -> fitted value, and its Gauss–Newton standard
    error), ``rms`` (the root mean square of the residuals at the solution, in the data's
    units), ``num_steps``, ``converged`` and ``message`` (how the iteration ended)."""

    params: dict
    stderr: dict
    rms: float
    num_steps: int
    converged: bool
    message: str = eqx.field(static=True)


RodFit = LatticeFit


def _start(params: Mapping[str, float]):
    if not params:
        raise ValueError("lattice fit: params must name at least one parameter to fit.")
    values = {k: np.asarray(v, dtype=float) for k, v in params.items()}
    bad = [k for k, v in values.items() if v.shape != () or not (np.isfinite(v) and v > 0)]
    if bad:
        raise ValueError(
            "lattice fit: the starting values must be finite numbers > 0 (they "
            "are fitted as logarithms), got " + ", ".join(f"{k}={params[k]!r}" for k in bad) + "."
        )
    return {k: jnp.log(jnp.asarray(v)) for k, v in values.items()}


@functools.partial(jit, small=True)
def _residuals_and_jacobian(model_fn, residuals, u, data):
    """The one compiled program of a fit (per ``model_fn``, ``residuals`` and data shapes): the
    residuals of the model with the constants $e^u$, and their Jacobian with respect to u."""
    return value_and_jacfwd(lambda v: residuals(model_fn(**tree_map(jnp.exp, v)), data), u)


def least_squares(model_fn, residuals, u0, data, tol, max_steps, measured=None) -> LatticeFit:
    r"""Levenberg–Marquardt on ``residuals(model_fn(**constants), data)`` (``residuals`` a
    function or a ``jax.tree_util.Partial``) from the logarithms ``u0`` of the constants, then
    their Gauss–Newton standard errors with $s^2 = |r|^2/(m - p)$ over the ``measured``
    residuals (a mask; default all of them), which also give ``rms``."""

    def evaluate(u):
        return _residuals_and_jacobian(model_fn, residuals, u, data)

    u, steps, converged, message = run_least_squares(
        evaluate, u0, "levenberg_marquardt", tol, max_steps, []
    )
    r, J = evaluate(u)
    r = np.asarray(r, dtype=float)
    measured = np.ones(r.size, bool) if measured is None else measured
    values = {k: float(np.exp(u[k])) for k in sorted(u)}  # the Jacobian's columns: sorted keys
    x = np.array(list(values.values()))
    _, se, note = gauss_newton_covariance(r, J, 1.0 / x, int(measured.sum()))
    return LatticeFit(
        params=values,
        stderr=dict(zip(values, map(float, se))),
        rms=np.sqrt(np.mean(r[measured] ** 2)),
        num_steps=int(steps),
        converged=bool(converged),
        message=message + note,
    )


def _dispersion_residuals(lat, data):
    q, target, mask, branches, theta_eq = data
    blocks = bloch_blocks(lat, theta_eq)
    lam = jax.vmap(lambda k: dispersion(lat, k, blocks=blocks))(q)
    w = jnp.sort(jnp.imag(lam)[:, 3:], axis=1)[:, branches]
    return jnp.ravel(jnp.where(mask, w - target, 0.0))


def _field_residuals(options, lat, data):
    ts, target, mask, theta0, Omega0 = data
    traj = simulate(lat, theta0, Omega0, ts, throw=False, **dict(options))
    return jnp.ravel(jnp.where(mask, traj.theta - target, 0.0))


def fit_dispersion(
    lattice_fn: Callable,
    params: Mapping[str, float],
    q,
    omega,
    *,
    branches=None,
    theta_eq=None,
    tol: float = 1e-12,
    max_steps: int = 100,
) -> LatticeFit:
    r"""Fit ``params`` (name -> starting value > 0) so that the lattice ``lattice_fn(**params)``
    has the measured frequencies ``omega`` at the wavevectors ``q``.

    ``q``: ``(Q,)`` wavenumbers of a chain, or ``(Q, dim)``; ``omega``: ``(Q,)`` or ``(Q, B)``
    frequencies (NaN where a branch was not measured) of the branches ``branches`` (indices into
    the three non-negative frequencies $\mathrm{Im}\,\lambda$ of :func:`dispersion`, sorted
    ascending; default the lowest ``B``). The lattice is linearized about ``theta_eq`` (default:
    each body's equilibrium, :func:`uniform_equilibrium`, which follows the parameters: the
    Jacobian program then also differentiates the Bloch matrix with respect to the state, and
    takes longer to compile — pass ``theta_eq`` where the equilibrium does not depend on the
    fitted parameters, e.g. ``np.zeros(3)`` at rest).
    ``tol``, ``max_steps``: as :func:`rbo_jax.fit` (the relative step size and the number of
    Levenberg–Marquardt iterations). One compiled program per ``lattice_fn`` and data shapes.
    Returns a :class:`LatticeFit` (``rms`` and the standard errors count every entry of
    ``omega``, a NaN one as a zero residual)."""
    u0 = _start(params)
    q = jnp.asarray(q, dtype=jnp.result_type(float))
    omega = np.asarray(omega, dtype=float)
    omega = omega[:, None] if omega.ndim == 1 else omega
    if omega.ndim != 2 or omega.shape[0] != q.shape[0]:
        raise ValueError(
            f"lattice.fit_dispersion: omega needs one row per wavevector "
            f"({q.shape[0]}), got shape {omega.shape}."
        )
    branches = np.arange(omega.shape[1]) if branches is None else np.asarray(branches)
    if branches.shape != (omega.shape[1],) or np.any((branches < 0) | (branches > 2)):
        raise ValueError(
            f"lattice.fit_dispersion: branches must give one index in 0..2 per "
            f"column of omega ({omega.shape[1]}), got {branches!r}."
        )
    measured = np.isfinite(omega)
    data = (
        q,
        jnp.asarray(np.where(measured, omega, 0.0)),
        jnp.asarray(measured),
        jnp.asarray(branches),
        None if theta_eq is None else jnp.asarray(theta_eq),
    )
    return least_squares(lattice_fn, _dispersion_residuals, u0, data, tol, max_steps)


def fit_field(
    lattice_fn: Callable,
    params: Mapping[str, float],
    ts,
    theta,
    theta0,
    Omega0,
    *,
    tol: float = 1e-12,
    max_steps: int = 100,
    **simulate_options,
) -> LatticeFit:
    r"""Fit ``params`` (name -> starting value > 0) so that the motion of
    ``lattice_fn(**params)`` from ``(theta0, Omega0)`` matches the recorded turn-vectors
    ``theta`` (``(T, N, 3)``, NaN where not recorded) at the times ``ts``: a space-time field.
    ``simulate_options`` go to :func:`rbo_jax.lattice.simulate` (``method``, its ``rtol``,
    ``atol``, ...; default DOP853 at 1e-10, 1e-12); forward-mode derivatives through the
    solver. One compiled program per ``lattice_fn``, options and data shapes. Returns a
    :class:`LatticeFit` (``rms`` and the standard errors count every entry of ``theta``, a NaN
    one as a zero residual)."""
    u0 = _start(params)
    theta = np.asarray(theta, dtype=float)
    measured = np.isfinite(theta)
    options = tuple(sorted((dict(rtol=1e-10, atol=1e-12) | dict(simulate_options)).items()))
    data = (
        jnp.asarray(ts, dtype=jnp.result_type(float)),
        jnp.asarray(np.where(measured, theta, 0.0)),
        jnp.asarray(measured),
        jnp.asarray(theta0, dtype=jnp.result_type(float)),
        jnp.asarray(Omega0, dtype=jnp.result_type(float)),
    )
    residuals = jax.tree_util.Partial(_field_residuals, options)
    return least_squares(lattice_fn, residuals, u0, data, tol, max_steps)


def _lowest(p, count):
    """The ``count`` eigenvalues with the smallest positive imaginary parts, ascending."""
    key = jnp.where(p.imag > 1e-9 * jnp.max(jnp.abs(p)), p.imag, jnp.inf)
    return p[jnp.argsort(key)[:count]]


def _spectrum_residuals(at_rest, rod, data):
    target, mask = data
    state = rod.straight() if at_rest else solve_equilibrium(rod).state
    p = _lowest(jnp.linalg.eigvals(linearize(rod, state)), target.shape[0])
    r = jnp.stack([p.real - target[:, 0], p.imag - target[:, 1]], axis=1)
    return jnp.ravel(jnp.where(mask, r, 0.0))


def fit_spectrum(
    rod_fn: Callable,
    params: Mapping[str, float],
    eigenvalues,
    *,
    at_rest: bool = True,
    tol: float = 1e-12,
    max_steps: int = 100,
) -> RodFit:
    r"""Fit ``params`` (name -> starting value > 0) so that the rod ``rod_fn(**params)`` has the
    measured ``eigenvalues``: complex $p_k = -\zeta_k + i\omega_k$ of its lowest modes in order
    of frequency (the modes with $\omega > 0$ of :func:`rbo_jax.lattice.spectrum`; a rod of
    circular section has each bending frequency twice, one per plane: list both). A real part
    that was not measured is NaN (``complex(nan, omega)``): only the frequency is fitted.
    ``at_rest``: linearise about the straight state at rest (a rod without loads), else about
    the equilibrium under the loads (Newton, differentiated implicitly). ``tol``,
    ``max_steps``: as :func:`rbo_jax.fit`. Returns a :class:`RodFit` with standard errors
    (``rms`` and $s^2$ over the measured numbers)."""
    u0 = _start(params)
    p = np.atleast_1d(np.asarray(eigenvalues, dtype=complex))
    if p.ndim != 1 or p.size == 0:
        raise ValueError(f"fit_spectrum: eigenvalues must be a 1-D array, got shape {p.shape}.")
    if not np.all(np.isfinite(p.imag)) or np.any(p.imag <= 0):
        raise ValueError("fit_spectrum: every eigenvalue needs a measured frequency Im p > 0.")
    target = np.stack([np.nan_to_num(p.real), p.imag], axis=1)
    mask = np.stack([np.isfinite(p.real), np.ones(p.size, bool)], axis=1)
    data = (jnp.asarray(target), jnp.asarray(mask))
    residuals = jax.tree_util.Partial(_spectrum_residuals, bool(at_rest))
    return least_squares(rod_fn, residuals, u0, data, tol, max_steps, mask.ravel())


def _trajectory_residuals(settings, rod, data):
    """The simulated positions of the measured body at ``ts`` minus the measured ones."""
    ts, target, state0 = data
    solver, rtol, atol, max_steps, dt0, body = settings
    adjoint = diffrax.ForwardMode()  # few parameters: forward mode through the solve
    ys, _, _ = _solve(rod, state0, ts, solver, rtol, atol, max_steps, dt0, adjoint)
    return jnp.ravel(ys.r[:, body, :] - target)


def fit_trajectory(
    rod_fn: Callable,
    params: Mapping[str, float],
    ts,
    positions,
    state0: RodState,
    *,
    body: int = -1,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    tol: float = 1e-12,
    max_fit_steps: int = 100,
) -> RodFit:
    r"""Fit ``params`` (name -> starting value > 0, fitted as logarithms) so that the motion of
    ``rod_fn(**params)`` from ``state0`` (a :class:`RodState`, held fixed: e.g. a measured
    deflected shape at rest) passes through the measured ``positions`` (T, 3) of one body
    (``body``, the tip by default) at the times ``ts`` (T,), ``ts[0]`` the time of ``state0``.

    The residuals are the simulated positions (:func:`rbo_jax.lattice.simulate`'s diffrax solve,
    ``solver`` default ``Dopri8`` with ``rtol``, ``atol``, ``max_steps``) minus the measured
    ones; Levenberg–Marquardt (:func:`rbo_jax.fit`'s) with forward-mode derivatives through the
    solve (``diffrax.ForwardMode``: one tangent per parameter); ``tol``, ``max_fit_steps``: its
    tolerance and iterations. Standard errors: Gauss–Newton, $s^2 (J^TJ)^{-1}$ with the residual
    variance $s^2 = |r|^2/(3T - p)$, by the delta method. Returns a :class:`RodFit` (``rms`` in
    the positions' units)."""
    u0 = _start(params)
    ts = np.asarray(ts, dtype=float)
    target = np.asarray(positions, dtype=float)
    if ts.ndim != 1 or ts.size < 2 or not np.all(np.diff(ts) > 0):
        raise ValueError("fit_trajectory: ts must be a strictly increasing 1-D array of >= 2.")
    if target.shape != (ts.size, 3) or not np.all(np.isfinite(target)):
        raise ValueError(
            f"fit_trajectory: positions must be finite, shape {(ts.size, 3)} (one row per "
            f"time), got {target.shape}."
        )
    if not isinstance(state0, RodState):
        raise TypeError(f"fit_trajectory: state0 must be a RodState, got {type(state0)}.")
    solver = diffrax.Dopri8() if solver is None else solver
    dt0 = float(ts[1] - ts[0]) / 10.0
    settings = (solver, float(rtol), float(atol), int(max_steps), dt0, int(body))
    state0 = jax.tree_util.tree_map(jnp.asarray, state0)
    data = (jnp.asarray(ts), jnp.asarray(target), state0)
    residuals = jax.tree_util.Partial(_trajectory_residuals, settings)
    return least_squares(rod_fn, residuals, u0, data, tol, int(max_fit_steps))
