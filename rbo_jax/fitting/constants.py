r"""Fits of named positive constants of a model built by a function, ``model_fn(**constants)``:
a lattice's stiffnesses, a rod's (:mod:`rbo_jax.lattice`'s fits), fitted as their logarithms.

:class:`Residuals` is the problem: the whitened residuals as a function of the logarithms x.
:func:`least_squares` fits it (Levenberg–Marquardt of :func:`rbo_jax.solvers.run_least_squares`
around one compiled program of the residuals and their forward-mode Jacobian) with Gauss–Newton
standard errors, $s^2 (J^TJ)^{-1}$ carried to each constant by the delta method,
$\sigma_p = p\,\sigma_{\log p}$. Measurements that build their own problem
(:class:`AbstractMeasurements`: a rod's eigenvalues or trajectory, defined with the rods) are
what :func:`rbo_jax.fit`, :func:`rbo_jax.profile_likelihood` and :func:`rbo_jax.posterior` take
with a model function in place of a model: this module is the interface they meet, so that the
fitting layer never imports the models' own fits. It is public for that reason: the packages
above (:mod:`rbo_jax.lattice`) build their fits on it, not on a private module.
"""

from __future__ import annotations

import abc
import functools
from collections.abc import Callable, Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._programs import jit
from ..solvers import gauss_newton_covariance, run_least_squares, value_and_jacfwd

__all__ = [
    "AbstractMeasurements",
    "LatticeFit",
    "Residuals",
    "fit_constants",
    "is_measurements",
    "least_squares",
    "start_values",
]


class LatticeFit(eqx.Module):
    """The result of a fit of a lattice's or a rod's constants
    (:func:`rbo_jax.lattice.fit_dispersion`, :func:`rbo_jax.lattice.fit_field`,
    :func:`rbo_jax.lattice.fit_spectrum`, :func:`rbo_jax.lattice.fit_trajectory`, and
    :func:`rbo_jax.fit` of a rod's measurements; :class:`rbo_jax.lattice.RodFit` is this
    class): ``params`` and ``stderr`` (name -> fitted value, and its Gauss–Newton standard
    error), ``rms`` (the root mean square of the residuals at the solution, in the data's
    units), ``num_steps``, ``converged`` and ``message`` (how the iteration ended),
    ``unconstrained`` (the logarithms of the constants, in the order of the sorted names: where
    :func:`rbo_jax.profile_likelihood` and :func:`rbo_jax.posterior` start)."""

    params: dict
    stderr: dict
    rms: float
    num_steps: int
    converged: bool
    message: str = eqx.field(static=True)
    unconstrained: np.ndarray | None = None


class Residuals(eqx.Module):
    r"""The residuals of a fit of named positive constants, as a function of their logarithms
    $x$ (the sorted ``names``' order): ``residuals(model_fn(**dict(names, e^x)), data)``,
    divided by the data's noise level ``sigma`` (None: not given, 1). One object for every fit
    of named constants (a lattice's, a rod's), and what :func:`rbo_jax.profile_likelihood`
    and :func:`rbo_jax.posterior` differentiate: ``model_fn`` and the names are static, the
    data's arrays traced."""

    model_fn: Callable = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    residuals: Callable
    data: object
    sigma: float | None = eqx.field(static=True, default=None)

    def __call__(self, x):
        model = self.model_fn(**dict(zip(self.names, jnp.exp(x))))
        return self.residuals(model, self.data) / (self.sigma or 1.0)


def start_values(params: Mapping[str, float]):
    if not params:
        raise ValueError("lattice fit: params must name at least one parameter to fit.")
    values = {k: np.asarray(v, dtype=float) for k, v in params.items()}
    bad = [k for k, v in values.items() if v.shape != () or not (np.isfinite(v) and v > 0)]
    if bad:
        raise ValueError(
            "lattice fit: the starting values must be finite numbers > 0 (they "
            "are fitted as logarithms), got " + ", ".join(f"{k}={params[k]!r}" for k in bad) + "."
        )
    names = tuple(sorted(values))
    return names, np.log(np.array([values[k] for k in names]))


@functools.partial(jit, small=True)
def _residuals_and_jacobian(problem, x):
    """The one compiled program of a fit (per model function, residuals and data shapes): the
    residuals at the logarithms x of the constants, and their Jacobian by forward mode."""
    return value_and_jacfwd(problem, x)


def least_squares(problem: Residuals, x0, tol, max_steps, measured=None) -> LatticeFit:
    r"""Levenberg–Marquardt on ``problem`` (:class:`Residuals`) from the logarithms ``x0`` of the
    constants, then their Gauss–Newton standard errors: $s^2 = 1$ where the data give their
    noise level (``problem.sigma``), else $s^2 = |r|^2/(m - p)$ over the ``measured`` residuals
    (a mask; default all of them), which also give ``rms`` (in the data's units)."""

    def evaluate(x):
        return _residuals_and_jacobian(problem, x)

    x, steps, converged, message = run_least_squares(
        evaluate, jnp.asarray(x0), "levenberg_marquardt", tol, max_steps, []
    )
    r, J = evaluate(x)
    r = np.asarray(r, dtype=float)
    measured = np.ones(r.size, bool) if measured is None else np.asarray(measured)
    values = np.exp(np.asarray(x, dtype=float))
    known = problem.sigma is not None
    _, se, note = gauss_newton_covariance(r, J, 1.0 / values, None if known else measured.sum())
    return LatticeFit(
        params=dict(zip(problem.names, map(float, values))),
        stderr=dict(zip(problem.names, map(float, se))),
        rms=float(np.sqrt(np.mean(r[measured] ** 2)) * (problem.sigma or 1.0)),
        num_steps=int(steps),
        converged=bool(converged),
        message=message + note,
        unconstrained=np.asarray(x, dtype=float),
    )


class AbstractMeasurements(eqx.Module):
    """Measurements of a model built by a function ``model_fn(**constants)``, which build their
    own :class:`Residuals`: what :func:`rbo_jax.fit`, :func:`rbo_jax.profile_likelihood` and
    :func:`rbo_jax.posterior` accept in place of sensor records. A subclass has the fields
    ``mask`` (which residual components were measured, shaped as the residuals before
    flattening) and ``sigma`` (the noise level of each, or None)."""

    @abc.abstractmethod
    def problem(self, model_fn, names, **solve_options) -> Residuals:
        """The whitened residuals of ``model_fn`` with the constants ``names`` (sorted)."""


def is_measurements(data) -> bool:
    """Whether ``data`` are measurements of a model function (a rod's:
    :class:`rbo_jax.lattice.RodSpectrumData`, :class:`rbo_jax.lattice.RodTrajectoryData`)
    rather than sensor records of a rigid body."""
    return isinstance(data, AbstractMeasurements)


def fit_constants(model_fn, data, params, *, tol=1e-12, max_fit_steps=100, **solve_options):
    """Fit the constants ``params`` (name -> starting value > 0) of ``model_fn`` to ``data`` (an
    :class:`AbstractMeasurements`): :func:`rbo_jax.fit` of a rod's measurements. ``tol``,
    ``max_fit_steps``: Levenberg–Marquardt's; ``solve_options`` (``solver``, ``rtol``, ``atol``,
    ``max_steps`` of a trajectory's solve) go to ``data.problem``. Returns a
    :class:`LatticeFit`."""
    if not isinstance(data, AbstractMeasurements):
        raise TypeError(f"data must be measurements of a model, got {type(data).__name__}.")
    names, x0 = start_values(params)
    problem = data.problem(model_fn, names, **solve_options)
    return least_squares(problem, x0, tol, int(max_fit_steps), np.ravel(np.asarray(data.mask)))
