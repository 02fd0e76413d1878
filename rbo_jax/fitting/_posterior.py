r""":func:`posterior`: the Bayesian posterior of a fit's parameters by NUTS (BlackJAX), through
the same whitened residuals as :func:`rbo_jax.fit`.

**The density.** With the whitened residuals $r(u)$ of every experiment (model minus observation
over the data's noise level $\sigma$; a missing sample contributes 0) the likelihood is Gaussian,
and the log posterior in the fit's unconstrained coordinates $u$ is

$$\log p(u \mid \text{data}) = -\tfrac12 |r(u)|^2 + \log\pi(u) + \text{const}.$$

$u$ holds the parameters in their transformed coordinates (log, softplus or identity, as
:func:`rbo_jax.fit` chooses them), the gyroscope's bias where some data fits it
(``Omega_bias="fit"``), and the initial state $(\theta_0, \Omega_0)$ of every experiment (always
sampled, nuisance parameters). The prior $\pi$ is a density **in u**: by default flat (improper)
on u, i.e. flat on log c for a log-transformed c (a scale-invariant $1/c$ prior in the natural
coordinate); ``priors`` adds log densities per name. As the prior is stated in u, the density in u
needs no Jacobian term. A flat prior on u gives a proper posterior where the data identify every
coordinate (the Gauss–Newton matrix $J^TJ$ is regular).

**The sampler.** :func:`rbo_jax.fit` (with ``fit_initial_state=True``) gives the optimum $u^*$;
the Gauss–Newton covariance $\Sigma = (J^TJ)^{-1}$ at $u^*$ (J: forward-mode Jacobian of r in
u) is factored, $\Sigma = LL^T$, and NUTS samples $z$ with $u = u^* + Lz$: the log density in z
differs from that in u by a constant, and the identity mass matrix in z is $\Sigma$ in u. Stan's
window adaptation (diagonal mass matrix in z, dual-averaging step size, ``num_warmup`` steps)
starts from there. Each chain starts at a draw of the Laplace approximation, $z_0 \sim N(0, I)$.

**Gradients.** ``integrator="fast_simulate"`` (DOP853 with forward-mode derivatives only): the
log likelihood is a ``jax.custom_vjp`` whose forward pass computes r and J by forward mode
(:func:`rbo_jax.solvers.value_and_jacfwd`, one tangent per scalar of u) and whose backward pass
is $-J^Tr$. ``integrator="simulate"`` (diffrax): reverse mode through the solve
(``RecursiveCheckpointAdjoint`` with a checkpoint per step), the records sampled from the
solve's dense output after it (:func:`rbo_jax.simulate`'s ``dense``) rather than saved inside its
loop; the step budget of these solves is 4 times the most steps an experiment takes at the
optimum, rounded up to a power of 2 (:func:`_dense_budget`), so a proposal that needs more is a
failed solve.

**Rods.** With a rod's measurements (:class:`rbo_jax.lattice.RodSpectrumData`,
:class:`rbo_jax.lattice.RodTrajectoryData`) the sampled coordinates are the logarithms of the
rod's constants; the problem is their whitened residuals
(:class:`rbo_jax.fitting.constants.Residuals`), the gradient $-J^Tr$ from forward mode.

**Chains** (:mod:`rbo_jax.fitting._sampler`) run in one program: split over the local devices
(``shard_map``, each device a ``vmap`` of its chains; ``chain_method="pmap"``) when the device
count divides ``chains``, else ``vmap``. Warmup and draws are one scan of one NUTS transition
(one compiled gradient): the transitions before ``num_warmup`` adapt, the later ones use the
adapted step size and mass matrix. The model's and the data's arrays are arguments of that
program, which is cached: a second data set of the same shapes compiles nothing.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .._progress import progress_bar
from ..solvers import value_and_jacfwd
from ._fit import fit, setup
from ._residuals import (
    INTEGRATORS,
    SensorResiduals,
    fast_trajectory,
    param_names,
    residuals_and_jacobian,
    unpack,
)
from ._sampler import run_chains
from .constants import fit_constants, is_measurements

__all__ = ["posterior"]

CHAIN_METHODS = ("auto", "pmap", "vmap")
_SIGMA_OF = (("theta", "sigma_theta"), ("Q", "sigma_theta"), ("omega", "sigma_omega"))
_SIGMA_OF += (("Omega", "sigma_Omega"),)


def _check_arguments(num_warmup, num_samples, chains, integrator, chain_method, progress_chunks):
    def integer(name, value, low):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}.")

    integer("num_warmup", num_warmup, 0)
    integer("num_samples", num_samples, 1)
    integer("chains", chains, 1)
    integer("progress_chunks", progress_chunks, 1)
    if integrator not in INTEGRATORS:
        raise ValueError(
            f"integrator must be one of {', '.join(map(repr, INTEGRATORS))}, got {integrator!r}."
        )
    if chain_method not in CHAIN_METHODS:
        raise ValueError(
            f"chain_method must be one of {', '.join(map(repr, CHAIN_METHODS))}, "
            f"got {chain_method!r}."
        )


def _check_installed():
    """BlackJAX and ArviZ come with the ``bayes`` extra: say so before anything runs."""
    import importlib.util

    missing = [m for m in ("blackjax", "arviz") if importlib.util.find_spec(m) is None]
    if missing:
        raise ImportError(
            f"rbo_jax.posterior needs {' and '.join(missing)}: pip install 'rbo_jax[bayes]'."
        )


def _check_sigmas(datas):
    """The likelihood is Gaussian with the data's noise levels: each observed channel needs
    its sigma."""
    for i, d in enumerate(datas):
        for channel, sigma in _SIGMA_OF:
            if getattr(d, channel) is not None and getattr(d, sigma) is None:
                raise ValueError(
                    f"data[{i}] observes {channel} without {sigma}: the posterior's likelihood "
                    f"needs the noise level of every observed channel (give {sigma}=...)."
                )


def _check_priors(priors, names, fit_bias, initial_state=True) -> dict:
    """``priors`` as a dict name -> callable, its names checked."""
    if priors is None:
        return {}
    if not isinstance(priors, dict):
        raise ValueError("priors must be a dict: name -> callable returning a log density.")
    known = list(names) + (["Omega_bias"] if fit_bias else [])
    known += ["initial_state"] if initial_state else []
    for name, f in priors.items():
        if name not in known:
            raise ValueError(
                f"priors names {name!r}, which is not sampled; choose from {', '.join(known)}."
            )
        if not callable(f):
            raise ValueError(f"priors[{name!r}] must be callable, got {type(f).__name__}.")
    return dict(priors)


def _log_prior(priors, names):
    """log π of the flat coordinates x of a problem: the sum of the given priors, each on its
    coordinates in u (transformed parameters, the bias, each experiment's (θ0, Ω0)); 0 (flat)
    for the rest. ``names``: a rod's constants (x holds their logarithms in this order), or
    None for sensor data (x is the fit's u flattened)."""

    def sensor_prior(problem, x):
        u = problem.unravel(x)
        total = jnp.zeros(())
        for name, value in zip(param_names(problem.spec), u["p"]):
            if name in priors:
                total = total + jnp.sum(priors[name](value))
        if "Omega_bias" in priors:
            total = total + jnp.sum(priors["Omega_bias"](u["p_bias"]))
        if "initial_state" in priors:
            for theta0, Omega0 in u["x0"]:
                total = total + jnp.sum(priors["initial_state"](theta0, Omega0))
        return total

    def named_prior(problem, x):
        total = jnp.zeros(())
        for i, name in enumerate(names):
            if name in priors:
                total = total + jnp.sum(priors[name](x[i]))
        return total

    return sensor_prior if names is None else named_prior


def _log_likelihood(problem, forward: bool):
    """-½|r(x)|² of the flat coordinates x of ``problem`` (its whitened residuals), differentiable
    in reverse mode: through the solve's adjoint (``forward=False``: diffrax), or a custom VJP
    whose forward pass is the forward-mode Jacobian (``fast_simulate``, a rod's few constants):
    the gradient is -Jᵀr."""
    if not forward:
        return lambda x: -0.5 * jnp.sum(problem(x) ** 2)

    @jax.custom_vjp
    def log_likelihood(x):
        return -0.5 * jnp.sum(problem(x) ** 2)

    def forward_pass(x):
        r, J = value_and_jacfwd(problem, x)
        return -0.5 * jnp.sum(r**2), -(J.T @ r)

    def backward(gradient, cotangent):
        return (cotangent * gradient,)

    log_likelihood.defvjp(forward_pass, backward)
    return log_likelihood


def _density(static, forward, log_prior):
    """``density(operands, z)``: log p(z) with x = x* + L z, the log likelihood plus the log
    prior, -inf where a solve failed (NUTS then rejects the step as divergent). The arrays
    (the problem's: the model's and the data's; x* and L) are the traced ``operands``, so one
    compiled sampler serves every data set of the same shapes."""

    def density(operands, z):
        dynamic, x_star, L = operands
        problem = eqx.combine(dynamic, static)
        x = x_star + L @ z
        value = _log_likelihood(problem, forward)(x) + log_prior(problem, x)
        return jnp.where(jnp.isfinite(value), value, -jnp.inf)

    return density


def _split(problem, x_star, L):
    """The arrays of the density (the ``operands``) and what stays static."""
    dynamic, static = eqx.partition(problem, eqx.is_array)
    return (dynamic, jnp.asarray(x_star), jnp.asarray(L)), static


def _cache_key(static, forward, priors, operands):
    """What a compiled sampler depends on: the static part of the problem (tree structure and
    non-array leaves: the model's and the data's, the spec), the gradient's kind, the priors
    (the functions themselves: held by the key, so never confused with a later function at the
    same address) and the operands' shapes and dtypes. None where something in it cannot be
    hashed (then nothing is cached)."""
    leaves, tree = jax.tree.flatten(static)
    shapes = tuple((np.shape(x), jnp.result_type(x)) for x in jax.tree.leaves(operands))
    key = (tree, tuple(leaves), forward, tuple((k, priors[k]) for k in sorted(priors)))
    key += (jax.tree.structure(operands), shapes)
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _log_density(model, datas, spec, priors, u_star, L):
    """log p(z) of one data set of sensor records, as a function of z alone."""
    problem = SensorResiduals(model, tuple(datas), u_star, spec)
    operands, static = _split(problem, ravel_pytree(u_star)[0], L)
    density = _density(static, spec.integrator == "fast_simulate", _log_prior(priors, None))
    return lambda z: density(operands, z)


def _covariance_factor(J):
    """The Gauss–Newton covariance (JᵀJ)⁻¹ and its Cholesky factor L, J a matrix."""
    w, V = np.linalg.eigh(J.T @ J)
    if not np.all(np.isfinite(w)) or w.min() <= 1e-12 * max(w.max(), 1e-300):
        raise ValueError(
            "the Gauss–Newton matrix JᵀJ at the fit's optimum is singular: the data do not "
            "identify every sampled coordinate, and the flat prior gives an improper posterior "
            "(fit fewer parameters, or give priors)."
        )
    cov = (V / w) @ V.T
    cov = 0.5 * (cov + cov.T)
    return cov, np.linalg.cholesky(cov)


def _laplace(model, datas, spec, u_star):
    """The Gauss–Newton covariance (JᵀJ)⁻¹ in u at the optimum and its Cholesky factor L."""
    r, J = residuals_and_jacobian(u_star, model, datas, dataclasses.replace(spec, forward=True))
    n = int(np.size(r))  # the Jacobian tree as a matrix, columns in the order of ravel_pytree
    return _covariance_factor(
        np.concatenate([np.asarray(b).reshape(n, -1) for b in jax.tree_util.tree_leaves(J)], 1)
    )


@eqx.filter_jit
def _steps_at(u, model, datas, spec):
    """The integrator's steps (accepted) over each experiment at ``u``."""
    m, _, states = unpack(u, model, len(datas), spec)
    return jnp.stack(
        [
            fast_trajectory(m, th0, Om0, d, spec.rtol, spec.atol, spec.max_solver_steps).num_steps
            for d, (th0, Om0) in zip(datas, states)
        ]
    )


def _dense_budget(model, datas, spec, u_star) -> int:
    """The step budget of the sampler's solves (they sample from the dense output, whose memory
    and cost grow with the budget): 4 times the most steps an experiment takes at the optimum
    (DOP853's count, close to diffrax's Dopri8 at the same tolerances), rounded up to a power
    of 2 (so that data sets of similar records share one compiled sampler), at least 64 and at
    most ``solve_max_steps``. A proposal whose solve needs more is a failed solve: density
    -inf, a divergent step."""
    steps = int(np.max(np.asarray(_steps_at(u_star, model, datas, spec))))
    budget = 1 << max(6, int(np.ceil(np.log2(4 * max(steps, 1)))))
    return min(budget, spec.max_solver_steps)


def _natural_draws(z, u_star, L, spec):
    """Draws of z (chains, draws, dim) as the posterior's variables: the parameters in natural
    units under their names, ``Omega_bias``, ``theta0`` and ``Omega0`` (experiment, 3)."""
    from ._residuals import transform

    flat_star, unravel = ravel_pytree(u_star)
    flat = np.asarray(flat_star)[None, None, :] + np.einsum("ij,cdj->cdi", np.asarray(L), z)
    shape = z.shape[:2]
    u = jax.vmap(jax.vmap(unravel))(jnp.asarray(flat))
    out = {}
    for name, how, value in zip(param_names(spec), spec.transforms, u["p"]):
        out[name] = transform(how, np.asarray(value), inverse=True).reshape(
            shape + np.shape(value)[2:]
        )
    if spec.fit_bias:
        out["Omega_bias"] = np.asarray(u["p_bias"])
    out["theta0"] = np.stack([np.asarray(th) for th, _ in u["x0"]], axis=2)
    out["Omega0"] = np.stack([np.asarray(om) for _, om in u["x0"]], axis=2)
    return out


def _import_arviz():
    with warnings.catch_warnings():  # ArviZ 0.x announces its refactor on import
        warnings.simplefilter("ignore", FutureWarning)
        import arviz

    return arviz


def _inference_data(variables, stats, n_experiments):
    """The draws as ArviZ takes them: ``InferenceData`` (ArviZ 0.x) or ``xarray.DataTree``
    (ArviZ >= 1.0), with the groups ``posterior``, ``sample_stats`` and ``diagnostics``
    (R-hat, bulk and tail ESS of every variable over a dimension ``diagnostic``)."""
    import xarray as xr

    az = _import_arviz()
    dims = {"Omega_bias": ["component"], "theta0": ["experiment", "component"]}
    dims["Omega0"] = ["experiment", "component"]
    coords = {"component": ["x", "y", "z"], "experiment": np.arange(n_experiments)}
    major = int(az.__version__.split(".")[0])
    if major >= 1:
        data = az.from_dict(
            {"posterior": variables, "sample_stats": stats}, dims=dims, coords=coords
        )
        posterior = data["posterior"].to_dataset()
    else:
        data = az.from_dict(posterior=variables, sample_stats=stats, dims=dims, coords=coords)
        posterior = data.posterior
    diagnostics = xr.concat(
        [
            az.rhat(posterior),
            az.ess(posterior, method="bulk"),
            az.ess(posterior, method="tail"),
        ],
        dim=xr.DataArray(["r_hat", "ess_bulk", "ess_tail"], dims="diagnostic"),
    )
    if major >= 1:
        data["diagnostics"] = xr.DataTree(diagnostics)
    else:
        data.add_groups({"diagnostics": diagnostics})
    return data, diagnostics


def _posterior_data(variables, stats, times, n_experiments, fit_time, integrator, start):
    """ArviZ's container of the draws (:func:`_inference_data`), its posterior group's
    attributes the convergence summary and where the time went (``wall_time``: since
    ``start``)."""
    out, diagnostics = _inference_data(variables, stats, n_experiments)
    r_hat = diagnostics.sel(diagnostic="r_hat")
    ess = diagnostics.sel(diagnostic="ess_bulk")
    n_draws = int(np.size(stats["lp"]))
    attrs = {
        "max_r_hat": float(max(float(r_hat[v].max()) for v in r_hat.data_vars)),
        "min_ess_bulk": float(min(float(ess[v].min()) for v in ess.data_vars)),
        "divergences": int(np.sum(stats["diverging"])),
        "mean_n_steps": float(np.mean(stats["n_steps"])),
        "fit_time": float(fit_time),
        "compile_time": float(times["compile"]),
        "sampling_time": float(times["sampling"]),
        "draws_per_second": float(n_draws / max(times["sampling"], 1e-12)),
        "integrator": integrator,
        "chain_method": times["chains"],
        "prior": "flat on the unconstrained coordinates u, unless priors says otherwise",
    }
    attrs["wall_time"] = time.perf_counter() - start
    out["posterior"].attrs.update(attrs)
    return out


def posterior(
    model,
    data,
    params,
    *,
    priors: dict | None = None,
    num_warmup: int = 500,
    num_samples: int = 1000,
    chains: int = 2,
    seed: int = 0,
    transforms=None,
    integrator: str = "simulate",
    solve_rtol: float = 1e-8,
    solve_atol: float = 1e-8,
    solve_max_steps: int = 100_000,
    chain_method: str = "auto",
    progress: bool = False,
    progress_chunks: int = 20,
):
    r"""Samples of the posterior of the parameters selected by ``params``, the gyroscope's bias
    (where the data fit it) and every experiment's initial state, by NUTS (BlackJAX).

    The log density, in the fit's unconstrained coordinates u (see the module docstring), is
    $-\tfrac12|r(u)|^2 + \log\pi(u)$: a Gaussian likelihood with the data's noise levels (every
    observed channel needs its ``sigma_*``) and a prior $\pi$ **flat on u** unless ``priors``
    says otherwise (flat on log c for a log-transformed c: improper, proper posterior where the
    data identify every coordinate). The sampler runs in $z$, $u = u^* + Lz$, $LL^T = (J^TJ)^{-1}$
    the Gauss–Newton covariance at the optimum $u^*$ of :func:`rbo_jax.fit` (run here with
    ``fit_initial_state=True``): the window adaptation's starting mass matrix is that covariance.

    **Arguments:**

    - `model`, `data`, `params`, `transforms`: as for :func:`rbo_jax.fit`.
    - `priors`: dict name -> callable giving a log density (a JAX function) of the coordinate
      **in u**: a parameter by its name in the fit (``"foundation.c"``: its value is log c for a
      log transform, e.g. ``lambda u: -0.5 * ((u - jnp.log(1.0)) / 0.3) ** 2``),
      ``"Omega_bias"`` (the bias (3,)), ``"initial_state"`` (called ``f(theta0, Omega0)`` for
      each experiment). Unnamed coordinates keep the flat prior.
    - `num_warmup`: adaptation steps (Stan's windows; 0: none, step size 1 and the
      Gauss–Newton mass matrix); `num_samples`: draws per chain; `chains`; `seed`.
    - `integrator`: ``"simulate"`` (diffrax; reverse mode; the default: measured 12 ms per
      gradient against 46 ms on two 10 s records, benchmarks/bench_posterior.py) or
      ``"fast_simulate"`` (DOP853; gradient -Jᵀr from the forward-mode Jacobian, one tangent per
      sampled scalar, in a ``jax.custom_vjp``; compiles in half the time).
    - `solve_rtol`, `solve_atol`, `solve_max_steps`: the ODE solves' tolerances and step budget
      (the fit's too; the sampler's solves have a smaller budget, see the module docstring).
      A failed solve gives the density -inf: NUTS marks the step divergent.
    - `chain_method`: ``"auto"`` (split over the local devices where their count divides
      ``chains``, else vmap), ``"pmap"`` (split over the devices, by ``shard_map``) or
      ``"vmap"``.
    - `progress`: a tqdm bar over the NUTS transitions, warmup and draws (it moves between the
      ``progress_chunks`` calls of the one compiled program the run is cut into; the last
      call's extra transitions are discarded).

    **A rod**: `model` a function ``rod_fn(**constants)`` building it, `data` a
    :class:`rbo_jax.lattice.RodSpectrumData` or :class:`rbo_jax.lattice.RodTrajectoryData` with
    its ``sigma``, `params` the constants' starting values by name; the posterior's variables
    are the constants under their names (flat prior on their logarithms unless `priors`, by
    name, says otherwise); `solve_*` apply to a trajectory's solve, `transforms` and
    `integrator` do not apply.

    **Returns** ArviZ's container (checked at call time): :class:`arviz.InferenceData` for
    ArviZ 0.x, an ``xarray.DataTree`` for ArviZ >= 1.0, with groups

    - ``posterior`` (dims ``chain``, ``draw``): the parameters in natural units under their fit
      names (``"foundation.c"``, ``"loads[0].b"``), ``"Omega_bias"`` (``component``), and
      ``"theta0"``, ``"Omega0"`` (``experiment``, ``component``); its attributes hold
      ``max_r_hat``, ``min_ess_bulk``, ``divergences``, ``mean_n_steps``, ``wall_time``
      (seconds, all included), ``fit_time``, ``compile_time``, ``sampling_time`` (warmup and
      draws), ``draws_per_second`` (chains x num_samples / sampling_time), ``integrator``,
      ``chain_method`` (as run: ``"shard_map + ..."`` where split over the devices, then
      ``"vmap"``, or ``"map"``: fast_simulate's chains one after the other on a device, as
      vmapping its forward-mode Jacobian is slower), ``prior``;
    - ``sample_stats``: ``diverging``, ``acceptance_rate``, ``tree_depth`` (trajectory
      doublings), ``n_steps`` (leapfrog steps), ``energy``, ``lp``, ``step_size``;
    - ``diagnostics``: every posterior variable over a dimension ``diagnostic`` =
      (``"r_hat"``, ``"ess_bulk"``, ``"ess_tail"``), from :func:`arviz.rhat` and
      :func:`arviz.ess`.

    Arguments are checked (ValueError naming the argument) before anything is compiled. The
    compiled sampler takes the model's and the data's arrays as arguments and is kept: a second
    call with data of the same shapes (and the same model structure, options and priors)
    compiles nothing (``compile_time`` then counts only the chains' start).
    """
    _check_arguments(num_warmup, num_samples, chains, integrator, chain_method, progress_chunks)
    _check_installed()
    start = time.perf_counter()
    opts = dict(
        num_warmup=num_warmup,
        num_samples=num_samples,
        chains=chains,
        seed=seed,
        chain_method=chain_method,
        sequential=integrator == "fast_simulate",
        progress_chunks=progress_chunks if progress else 1,
    )
    solve = dict(solve_rtol=solve_rtol, solve_atol=solve_atol, solve_max_steps=solve_max_steps)
    if is_measurements(data):
        return _rod_posterior(model, data, params, priors, opts, solve, progress, start)
    datas, spec, _ = setup(
        model, data, params, transforms=transforms, fit_initial_state=True, **solve,
        integrator="fast_simulate",
    )  # fmt: skip
    _check_sigmas(datas)
    priors = _check_priors(priors, param_names(spec), spec.fit_bias)
    result = fit(
        model, datas, params, transforms=spec.transforms, fit_initial_state=True, **solve,
        integrator="fast_simulate",
    )  # fmt: skip
    u_star = result.unconstrained
    _, L = _laplace(model, datas, spec, u_star)
    dense_steps = _dense_budget(model, datas, spec, u_star) if integrator == "simulate" else 0
    sampled = dataclasses.replace(
        spec, integrator=integrator, forward=False, dense_steps=dense_steps
    )
    problem = SensorResiduals(model, tuple(datas), u_star, sampled)
    operands, static = _split(problem, ravel_pytree(u_star)[0], L)
    forward = integrator == "fast_simulate"
    density = _density(static, forward, _log_prior(priors, None))
    key = _cache_key(static, forward, priors, operands)
    z, stats, times = _run(density, operands, key, L.shape[0], opts, progress)
    variables = _natural_draws(z, u_star, L, spec)
    return _posterior_data(variables, stats, times, len(datas), result.wall_time, integrator, start)


def _run(density, operands, key, dim, opts, progress):
    """The chains (:func:`rbo_jax.fitting._sampler.run_chains`), with a progress bar."""
    total = opts["num_warmup"] + opts["num_samples"]
    with progress_bar(progress, total, "posterior", "step") as bar:
        return run_chains(density, operands, key, dim, opts, bar)


def _rod_posterior(rod_fn, data, params, priors, opts, solve, progress, start):
    """The posterior of a rod's constants (``data`` a rod's measurements with their ``sigma``,
    ``params`` the starting values by name): log-normal coordinates x = log constants, the
    gradient -Jᵀr from forward mode (a rod's few constants), the chains one after the other
    on each device. The same result as a rigid body's, its variables the constants' names."""
    if data.sigma is None:
        raise ValueError(
            f"data ({type(data).__name__}) has no sigma: the posterior's likelihood needs the "
            "noise level of the measurements (give sigma=...)."
        )
    names = tuple(sorted(params))
    priors = _check_priors(priors, names, False, initial_state=False)
    options = dict(rtol=solve["solve_rtol"], atol=solve["solve_atol"])
    options["max_steps"] = solve["solve_max_steps"]
    result = fit_constants(rod_fn, data, params, **options)
    fit_time = time.perf_counter() - start
    problem = data.problem(rod_fn, names, **options)
    x_star = np.asarray(result.unconstrained)
    _, J = _value_and_jacobian(problem, jnp.asarray(x_star))
    _, L = _covariance_factor(np.asarray(J))
    operands, static = _split(problem, x_star, L)
    density = _density(static, True, _log_prior(priors, names))
    key = _cache_key(static, True, priors, operands)
    opts = dict(opts, sequential=True)
    z, stats, times = _run(density, operands, key, L.shape[0], opts, progress)
    x = x_star[None, None, :] + np.einsum("ij,cdj->cdi", L, z)
    variables = {name: np.exp(x[..., i]) for i, name in enumerate(names)}
    return _posterior_data(variables, stats, times, 0, fit_time, "forward mode", start)


_value_and_jacobian = eqx.filter_jit(value_and_jacfwd)
