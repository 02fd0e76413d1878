r"""Fitting a rod's constants to its measured eigenvalues: frequencies and decay rates.

A rod's small vibrations about its state at rest (or about its equilibrium under its loads) have
the eigenvalues $p_k = -\zeta_k + i\,\omega_k$ of :func:`rbo_jax.lattice.spectrum`. Given measured
$p_k$ of the lowest modes (a frequency alone when the decay was not measured), the constants
$EI$, $GJ$, the Kelvin–Voigt time $\eta$, ... are fitted by the Levenberg–Marquardt iteration
of :func:`rbo_jax.fit` (:func:`rbo_jax.fitting._least_squares.run_least_squares`) around one
compiled program, the residuals and their forward-mode Jacobian through the eigenvalue problem
(and through the Newton solve of the equilibrium, by the implicit function theorem, when the rod
is loaded). Every parameter is positive and fitted as its logarithm; its standard error is the
Gauss–Newton one, $s^2 (J^TJ)^{-1}$ with $s^2$ the residual variance, carried to the parameter
by the delta method.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..fitting._least_squares import run_least_squares
from ..fitting._residuals import jacobian_matrix
from ._fit import _residuals_and_jacobian, _start
from ._rod_dynamics import linearize
from ._rod_statics import solve_equilibrium

__all__ = ["RodFit", "fit_spectrum"]


class RodFit(eqx.Module):
    """The result of :func:`fit_spectrum`: ``params`` and ``stderr`` (name -> value), ``rms``
    (of the residuals at the solution, in the eigenvalues' units), ``num_steps``,
    ``converged``, ``message``."""

    params: dict
    stderr: dict
    rms: float
    num_steps: int
    converged: bool
    message: str = eqx.field(static=True)


def _lowest(p, count):
    """The ``count`` eigenvalues with the smallest positive imaginary parts, ascending."""
    key = jnp.where(p.imag > 1e-9 * jnp.max(jnp.abs(p)), p.imag, jnp.inf)
    return p[jnp.argsort(key)[:count]]


def _spectrum_residuals(rod_fn, at_rest, u, data):
    target, mask = data
    rod = rod_fn(**{k: jnp.exp(v) for k, v in u.items()})
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
    ``max_steps``: as :func:`rbo_jax.fit`. Returns a :class:`RodFit` with standard errors."""
    u0 = _start(params)
    p = np.atleast_1d(np.asarray(eigenvalues, dtype=complex))
    if p.ndim != 1 or p.size == 0:
        raise ValueError(f"fit_spectrum: eigenvalues must be a 1-D array, got shape {p.shape}.")
    if not np.all(np.isfinite(p.imag)) or np.any(p.imag <= 0):
        raise ValueError("fit_spectrum: every eigenvalue needs a measured frequency Im p > 0.")
    target = np.stack([np.nan_to_num(p.real), p.imag], axis=1)
    mask = np.stack([np.isfinite(p.real), np.ones(p.size, bool)], axis=1)
    data = (jnp.asarray(target), jnp.asarray(mask))
    residuals = jax.tree_util.Partial(_spectrum_residuals, rod_fn, bool(at_rest))

    def evaluate(u):
        return _residuals_and_jacobian(residuals, u, data)

    u, steps, converged, message = run_least_squares(
        evaluate, u0, "levenberg_marquardt", tol, max_steps, []
    )
    r, J_tree = evaluate(u)
    r = np.asarray(r, dtype=float)
    J = jacobian_matrix(J_tree, r.size)
    dof = max(int(mask.sum()) - len(u), 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    values = {k: float(np.exp(v)) for k, v in u.items()}
    names = sorted(u)  # jacobian_matrix flattens the tree in key order
    stderr = {k: values[k] * float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(names)}
    return RodFit(
        params=values,
        stderr=stderr,
        rms=float(np.sqrt(np.mean(r[mask.ravel()] ** 2))),
        num_steps=int(steps),
        converged=bool(converged),
        message=message,
    )
