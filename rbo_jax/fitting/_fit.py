""":func:`fit` and its result :class:`FitResult`."""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings
from collections.abc import Callable, Sequence

import equinox as eqx
import numpy as np

from .._progress import progress_bar
from ..models.rigid_body import RigidBodyOscillator
from ..solvers import gauss_newton_covariance, run_least_squares
from ._data import TrajectoryData
from ._residuals import (
    INTEGRATORS,
    Spec,
    leaf_paths,
    observed_count,
    param_names,
    residuals_and_jacobian,
    resolve_transforms,
    scalar_names,
    transform,
    transform_derivative,
    unpack,
)
from .constants import fit_constants, is_measurements

__all__ = ["FitResult", "fit"]

OPTIMIZERS = ("levenberg_marquardt", "gauss_newton", "adam", "lbfgs")
LEAST_SQUARES = ("levenberg_marquardt", "gauss_newton")


class FitResult(eqx.Module):
    """Result of :func:`fit`.

    ``model``: the fitted model; ``params``: fitted values of the selected parameters (tuple, in
    the order of the selector); ``stderr``: their standard errors (same structure);
    ``covariance``: covariance of all fitted scalars (flattened: parameters, the gyroscope's
    bias, initial states); ``initial_states``: fitted or given ``(theta0, Omega0)`` per
    trajectory; ``loss_history``: the loss ½Σr² after each iteration (every stage);
    ``num_steps``; ``converged``; ``message``; ``residual_rms`` (the rms of the whitened
    residuals over the observed components: near 1 where the model and the noise levels are
    right; missing samples do not count); ``wall_time`` (seconds, compilation included).

    ``Omega_bias``, ``Omega_bias_standard_errors``: the gyroscope's fitted constant bias (3,)
    (body frame, rad/s) and its standard errors, where some data asked for it
    (``TrajectoryData(..., Omega_bias="fit")``), else None. ``names``: the parameters' names,
    their paths in the model (``"foundation.c"``, ``"loads[0].b"``). ``unconstrained``: the
    optimum in the coordinates the fit iterates on (log/softplus of the parameters).
    """

    model: RigidBodyOscillator
    params: tuple
    stderr: tuple
    covariance: np.ndarray
    initial_states: tuple
    loss_history: np.ndarray
    num_steps: int
    converged: bool
    message: str
    residual_rms: float
    wall_time: float
    names: tuple = ()
    Omega_bias: np.ndarray | None = None
    Omega_bias_standard_errors: np.ndarray | None = None
    unconstrained: dict | None = None

    def to_xarray(self, names: Sequence[str] | None = None, **attrs):
        """The result as an :class:`xarray.Dataset`: ``estimate`` and ``stderr`` over the
        dimension ``parameter`` (scalar parameters, named by ``names`` or by their paths in the
        model, ``foundation.c``; ``inertia[0]`` for an element of an array),
        ``covariance`` over (``parameter``, ``parameter_2``) of the fitted scalars,
        ``loss_history`` over ``iteration``; attributes ``converged``, ``message``,
        ``num_steps``, ``residual_rms``, ``wall_time`` plus ``attrs``."""
        import xarray as xr

        values = np.concatenate([np.ravel(p) for p in self.params])
        errors = np.concatenate([np.ravel(s) for s in self.stderr])
        names = list(names) if names is not None else scalar_names(self.names, self.params)
        if len(names) != values.size:
            raise ValueError(f"names has {len(names)} entries for {values.size} fitted scalars.")
        n_cov = self.covariance.shape[0]
        bias = [] if self.Omega_bias is None else [f"Omega_bias[{i}]" for i in range(3)]
        labels = names + bias
        labels += [f"initial_state_{i}" for i in range(n_cov - len(labels))]
        ds = xr.Dataset(
            {
                "estimate": ("parameter", values, {"long_name": "fitted value"}),
                "stderr": (
                    "parameter",
                    errors,
                    {"long_name": "Gauss-Newton standard error, s^2 (J^T J)^-1"},
                ),
                "covariance": (("parameter_all", "parameter_all_2"), self.covariance),
                "loss_history": (
                    "iteration",
                    np.asarray(self.loss_history),
                    {"long_name": "1/2 sum r^2 of the whitened residuals"},
                ),
            },
            coords={"parameter": names, "parameter_all": labels, "parameter_all_2": labels},
        )
        ds.attrs.update(
            converged=int(self.converged),
            message=self.message,
            num_steps=int(self.num_steps),
            residual_rms=float(self.residual_rms),
            wall_time=float(self.wall_time),
            **attrs,
        )
        return ds


def _as_data_list(data) -> list[TrajectoryData]:
    if isinstance(data, TrajectoryData):
        return [data]
    data = list(data)
    if not data:
        raise ValueError("data is empty: give one or more TrajectoryData.")
    for i, d in enumerate(data):
        if not isinstance(d, TrajectoryData):
            raise TypeError(f"data[{i}] must be a TrajectoryData, got {type(d).__name__}.")
    return data


def _check_options(optimizer, horizons, max_steps, solve_max_steps):
    if optimizer not in OPTIMIZERS:
        raise ValueError(
            f"optimizer must be one of {', '.join(map(repr, OPTIMIZERS))}, got {optimizer!r}."
        )
    horizons = tuple(float(h) for h in horizons)
    if (
        not horizons
        or any(not (0 < h <= 1) for h in horizons)
        or list(horizons) != sorted(horizons)
    ):
        raise ValueError(f"horizons must be increasing fractions in (0, 1], got {horizons}.")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}.")
    if solve_max_steps < 1:
        raise ValueError(f"solve_max_steps must be >= 1, got {solve_max_steps}.")
    return horizons


def _integrator(integrator, optimizer) -> str:
    """The ODE integrator of a fit: by default fast_simulate (forward mode) for the
    least-squares optimizers, simulate (reverse mode) for the optax ones."""
    if integrator is None:
        return "fast_simulate" if optimizer in LEAST_SQUARES else "simulate"
    if integrator not in INTEGRATORS:
        raise ValueError(
            f"integrator must be one of {', '.join(map(repr, INTEGRATORS))}, got {integrator!r}."
        )
    if integrator == "fast_simulate" and optimizer not in LEAST_SQUARES:
        raise ValueError(
            f"optimizer {optimizer!r} needs reverse-mode gradients, which "
            "fast_simulate does not have: use integrator='simulate' (the default "
            "for it) or a least-squares optimizer."
        )
    return integrator


def _selected(model, params) -> tuple:
    try:
        values = params(model)
    except Exception as e:  # a selector that does not match the model
        raise ValueError(f"params selector failed on the model: {e}") from e
    values = tuple(values) if isinstance(values, (tuple, list)) else (values,)
    if not values or not all(eqx.is_inexact_array(v) for v in values):
        raise ValueError(
            "params must select float array leaves of the model (e.g. m.foundation.c)."
        )
    return values


def _covariance(u, model, datas, spec: Spec):
    """Gauss–Newton covariance at the optimum, w.r.t. the natural parameters: the Jacobian in
    the reparametrised coordinates u, times du/dx (chain rule); initial states are not
    reparametrised. Returns (residuals, covariance, standard errors per parameter, note)."""
    _, natural, _ = unpack(u, model, len(datas), spec)
    r, J = residuals_and_jacobian(u, model, datas, dataclasses.replace(spec, forward=True))
    r = np.asarray(r, dtype=np.float64)
    scale = [transform_derivative(n, x).ravel() for n, x in zip(spec.transforms, natural)]
    if spec.fit_bias:
        scale.append(np.ones(3))
    if spec.fit_initial_state:
        scale.append(np.ones(sum(np.size(x) for state in u["x0"] for x in state)))  # (θ0, Ω0)
    sigma_known = all(
        (d.sigma_theta is not None or (d.theta is None and d.Q is None))
        and (d.sigma_omega is not None or d.omega is None)
        and (d.sigma_Omega is not None or d.Omega is None)
        for d in datas
    )
    # s² = 1, or the residual variance over the observed components (missing samples give 0)
    measured = None if sigma_known else observed_count(datas)
    cov, se_flat, note = gauss_newton_covariance(r, J, np.concatenate(scale), measured)
    offsets = np.cumsum([0] + [int(np.size(x)) for x in natural])  # parameters come first in u
    se = tuple(
        se_flat[offsets[i] : offsets[i + 1]].reshape(np.shape(v)) for i, v in enumerate(natural)
    )
    bias_se = se_flat[offsets[-1] : offsets[-1] + 3] if spec.fit_bias else None
    return r, cov, se, bias_se, note


def _stages(u, model, datas, spec, horizons, optimizer, options, history, bar, verbose):
    """Run the optimiser on each horizon in turn; returns (u, steps, converged, message)."""
    total = 0
    converged, message = True, "converged"
    for h in horizons:
        stage = tuple(
            d if h >= 1.0 else d.truncate(float(d.t0) + h * (float(d.ts[-1]) - float(d.t0)))
            for d in datas
        )
        if optimizer in LEAST_SQUARES:  # one signature: (u, optimizer, tol, max_steps, ...)
            solver = functools.partial(
                run_least_squares, lambda v: residuals_and_jacobian(v, model, stage, spec)
            )
        else:
            from ._optax import run_optax  # optax: only for the first-order optimizers

            solver = functools.partial(run_optax, model, stage, spec, options["learning_rate"])
        u, steps, converged, message = solver(
            u, optimizer, options["tol"], options["max_steps"], history, bar, verbose
        )
        total += steps
    return u, total, converged, message


def setup(
    model,
    data,
    params,
    *,
    transforms=None,
    fit_initial_state=False,
    optimizer="levenberg_marquardt",
    solve_rtol=1e-10,
    solve_atol=1e-10,
    solve_max_steps=100_000,
    integrator=None,
):
    """The checked problem of a fit: ``(datas, spec, u)`` with ``u`` the starting point in the
    fit's unconstrained coordinates (``{"p": parameters, "p_bias": the gyroscope's bias,
    "x0": initial states}``, the last two where fitted). :func:`fit`,
    :func:`rbo_jax.posterior` and :func:`rbo_jax.profile_likelihood` all start here."""
    datas = tuple(_as_data_list(data))
    _check_options(optimizer, (1.0,), 1, solve_max_steps)
    if not fit_initial_state and any(d.initial_state_guessed for d in datas):
        warnings.warn(
            "an initial state was taken from a sample after t0 (the data's first samples are "
            "missing): give theta0 and Omega0, or fit them (fit_initial_state=True).",
            stacklevel=3,
        )
    integrator = _integrator(integrator, optimizer)
    values = _selected(model, params)
    spec = Spec(
        paths=leaf_paths(model, values),
        transforms=resolve_transforms(values, transforms),
        fit_initial_state=bool(fit_initial_state),
        rtol=float(solve_rtol),
        atol=float(solve_atol),
        forward=optimizer in LEAST_SQUARES,
        max_solver_steps=int(solve_max_steps),
        integrator=integrator,
        fit_bias=any(d.fit_Omega_bias for d in datas),
    )
    u = {"p": tuple(transform(n, v) for n, v in zip(spec.transforms, values))}
    if spec.fit_bias:  # the dict's keys sort as p, p_bias, x0: the order of the covariance
        u["p_bias"] = np.zeros(3)
    if fit_initial_state:
        u["x0"] = tuple((d.theta0, d.Omega0) for d in datas)
    return datas, spec, u


def fit(
    model: RigidBodyOscillator,
    data: TrajectoryData | Sequence[TrajectoryData],
    params: Callable[[RigidBodyOscillator], object],
    *,
    transforms: str | Sequence[str] | None = None,
    fit_initial_state: bool = False,
    optimizer: str = "levenberg_marquardt",
    max_steps: int = 100,
    learning_rate: float = 1e-2,
    tol: float = 1e-8,
    horizons: Sequence[float] = (1.0,),
    solve_rtol: float = 1e-10,
    solve_atol: float = 1e-10,
    solve_max_steps: int = 100_000,
    integrator: str | None = None,
    progress: bool = False,
    verbose: bool = False,
) -> FitResult:
    r"""Fit the parameters selected by ``params`` (and optionally the initial states) so that
    simulated trajectories match ``data``.

    **Arguments:**

    - `model`: the model with the starting values of the parameters.
    - `data`: a :class:`TrajectoryData` or a sequence of them (several experiments share the
      parameters; each has its own initial state).
    - `params`: selector of the parameters to fit, as for ``eqx.tree_at``:
      ``lambda m: (m.foundation.c, m.foundation.d)``; any float leaves of the model (foundation,
      loads such as ``m.loads[0].b``, ``m.inertia``).
    - `transforms`: per parameter ``"log"``, ``"softplus"`` or ``"identity"``; default log for
      positive starting values, identity otherwise.
    - `fit_initial_state`: also fit (θ0, Ω0) of every trajectory (starting from the data's).
    - `optimizer`: ``"levenberg_marquardt"`` (default) or ``"gauss_newton"`` (least squares),
      ``"adam"`` or ``"lbfgs"`` (optax, general losses).
    - `max_steps`: iterations per stage; `tol`: relative/absolute tolerance of the least-squares
      solvers (and the stagnation test); `learning_rate`: for Adam.
    - `horizons`: staged fitting on growing fractions of each record (see the package docstring).
    - `solve_rtol`, `solve_atol`: tolerances of the ODE solves; `solve_max_steps`: their step
      budget (a solve that exhausts it gives infinite residuals, which the optimizer rejects).
    - `integrator`: ``"fast_simulate"`` (DOP853, :func:`rbo_jax.fast_simulate`; the default of
      the least-squares optimizers, whose Jacobians are forward mode) or ``"simulate"`` (diffrax
      Dopri8; the default, and the only choice, of ``"adam"`` and ``"lbfgs"``, which need
      reverse mode). Both integrate the right form (4.55)–(4.56).
    - `progress`: tqdm bar over iterations; `verbose`: print the loss each iteration.

    Compiled programs are cached on the model's structure, the data's shapes and these options,
    so repeated fits (bootstrap, noise studies) compile once. **A rod**: `model` a function
    ``rod_fn(**constants)``, `data` :class:`rbo_jax.lattice.RodSpectrumData` (or
    ``RodTrajectoryData``), `params` starting values by name: a :class:`rbo_jax.lattice.RodFit`.
    """
    start = time.perf_counter()
    if is_measurements(data):
        solve = dict(rtol=solve_rtol, atol=solve_atol, max_steps=solve_max_steps, tol=tol)
        return fit_constants(model, data, params, max_fit_steps=max_steps, **solve)
    datas, spec, u = setup(
        model, data, params, transforms=transforms, fit_initial_state=fit_initial_state,
        optimizer=optimizer, solve_rtol=solve_rtol, solve_atol=solve_atol,
        solve_max_steps=solve_max_steps, integrator=integrator,
    )  # fmt: skip
    horizons = _check_options(optimizer, horizons, max_steps, solve_max_steps)
    history: list[float] = []
    with progress_bar(progress, max_steps * len(horizons), "fit", "it") as bar:
        u, steps, converged, message = _stages(
            u,
            model,
            datas,
            spec,
            horizons,
            optimizer,
            {"tol": tol, "max_steps": max_steps, "learning_rate": learning_rate},
            history,
            bar,
            verbose,
        )
    r, cov, se, bias_se, note = _covariance(u, model, datas, spec)
    fitted_model, natural, states = unpack(u, model, len(datas), spec)
    init_states = tuple(
        (np.asarray(d.theta0 if th0 is None else th0), np.asarray(d.Omega0 if Om0 is None else Om0))
        for d, (th0, Om0) in zip(datas, states)
    )
    return FitResult(
        model=fitted_model,
        params=tuple(np.asarray(v) for v in natural),
        stderr=se,
        covariance=cov,
        initial_states=init_states,
        loss_history=np.asarray(history),
        num_steps=int(steps),
        converged=bool(converged),
        message=message + note,
        residual_rms=float(np.sqrt(np.sum(r**2) / max(observed_count(datas), 1))),
        wall_time=time.perf_counter() - start,
        names=param_names(spec),
        Omega_bias=np.asarray(u["p_bias"]) if spec.fit_bias else None,
        Omega_bias_standard_errors=bias_se,
        unconstrained=u,
    )
