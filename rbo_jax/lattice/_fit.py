r"""Fitting a lattice's stiffnesses by gradients: to a measured dispersion curve, or to a recorded
space-time field of turn-vectors.

Both are nonlinear least squares, solved by the Levenberg–Marquardt iteration of
:func:`rbo_jax.fit` (:func:`rbo_jax.fitting._least_squares.run_least_squares`, on the host)
around one compiled program: the residuals and their forward-mode Jacobian, of the eigenvalues
of the Bloch matrix (:func:`rbo_jax.lattice.dispersion`) or of the lattice's motion (through the
DOP853 loop of :func:`rbo_jax.lattice.simulate`, or diffrax). Every fitted parameter is
positive and fitted as its logarithm (a stiffness, an inertia).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._programs import jit
from ..fitting._least_squares import run_least_squares
from ._dispersion import bloch_blocks, dispersion
from ._simulate import simulate

__all__ = ["LatticeFit", "fit_dispersion", "fit_field"]


class LatticeFit(eqx.Module):
    """The result of a fit: ``params`` (name -> fitted value), ``rms`` (the root mean square of
    the residuals at the solution, in the data's units), ``num_steps``, ``converged`` and
    ``message`` (how the iteration ended)."""

    params: dict
    rms: Float[Array, ""]
    num_steps: int
    converged: bool
    message: str = eqx.field(static=True)


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
def _residuals_and_jacobian(residuals, u, data):
    """The one compiled program of a lattice fit (per ``residuals`` function and data shapes)."""

    def both(v):
        r = residuals(v, data)
        return r, r

    J, r = jax.jacfwd(both, has_aux=True)(u)
    return r, J


def _solve(residuals, u0, data, tol, max_steps) -> LatticeFit:
    def evaluate(u):
        return _residuals_and_jacobian(residuals, u, data)

    u, steps, converged, message = run_least_squares(
        evaluate, u0, "levenberg_marquardt", tol, max_steps, []
    )
    r = np.asarray(evaluate(u)[0])
    return LatticeFit(
        params={k: float(np.exp(v)) for k, v in u.items()},
        rms=jnp.asarray(np.sqrt(np.mean(r * r))),
        num_steps=int(steps),
        converged=bool(converged),
        message=message,
    )


def _dispersion_residuals(lattice_fn, u, data):
    q, target, mask, branches, theta_eq = data
    lat = lattice_fn(**{k: jnp.exp(v) for k, v in u.items()})
    blocks = bloch_blocks(lat, theta_eq)
    lam = jax.vmap(lambda k: dispersion(lat, k, blocks=blocks))(q)
    w = jnp.sort(jnp.imag(lam)[:, 3:], axis=1)[:, branches]
    return jnp.ravel(jnp.where(mask, w - target, 0.0))


def _field_residuals(lattice_fn, options, u, data):
    ts, target, mask, theta0, Omega0 = data
    lat = lattice_fn(**{k: jnp.exp(v) for k, v in u.items()})
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
    Jacobian program then also differentiates the Bloch matrix with respect to the state, ~5x
    longer to compile — pass ``theta_eq`` where the equilibrium does not depend on the fitted
    parameters, e.g. ``np.zeros(3)`` at rest).
    ``tol``, ``max_steps``: as :func:`rbo_jax.fit` (the relative step size and the number of
    Levenberg–Marquardt iterations). One compiled program per ``lattice_fn`` and data shapes.
    Returns a :class:`LatticeFit`."""
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
    return _solve(
        jax.tree_util.Partial(_dispersion_residuals, lattice_fn), u0, data, tol, max_steps
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
    :class:`LatticeFit`."""
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
    return _solve(
        jax.tree_util.Partial(_field_residuals, lattice_fn, options), u0, data, tol, max_steps
    )
