r"""Fitting the constants of a lattice or a rod by least squares: a lattice's stiffnesses to a
measured dispersion curve or to a recorded space-time field of turn-vectors, a rod's to its
measured eigenvalues (frequencies and decay rates) or to a measured trajectory of one body.

Every fit runs through one implementation (:func:`rbo_jax.fitting.constants.least_squares`). The
constants are named and positive (a stiffness, an inertia, a damping time) and are fitted as their
logarithms. One compiled program returns the residuals and their forward-mode Jacobian: through the
eigenvalues of the Bloch matrix (:func:`rbo_jax.lattice.dispersion`) or of a rod's linearisation
(and through the Newton solve of its equilibrium, by the implicit function theorem, when it is
loaded), or through the motion (the lattice's DOP853 loop of :func:`rbo_jax.lattice.simulate`, or
diffrax; one tangent per constant). The Levenberg–Marquardt iteration of :func:`rbo_jax.fit`
(:func:`rbo_jax.solvers.run_least_squares`) runs on the host around it. The standard errors are
Gauss–Newton's, $s^2 (J^TJ)^{-1}$ with $s^2$ the residual variance, carried to each constant by the
delta method, $\sigma_p = p\,\sigma_{\log p}$ (:func:`rbo_jax.solvers.gauss_newton_covariance`, as
:func:`rbo_jax.fit`'s).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..fitting.constants import (
    AbstractMeasurements,
    LatticeFit,
    Residuals,
    fit_constants,
    least_squares,
    start_values,
)
from ..models.rod import RodState
from ..stability import linearize, solve_equilibrium
from ._dispersion import bloch_blocks, dispersion
from ._rod_dynamics import _solve
from ._simulate import simulate

__all__ = [
    "LatticeFit",
    "RodFit",
    "RodSpectrumData",
    "RodTrajectoryData",
    "fit_dispersion",
    "fit_field",
    "fit_spectrum",
    "fit_trajectory",
]


RodFit = LatticeFit


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
    names, x0 = start_values(params)
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
    return least_squares(
        Residuals(lattice_fn, names, _dispersion_residuals, data), x0, tol, max_steps
    )


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
    names, x0 = start_values(params)
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
    return least_squares(Residuals(lattice_fn, names, residuals, data), x0, tol, max_steps)


def _matched(p, target, mask):
    """The model's eigenvalue (among those with Im p > 0) nearest each measured one, by the
    measured parts (the frequency, and the decay rate where measured): not the k-th lowest by
    frequency, which jumps where an overdamped mode of a stiff direction turns oscillatory
    with a low frequency (a Kelvin–Voigt rod near its critical damping)."""
    cand = jnp.where(p.imag > 1e-9 * jnp.max(jnp.abs(p)), p, jnp.inf)
    distance = jnp.abs(cand.imag[None, :] - target[:, 1:2])
    distance += jnp.where(mask[:, :1], jnp.abs(cand.real[None, :] - target[:, :1]), 0.0)
    return cand[jnp.argmin(distance, axis=1)]


def _spectrum_residuals(at_rest, rod, data):
    target, mask = data
    state = rod.straight() if at_rest else solve_equilibrium(rod).state
    p = _matched(jnp.linalg.eigvals(linearize(rod, state)), target, mask)
    r = jnp.stack([p.real - target[:, 0], p.imag - target[:, 1]], axis=1)
    return jnp.ravel(jnp.where(mask, r, 0.0))


def _trajectory_residuals(settings, rod, data):
    """The simulated positions of the measured body at ``ts`` minus the measured ones (0 where
    not measured)."""
    ts, target, mask, state0 = data
    solver, rtol, atol, max_steps, dt0, body = settings
    adjoint = diffrax.ForwardMode()  # few parameters: forward mode through the solve
    ys, _, _ = _solve(rod, state0, ts, solver, rtol, atol, max_steps, dt0, adjoint)
    return jnp.ravel(jnp.where(mask, ys.r[:, body, :] - target, 0.0))


def _check_sigma(owner, sigma):
    if sigma is None:
        return None
    if isinstance(sigma, bool) or not np.isscalar(sigma) or not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"{owner}: sigma must be a finite number > 0 (or None), got {sigma!r}.")
    return float(sigma)


class RodSpectrumData(AbstractMeasurements):
    r"""Measured eigenvalues of a rod: what :func:`fit_spectrum` fits, and what
    :func:`rbo_jax.fit`, :func:`rbo_jax.profile_likelihood` and :func:`rbo_jax.posterior` take
    with a rod function ``rod_fn(**constants)`` in place of a model.

    ``eigenvalues``: complex $p_k = -\zeta_k + i\omega_k$ of the lowest modes in order of
    frequency (the modes with $\omega > 0$ of :func:`rbo_jax.lattice.spectrum`; a rod of
    circular section has each bending frequency twice, one per plane: list both); a real part
    that was not measured is NaN (only the frequency counts). ``sigma``: the noise level of each
    measured real and imaginary part (None: unknown, estimated from the residuals by the fit;
    the posterior needs it). ``at_rest``: linearise about the straight state at rest, else
    about the equilibrium under the rod's loads (Newton, differentiated implicitly)."""

    target: jax.Array
    mask: jax.Array
    sigma: float | None = eqx.field(static=True)
    at_rest: bool = eqx.field(static=True)

    def __init__(self, eigenvalues, *, sigma=None, at_rest: bool = True):
        p = np.atleast_1d(np.asarray(eigenvalues, dtype=complex))
        if p.ndim != 1 or p.size == 0:
            raise ValueError(f"eigenvalues must be a non-empty 1-D array, got shape {p.shape}.")
        if not np.all(np.isfinite(p.imag)) or np.any(p.imag <= 0):
            raise ValueError("eigenvalues: each needs a measured frequency Im p > 0.")
        if np.any(np.isinf(p.real)):
            raise ValueError("eigenvalues: a real part is finite, or NaN (not measured).")
        measured = np.where(np.isfinite(p.real), p.real, 0.0)  # masked where not measured
        self.target = jnp.asarray(np.stack([measured, p.imag], axis=1))
        self.mask = jnp.asarray(np.stack([np.isfinite(p.real), np.ones(p.size, bool)], axis=1))
        self.sigma = _check_sigma("RodSpectrumData", sigma)
        self.at_rest = bool(at_rest)

    def problem(self, rod_fn, names, **solve_options) -> Residuals:
        """The fit's :class:`Residuals` (``solve_options`` do not apply: no motion)."""
        residuals = jax.tree_util.Partial(_spectrum_residuals, self.at_rest)
        return Residuals(rod_fn, names, residuals, (self.target, self.mask), self.sigma)


class RodTrajectoryData(AbstractMeasurements):
    r"""Measured positions (T, 3) of one body of a rod (``body``, the tip by default) at the
    times ``ts`` (T,), the motion starting from ``state0`` (a :class:`RodState` at ``ts[0]``,
    held fixed: e.g. a measured deflected shape at rest): what :func:`fit_trajectory` fits, and
    what :func:`rbo_jax.fit`, :func:`rbo_jax.profile_likelihood` and :func:`rbo_jax.posterior`
    take with a rod function. NaN in a position (a sample or one coordinate of it) means not
    measured. ``sigma``: the noise level of each coordinate (None: unknown, estimated from the
    residuals by the fit; the posterior needs it)."""

    ts: jax.Array
    positions: jax.Array
    mask: jax.Array
    state0: RodState
    body: int = eqx.field(static=True)
    sigma: float | None = eqx.field(static=True)

    def __init__(self, ts, positions, state0, *, body: int = -1, sigma=None):
        ts = np.asarray(ts, dtype=float)
        x = np.asarray(positions, dtype=float)
        if ts.ndim != 1 or ts.size < 2 or not np.all(np.diff(ts) > 0):
            raise ValueError("ts must be a strictly increasing 1-D array of at least 2 times.")
        if x.shape != (ts.size, 3) or not np.any(np.isfinite(x)) or np.any(np.isinf(x)):
            raise ValueError(
                f"positions must have shape {(ts.size, 3)} (one row per time), finite or NaN "
                f"(not measured), not all NaN; got shape {x.shape}."
            )
        if not isinstance(state0, RodState):
            raise TypeError(f"state0 must be a RodState, got {type(state0).__name__}.")
        self.ts = jnp.asarray(ts)
        self.positions = jnp.asarray(np.where(np.isfinite(x), x, 0.0))  # masked where NaN
        self.mask = jnp.asarray(np.isfinite(x))
        self.state0 = jax.tree_util.tree_map(jnp.asarray, state0)
        self.body = int(body)
        self.sigma = _check_sigma("RodTrajectoryData", sigma)

    def problem(self, rod_fn, names, *, solver=None, rtol=1e-8, atol=1e-10, max_steps=100_000):
        """The fit's :class:`Residuals`: the diffrax solve of :func:`rbo_jax.lattice.simulate`
        (``solver`` default ``Dopri8``), differentiated in forward mode."""
        solver = diffrax.Dopri8() if solver is None else solver
        dt0 = float(self.ts[1] - self.ts[0]) / 10.0
        settings = (solver, float(rtol), float(atol), int(max_steps), dt0, self.body)
        residuals = jax.tree_util.Partial(_trajectory_residuals, settings)
        data = (self.ts, self.positions, self.mask, self.state0)
        return Residuals(rod_fn, names, residuals, data, self.sigma)


def fit_spectrum(
    rod_fn: Callable,
    params: Mapping[str, float],
    eigenvalues,
    *,
    at_rest: bool = True,
    sigma: float | None = None,
    tol: float = 1e-12,
    max_steps: int = 100,
) -> RodFit:
    r"""Fit ``params`` (name -> starting value > 0) so that the rod ``rod_fn(**params)`` has the
    measured ``eigenvalues`` (complex, lowest modes in order of frequency, NaN real part where
    only the frequency was measured), linearised ``at_rest`` or about its loaded equilibrium,
    with the noise level ``sigma`` of each number where known: see :class:`RodSpectrumData`.
    ``tol``, ``max_steps``: as :func:`rbo_jax.fit`. Returns a :class:`RodFit` with standard
    errors: Gauss–Newton, $s^2 = 1$ with ``sigma``, else the residual variance over the
    measured numbers (which also give ``rms``). The same as
    ``rbo_jax.fit(rod_fn, RodSpectrumData(eigenvalues, ...), params)``."""
    data = RodSpectrumData(eigenvalues, sigma=sigma, at_rest=at_rest)
    return fit_constants(rod_fn, data, params, tol=tol, max_fit_steps=max_steps)


def fit_trajectory(
    rod_fn: Callable,
    params: Mapping[str, float],
    ts,
    positions,
    state0: RodState,
    *,
    body: int = -1,
    sigma: float | None = None,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    tol: float = 1e-12,
    max_fit_steps: int = 100,
) -> RodFit:
    r"""Fit ``params`` (name -> starting value > 0, fitted as logarithms) so that the motion of
    ``rod_fn(**params)`` from ``state0`` passes through the measured ``positions`` (T, 3; NaN:
    not measured) of one body (``body``, the tip by default) at the times ``ts``: see
    :class:`RodTrajectoryData`, which also takes the noise level ``sigma`` where known.

    The residuals are the simulated positions (:func:`rbo_jax.lattice.simulate`'s diffrax solve,
    ``solver`` default ``Dopri8`` with ``rtol``, ``atol``, ``max_steps``) minus the measured
    ones; Levenberg–Marquardt (:func:`rbo_jax.fit`'s) with forward-mode derivatives through the
    solve (``diffrax.ForwardMode``: one tangent per parameter); ``tol``, ``max_fit_steps``: its
    tolerance and iterations. Standard errors: Gauss–Newton, $s^2 (J^TJ)^{-1}$ with $s^2 = 1$
    where ``sigma`` is given, else the residual variance $|r|^2/(m - p)$ over the $m$ measured
    coordinates, by the delta method. Returns a :class:`RodFit` (``rms`` in the positions'
    units). The same as ``rbo_jax.fit(rod_fn, RodTrajectoryData(ts, positions, state0, ...),
    params)``."""
    data = RodTrajectoryData(ts, positions, state0, body=body, sigma=sigma)
    options = dict(solver=solver, rtol=rtol, atol=atol, max_steps=max_steps)
    return fit_constants(rod_fn, data, params, tol=tol, max_fit_steps=max_fit_steps, **options)
