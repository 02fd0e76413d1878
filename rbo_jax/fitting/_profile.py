r""":func:`profile_likelihood`: the profile of the negative log-likelihood along one parameter,
every other fitted quantity re-fitted at each value.

For the whitened residuals $r(u)$ of :func:`rbo_jax.fit` (Gaussian noise with the data's
$\sigma$), the negative log-likelihood is

$$\ell(u) = \tfrac12 \sum_i r_i^2 + \sum_i \log\big(\sigma_i\sqrt{2\pi}\big),$$

the sum over the observed residual components (missing samples do not count). The profile of a
parameter $p$ is $\ell_p(v) = \min_{u:\,p = v} \ell(u)$, the others (and the gyroscope's bias and
the initial states) re-fitted. By Wilks' theorem $2(\ell_p(v) - \min \ell)$ is asymptotically
$\chi^2_1$, so the interval of level $1 - \alpha$ is where
$\ell_p(v) - \min\ell \le \chi^2_{1,1-\alpha}/2$ (1.92 at 95 %). Unlike $\pm 1.96$ standard
errors it follows the likelihood where it is not quadratic: a weakly excited axis, a damping of
a few percent near zero.

The re-fits are Levenberg–Marquardt iterations in JAX (:func:`rbo_jax.solvers.levenberg_marquardt`)
with forward-mode Jacobians through the ODE solves, one lane per value, in one program compiled
once for all values (``lax.map`` over them: a ``vmap`` measured far slower on CPU, see
:func:`_refit`). Each lane starts from the fit's optimum moved along the
Gauss–Newton prediction $u_f = u_f^* - H_{ff}^{-1} H_{fp}(u_p - u_p^*)$.
"""

from __future__ import annotations

import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..solvers import levenberg_marquardt, value_and_jacfwd
from ._fit import fit, setup
from ._residuals import (
    SensorResiduals,
    leaf_at,
    observed_components,
    param_names,
    scalar_names,
    transform,
    unpack,
)
from .constants import fit_constants, is_measurements

__all__ = ["profile_likelihood"]


def _which(name, names, values) -> int:
    scalars = scalar_names(names, values)
    if name not in scalars:
        raise ValueError(f"name must be one of the fitted parameters {scalars}, got {name!r}.")
    return scalars.index(name)


def _fixed_values(values, transform_name, name) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 1 or v.size < 2 or not np.all(np.isfinite(v)):
        raise ValueError(f"values must be a 1-D array of at least 2 finite values of {name}.")
    if transform_name in ("log", "softplus") and not np.all(v > 0):
        raise ValueError(f"values of {name} must be positive (it is fitted as {transform_name}).")
    return v


@eqx.filter_jit
def _at_optimum(x, problem):
    """The residuals and their Jacobian at the fit's optimum (all coordinates)."""
    return value_and_jacfwd(problem, x)


@eqx.filter_jit
def _refit(x_free0, fixed, k, problem, max_steps, tol):
    """The re-fit at each fixed value, in one program: ``(x_free, F, converged, num_steps)``; the
    unknowns are the flat coordinates x of ``problem`` (residuals of x) but the ``k``-th."""

    def evaluate(x_free, xk):
        return value_and_jacfwd(lambda z: problem(jnp.insert(z, k, xk)), x_free)

    def one(lane):
        x_free, xk = lane
        return levenberg_marquardt(lambda y: evaluate(y, xk), x_free, max_steps=max_steps, tol=tol)

    # one lane after another in the compiled program: a vmap of the ODE solves' forward-mode
    # Jacobians runs every lane for the longest lane's iterations and steps, measured ~30x
    # slower on CPU (issue 51's closing note)
    return jax.lax.map(one, (x_free0, fixed))


def _predicted_starts(J, x_star, k, fixed) -> np.ndarray:
    """The free coordinates at each fixed value by the Gauss–Newton prediction
    $u_f = u_f^* - H_{ff}^{-1} H_{fk} (u_k - u_k^*)$, $H = J^TJ$."""
    H = J.T @ J
    free = np.delete(np.arange(x_star.size), k)
    slope = np.linalg.lstsq(H[np.ix_(free, free)], H[free, k], rcond=None)[0]
    return x_star[free][None, :] - (fixed - x_star[k])[:, None] * slope[None, :]


def _interval(v, delta, threshold, estimate):
    """The χ² interval from the profile: where Δℓ crosses the threshold on each side of the
    estimate (NaN where it does not cross), interpolated linearly in the root √(2Δℓ) between
    the bracketing values: exact where the profile is quadratic, however coarse the values
    (interpolating Δℓ itself, convex, puts the bound short: 1.57 for 1.645 standard errors on
    values 1 standard error apart)."""
    order = np.argsort(v)
    v, root = v[order], np.sqrt(2.0 * np.maximum(delta[order], 0.0))
    target = np.sqrt(2.0 * threshold)
    bounds = []
    for side in (-1, 1):
        idx = np.flatnonzero(v < estimate)[::-1] if side < 0 else np.flatnonzero(v > estimate)
        bound, prev = np.nan, (estimate, 0.0)
        for i in idx:
            if np.isfinite(root[i]) and root[i] >= target:
                (v0, r0), (v1, r1) = prev, (v[i], root[i])
                bound = v0 + (target - r0) * (v1 - v0) / (r1 - r0)
                break
            prev = (v[i], root[i])
        bounds.append(bound)
    return bounds


def _profile(problem, x_star, k, fixed, v, estimate, observed, level, max_steps, tol):
    """The profile of the coordinate ``k`` of ``problem`` at the ``fixed`` values of it (``v``
    in natural units): the re-fitted coordinates (one row per value, all of them), the
    negative log-likelihood, and the attributes of the result. ``observed``: (count, sigma) of
    each channel (sigma None: the residual scale is estimated at the optimum)."""
    r, J = (np.asarray(a) for a in _at_optimum(jnp.asarray(x_star), problem))
    m = sum(count for count, _ in observed)
    known = all(sigma is not None for _, sigma in observed)
    scale = 1.0 if known else float(np.sqrt(float(r @ r) / max(m - x_star.size, 1)))
    const = sum(c * np.log((sigma or scale) * np.sqrt(2 * np.pi)) for c, sigma in observed)
    starts = jnp.asarray(_predicted_starts(J, x_star, k, fixed))
    x_free, F, ok, steps = _refit(starts, jnp.asarray(fixed), k, problem, max_steps, tol)
    nll = np.asarray(F) / scale**2 + const
    nll_min = min(0.5 * float(r @ r) / scale**2 + const, float(np.nanmin(nll)))
    threshold = statistics.NormalDist().inv_cdf((1 + level) / 2) ** 2 / 2
    lower, upper = _interval(v, nll - nll_min, threshold, estimate)
    full = np.insert(np.asarray(x_free), k, fixed, axis=1)
    attrs = dict(
        estimate=estimate,
        level=level,
        threshold=threshold,
        lower=lower,
        upper=upper,
        min_neg_log_likelihood=nll_min,
        sigma_scale=scale,
    )
    return full, nll, nll_min, np.asarray(ok), np.asarray(steps), attrs


def _finish(ds, name, stderr, nll, nll_min, ok, steps, attrs, t_start):
    """The profile's common variables and attributes, added to ``ds``."""
    ds["neg_log_likelihood"] = ("value", nll, {"long_name": "negative log-likelihood"})
    ds["delta"] = ("value", nll - nll_min, {"long_name": "neg_log_likelihood - its minimum"})
    ds["converged"] = ("value", ok)
    ds["num_steps"] = ("value", steps)
    ds.attrs.update(parameter=name, stderr=stderr, **attrs)
    ds.attrs["wall_time"] = time.perf_counter() - t_start
    return ds


def profile_likelihood(
    model,
    data,
    params,
    name: str,
    values,
    *,
    level: float = 0.95,
    fit_initial_state: bool = True,
    transforms=None,
    start=None,
    max_steps: int = 30,
    tol: float = 1e-10,
    solve_rtol: float = 1e-10,
    solve_atol: float = 1e-10,
    solve_max_steps: int = 100_000,
):
    r"""The profile likelihood of the parameter ``name`` at ``values`` (see the module
    docstring), and its interval of level ``level`` by the $\chi^2_1$ threshold.

    **Arguments:** `model`, `data`, `params`, `transforms`, `fit_initial_state`, `solve_*` as for
    :func:`rbo_jax.fit` (the initial states and the gyroscope's bias, where the data fits it,
    are re-fitted too by default); `name`: the profiled parameter as the fit names it
    (``"foundation.c"``, ``"loads[0].b"``, ``"inertia[1]"``); `values`: its values (natural
    units), at least two; `start`: a :class:`rbo_jax.FitResult` of the same problem (else
    :func:`rbo_jax.fit` runs first); `max_steps`, `tol`: of the re-fits.

    **A rod** (:mod:`rbo_jax.lattice`): `model` is a function ``rod_fn(**constants)`` building
    the rod, `data` a :class:`rbo_jax.lattice.RodSpectrumData` (measured eigenvalues) or
    :class:`rbo_jax.lattice.RodTrajectoryData` (a body's measured positions), `params` the
    constants' starting values by name (``{"EI": 1.0, "eta": 1e-3}``, all positive, fitted as
    logarithms), `name` one of them, `start` a :class:`rbo_jax.lattice.RodFit`; the other
    constants are re-fitted at each value. `solve_*` apply to a trajectory's solve;
    `transforms` and `fit_initial_state` do not apply (the start is measured).

    **Returns** an :class:`xarray.Dataset` over the dimension ``value`` (coordinate: the values
    of ``name``): ``neg_log_likelihood`` ($\ell_p$), ``delta`` ($\ell_p - \min\ell$), the
    re-fitted parameters under their names, ``Omega_bias`` (``value``, ``component``) where
    fitted, ``theta0`` and ``Omega0`` (``value``, ``experiment``, ``component``) where fitted,
    ``converged`` and ``num_steps`` per value. Attributes: ``parameter``, ``estimate``,
    ``stderr`` (Gauss–Newton), ``level``, ``threshold`` ($\chi^2_{1,level}/2$), ``lower``,
    ``upper`` (NaN where the profile does not cross the threshold within ``values``: widen
    them), ``min_neg_log_likelihood``, ``sigma_scale`` (1, or the residual scale estimated by
    the fit where the data give no ``sigma_*``), ``wall_time``.
    """
    t_start = time.perf_counter()
    _check(level, max_steps)
    solve = dict(solve_rtol=solve_rtol, solve_atol=solve_atol, solve_max_steps=solve_max_steps)
    if is_measurements(data):
        return _rod_profile(model, data, params, name, values, level, start, max_steps, tol, solve)
    options = dict(transforms=transforms, fit_initial_state=fit_initial_state, **solve)
    datas, spec, _ = setup(model, data, params, **options)
    names = param_names(spec)
    natural0 = tuple(np.asarray(leaf_at(model, p)) for p in spec.paths)
    k = _which(name, names, natural0)
    owner = int(np.searchsorted(np.cumsum([np.size(x) for x in natural0]), k, side="right"))
    v = _fixed_values(values, spec.transforms[owner], name)
    result = start if start is not None else fit(model, datas, params, **options)
    x_star, unravel = ravel_pytree(result.unconstrained)
    x_star = np.asarray(x_star, dtype=np.float64)
    fixed = np.array([transform(spec.transforms[owner], x) for x in v])
    estimate = float(np.concatenate([np.ravel(p) for p in result.params])[k])
    problem = SensorResiduals(model, tuple(datas), result.unconstrained, spec)
    full, nll, nll_min, ok, steps, attrs = _profile(
        problem, x_star, k, fixed, v, estimate, observed_components(datas), level, max_steps, tol
    )
    ds = _dataset([unravel(jnp.asarray(x)) for x in full], model, datas, spec, name, v)
    stderr = float(np.concatenate([np.ravel(s) for s in result.stderr])[k])
    return _finish(ds, name, stderr, nll, nll_min, ok, steps, attrs, t_start)


def _rod_profile(rod_fn, data, params, name, values, level, start, max_steps, tol, solve):
    """The profile of a rod's constant (``data`` a rod's measurements, ``params`` the starting
    values by name): the same result as a rigid body's."""
    import xarray as xr

    t_start = time.perf_counter()
    names = tuple(sorted(params))
    if name not in names:
        raise ValueError(f"name must be one of the fitted parameters {list(names)}, got {name!r}.")
    k = names.index(name)
    v = _fixed_values(values, "log", name)
    options = dict(rtol=solve["solve_rtol"], atol=solve["solve_atol"])
    options["max_steps"] = solve["solve_max_steps"]
    result = start if start is not None else fit_constants(rod_fn, data, params, tol=tol, **options)
    problem = data.problem(rod_fn, names, **options)
    observed = [(int(np.sum(np.asarray(data.mask))), data.sigma)]
    x_star = np.asarray(result.unconstrained, dtype=np.float64)
    full, nll, nll_min, ok, steps, attrs = _profile(
        problem, x_star, k, np.log(v), v, result.params[name], observed, level, max_steps, tol
    )
    ds = xr.Dataset(coords={"value": ("value", v, {"long_name": name})})
    for i, other in enumerate(names):
        if other != name:
            ds[other] = ("value", np.exp(full[:, i]))
    return _finish(ds, name, result.stderr[name], nll, nll_min, ok, steps, attrs, t_start)


def _check(level, max_steps):
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level!r}.")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}.")


def _dataset(us, model, datas, spec, name, v):
    """The re-fitted quantities of each lane as an :class:`xarray.Dataset` over ``value``."""
    import xarray as xr

    lanes = [unpack(u, model, len(datas), spec) for u in us]
    names = scalar_names(param_names(spec), lanes[0][1])
    flat = np.array([np.concatenate([np.ravel(np.asarray(x)) for x in n]) for _, n, _ in lanes])
    ds = xr.Dataset(coords={"value": ("value", v, {"long_name": name})})
    for i, other in enumerate(names):
        if other != name:
            ds[other] = ("value", flat[:, i])
    if spec.fit_bias:
        ds["Omega_bias"] = (("value", "component"), np.array([np.asarray(u["p_bias"]) for u in us]))
    if spec.fit_initial_state:
        for j, key in enumerate(("theta0", "Omega0")):
            ds[key] = (
                ("value", "experiment", "component"),
                np.array([[np.asarray(s[j]) for s in u["x0"]] for u in us]),
            )
    return ds
