r"""Gradient-based fitting of model parameters (foundation stiffness, damping, inertia, initial
state) to observed trajectories, with Gauss–Newton standard errors.

The residuals of one observed trajectory, whitened by the noise level $\sigma$, are

- attitude (full turn-vector θ or turn-tensor Q observed): the rotation distance
  $r = \mathrm{turn\_vector}(Q_{obs}^T\cdot Q(\theta_{model}))/\sigma_\theta$, a proper metric on
  rotations (its norm is the angle between the two attitudes), so data that wraps through
  $|\theta| = \pi$ (principal turn-vectors) is fitted correctly;
- attitude with only some components of θ observed (``theta_weight`` with zeros): the
  component differences $w\,(\theta_{model} - \theta_{obs})/\sigma_\theta$;
- angular velocities ω (left, world frame) or Ω (right, body frame): $w\,(\cdot_{model} -
  \cdot_{obs})/\sigma$.

The loss is $\frac12\sum r^2$. Parameters are chosen with an equinox-style selector
``params=lambda m: (m.foundation.c, m.foundation.d)`` and are optimised in an unconstrained
reparametrisation (log for positive parameters by default; softplus or identity on request), never
by clipping. The least-squares solvers (Levenberg–Marquardt, default; damped Gauss–Newton) use
forward-mode Jacobians through the ODE solve (``diffrax.ForwardMode``: memory independent of the
number of steps) and iterate on the host around one compiled program (see
:func:`_run_least_squares` for why not optimistix's solvers); the first-order optimisers (Adam,
L-BFGS) come from optax with reverse-mode gradients (``diffrax.RecursiveCheckpointAdjoint``:
memory logarithmic in the number of steps).

Standard errors use the Gauss–Newton approximation of the Hessian at the optimum,
$\mathrm{Cov} = s^2 (J^TJ)^{-1}$ with $J$ the Jacobian of the whitened residuals with respect to
the natural parameters; $s^2 = 1$ when the noise levels are given (``sigma_*``), otherwise the
residual variance $\sum r^2/(n - p)$.

**When to use staged horizons.** For long records, or motions that look chaotic (large
amplitudes, follower loads), a fit started far from the truth can lock onto a wrong local minimum:
the simulated and observed attitudes drift apart by more than a period and the loss landscape
becomes rugged. ``horizons=(0.25, 0.5, 1.0)`` fits the first quarter of each record, then half,
then all, each stage starting from the previous estimate (one compilation per stage).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .kinematics import turn_tensor, turn_vector
from .model import RigidBodyOscillator
from .simulate import simulate

__all__ = ["TrajectoryData", "FitResult", "fit", "residuals"]


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


def _host_array(x, name, shape_tail, n=None):
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1 + len(shape_tail) or tuple(a.shape[1:]) != tuple(shape_tail):
        raise ValueError(
            f"{name} must have shape (n, {', '.join(map(str, shape_tail))}), got {a.shape}."
        )
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} has {a.shape[0]} samples but ts has {n}.")
    return a


class TrajectoryData(eqx.Module):
    r"""One observed trajectory: sample times ``ts`` and any of ``theta`` (n, 3), ``Q`` (n, 3, 3),
    ``omega`` (n, 3) (left angular velocity), ``Omega`` (n, 3) (right angular velocity).

    ``theta0``, ``Omega0``: the initial state at ``t0`` (default ``ts[0]``); if not given they
    are taken from the first samples (θ or Q, and Ω or ω) — they are the starting guess when the
    initial state is fitted. ``*_weight`` (n, 3) arrays of non-negative weights mark missing or
    unobserved components with 0 (NaN values are refused: give them weight 0 and any finite
    value). ``sigma_*`` are the noise standard deviations (None: unknown, estimated from the
    residuals).

    All checks (shapes, NaN, sorted times, at least one observed quantity) happen here, on the
    host, before anything is compiled.
    """

    ts: jax.Array
    theta0: jax.Array
    Omega0: jax.Array
    t0: jax.Array
    theta: jax.Array | None
    Q: jax.Array | None
    omega: jax.Array | None
    Omega: jax.Array | None
    theta_weight: jax.Array | None
    omega_weight: jax.Array | None
    Omega_weight: jax.Array | None
    sigma_theta: float | None = eqx.field(static=True)
    sigma_omega: float | None = eqx.field(static=True)
    sigma_Omega: float | None = eqx.field(static=True)

    def __init__(self, ts, *, theta=None, Q=None, omega=None, Omega=None, theta0=None,
                 Omega0=None, t0=None, theta_weight=None, omega_weight=None, Omega_weight=None,
                 sigma_theta=None, sigma_omega=None, sigma_Omega=None):
        ts = np.asarray(ts, dtype=np.float64)
        if ts.ndim != 1:
            raise ValueError(f"ts must be a 1-D array of times, got shape {ts.shape}.")
        if ts.size == 0:
            raise ValueError("ts is empty: a trajectory needs at least one sample.")
        if not np.all(np.isfinite(ts)):
            raise ValueError("ts contains NaN or inf.")
        if ts.size > 1 and not np.all(np.diff(ts) > 0):
            raise ValueError("ts must be strictly increasing (sort the samples).")
        n = ts.size
        if theta is not None and Q is not None:
            raise ValueError("give the attitude either as theta or as Q, not both.")
        if all(x is None for x in (theta, Q, omega, Omega)):
            raise ValueError("nothing observed: give at least one of theta, Q, omega, Omega.")
        arrays = {}
        for name, x, tail in [("theta", theta, (3,)), ("Q", Q, (3, 3)), ("omega", omega, (3,)),
                              ("Omega", Omega, (3,))]:
            arrays[name] = None if x is None else _host_array(x, name, tail, n)
        weights = {}
        for name, w, obs in [("theta_weight", theta_weight, arrays["theta"]),
                             ("omega_weight", omega_weight, arrays["omega"]),
                             ("Omega_weight", Omega_weight, arrays["Omega"])]:
            if w is None:
                weights[name] = None
                continue
            if obs is None:
                raise ValueError(f"{name} given but {name.split('_')[0]} is not observed.")
            w = _host_array(w, name, (3,), n)
            if np.any(w < 0) or not np.all(np.isfinite(w)):
                raise ValueError(f"{name} must be finite and non-negative.")
            weights[name] = w
        for name, x in arrays.items():
            if x is None:
                continue
            w = weights.get(f"{name}_weight")
            bad = ~np.isfinite(x)
            if w is not None:
                bad = bad & (w > 0)
            if np.any(bad):
                i = int(np.argwhere(bad)[0][0])
                raise ValueError(
                    f"{name} contains NaN or inf (first at sample {i}, t = {ts[i]}); mark missing "
                    f"values with {name}_weight = 0 and any finite value."
                )
            if w is not None:
                arrays[name] = np.where(w > 0, x, 0.0)
        for name, s in [("sigma_theta", sigma_theta), ("sigma_omega", sigma_omega),
                        ("sigma_Omega", sigma_Omega)]:
            if s is not None and not (np.isfinite(s) and s > 0):
                raise ValueError(f"{name} must be a positive number, got {s}.")
        if weights["theta_weight"] is not None and arrays["theta"] is None:
            raise ValueError("theta_weight needs theta.")

        # Initial state (the starting guess if it is fitted).
        if theta0 is None:
            if arrays["theta"] is not None and (
                weights["theta_weight"] is None or np.all(weights["theta_weight"][0] > 0)
            ):
                theta0 = arrays["theta"][0]
            elif arrays["Q"] is not None:
                theta0 = np.asarray(turn_vector(arrays["Q"][0]))
            else:
                raise ValueError("theta0 is needed: the attitude at t0 is not fully observed.")
        if Omega0 is None:
            th0 = np.asarray(theta0, dtype=np.float64)
            if arrays["Omega"] is not None and (
                weights["Omega_weight"] is None or np.all(weights["Omega_weight"][0] > 0)
            ):
                Omega0 = arrays["Omega"][0]
            elif arrays["omega"] is not None and (
                weights["omega_weight"] is None or np.all(weights["omega_weight"][0] > 0)
            ):
                Omega0 = np.asarray(turn_tensor(th0)).T @ arrays["omega"][0]
            else:
                raise ValueError("Omega0 is needed: the angular velocity at t0 is not observed.")
        theta0 = _host_array(np.asarray(theta0)[None], "theta0", (3,))[0]
        Omega0 = _host_array(np.asarray(Omega0)[None], "Omega0", (3,))[0]
        if not (np.all(np.isfinite(theta0)) and np.all(np.isfinite(Omega0))):
            raise ValueError("theta0 and Omega0 must be finite.")
        t0 = ts[0] if t0 is None else float(t0)
        if t0 > ts[0]:
            raise ValueError(f"t0 = {t0} is after the first sample ts[0] = {ts[0]}.")

        def j(x):
            return None if x is None else jnp.asarray(x)

        self.ts, self.theta0, self.Omega0, self.t0 = j(ts), j(theta0), j(Omega0), jnp.asarray(t0)
        self.theta, self.Q, self.omega, self.Omega = (
            j(arrays[k]) for k in ("theta", "Q", "omega", "Omega"))
        self.theta_weight, self.omega_weight, self.Omega_weight = (
            j(weights[k]) for k in ("theta_weight", "omega_weight", "Omega_weight"))
        self.sigma_theta, self.sigma_omega, self.sigma_Omega = sigma_theta, sigma_omega, sigma_Omega

    @property
    def num_samples(self) -> int:
        return int(self.ts.shape[0])

    def truncate(self, t_end) -> TrajectoryData:
        """The samples with t ≤ t_end (for staged horizons)."""
        keep = np.asarray(self.ts) <= t_end
        keep[0] = True

        def cut(x):
            return None if x is None else np.asarray(x)[keep]

        return TrajectoryData(
            np.asarray(self.ts)[keep], theta=cut(self.theta), Q=cut(self.Q), omega=cut(self.omega),
            Omega=cut(self.Omega), theta0=self.theta0, Omega0=self.Omega0, t0=self.t0,
            theta_weight=cut(self.theta_weight), omega_weight=cut(self.omega_weight),
            Omega_weight=cut(self.Omega_weight), sigma_theta=self.sigma_theta,
            sigma_omega=self.sigma_omega, sigma_Omega=self.sigma_Omega,
        )


# --------------------------------------------------------------------------------------------
# Residuals
# --------------------------------------------------------------------------------------------


def residuals(model: RigidBodyOscillator, data: TrajectoryData, theta0=None, Omega0=None, *,
              rtol=1e-10, atol=1e-10, adjoint=None, max_steps=100_000) -> jax.Array:
    """The whitened residual vector of one trajectory (see the module docstring)."""
    theta0 = data.theta0 if theta0 is None else theta0
    Omega0 = data.Omega0 if Omega0 is None else Omega0
    traj = simulate(model, theta0, Omega0, data.ts, t0=data.t0, rtol=rtol, atol=atol,
                    adjoint=adjoint, max_steps=max_steps, throw=False)
    out = []
    if data.Q is not None or (data.theta is not None and data.theta_weight is None):
        Q_obs = data.Q if data.Q is not None else jax.vmap(turn_tensor)(data.theta)
        Q_mod = jax.vmap(turn_tensor)(traj.theta)
        r = jax.vmap(lambda a, b: turn_vector(a.T @ b))(Q_obs, Q_mod)
        out.append(r / (data.sigma_theta or 1.0))
    elif data.theta is not None:
        out.append(data.theta_weight * (traj.theta - data.theta) / (data.sigma_theta or 1.0))
    if data.omega is not None:
        w = 1.0 if data.omega_weight is None else data.omega_weight
        out.append(w * (traj.omega - data.omega) / (data.sigma_omega or 1.0))
    if data.Omega is not None:
        w = 1.0 if data.Omega_weight is None else data.Omega_weight
        out.append(w * (traj.Omega - data.Omega) / (data.sigma_Omega or 1.0))
    return jnp.concatenate([o.ravel() for o in out])


# --------------------------------------------------------------------------------------------
# Parametrisation
# --------------------------------------------------------------------------------------------

_TRANSFORMS = {
    "log": (jnp.log, jnp.exp),
    "softplus": (lambda x: x + jnp.log(-jnp.expm1(-x)), jax.nn.softplus),
    "identity": (lambda x: x, lambda u: u),
}


def _resolve_transforms(values, transforms):
    if transforms is None:
        out = []
        for v in values:
            v = np.asarray(v)
            out.append("log" if (v.size and np.all(v > 0)) else "identity")
        return tuple(out)
    if isinstance(transforms, str):
        transforms = (transforms,) * len(values)
    transforms = tuple(transforms)
    if len(transforms) != len(values):
        raise ValueError(f"transforms has {len(transforms)} entries for {len(values)} parameters.")
    for t, v in zip(transforms, values):
        if t not in _TRANSFORMS:
            raise ValueError(f"unknown transform {t!r}; choose from {sorted(_TRANSFORMS)}.")
        if t in ("log", "softplus") and not np.all(np.asarray(v) > 0):
            raise ValueError(
                f"a {t} transform needs a positive starting value, got {np.asarray(v)}."
            )
    return transforms


class FitResult(eqx.Module):
    """Result of :func:`fit`.

    ``model``: the fitted model; ``params``: fitted values of the selected parameters (tuple, in
    the order of the selector); ``stderr``: their standard errors (same structure);
    ``covariance``: covariance of all fitted scalars (flattened, parameters then initial states);
    ``initial_states``: fitted or given ``(theta0, Omega0)`` per trajectory; ``loss_history``:
    the loss ½Σr² after each iteration (every stage); ``num_steps``; ``converged``;
    ``message``; ``residual_rms``; ``wall_time`` (seconds, compilation included).
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


@dataclasses.dataclass(frozen=True)
class _Spec:
    """Static description of a fit (hashable: one compilation per structure, reused across
    calls)."""

    paths: tuple
    transforms: tuple
    fit_initial_state: bool
    rtol: float
    atol: float
    forward: bool
    max_solver_steps: int = 100_000


def _leaf_paths(model, values) -> tuple:
    leaves = jax.tree_util.tree_flatten_with_path(model)[0]
    paths = []
    for v in values:
        matches = [path for path, leaf in leaves if leaf is v]
        if len(matches) != 1:
            raise ValueError(
                "params must select float array leaves of the model itself, e.g. "
                "lambda m: (m.foundation.c, m.foundation.d)."
            )
        paths.append(matches[0])
    return tuple(paths)


def _get(tree, path):
    for key in path:
        if isinstance(key, jax.tree_util.GetAttrKey):
            tree = getattr(tree, key.name)
        elif isinstance(key, jax.tree_util.SequenceKey):
            tree = tree[key.idx]
        elif isinstance(key, jax.tree_util.DictKey):
            tree = tree[key.key]
        else:
            raise ValueError(f"cannot fit a parameter stored under {key!r}.")
    return tree


def _replace(model, spec: _Spec, natural):
    return eqx.tree_at(lambda m: tuple(_get(m, p) for p in spec.paths), model, tuple(natural))


def _unpack(u, model, n_data, spec: _Spec):
    natural = tuple(_TRANSFORMS[n][1](x) for n, x in zip(spec.transforms, u["p"]))
    states = u["x0"] if spec.fit_initial_state else ((None, None),) * n_data
    return _replace(model, spec, natural), natural, states


def _stack_residuals(model, datas, states, spec: _Spec):
    adjoint = diffrax.ForwardMode() if spec.forward else diffrax.RecursiveCheckpointAdjoint()
    return jnp.concatenate([
        residuals(model, d, th0, Om0, rtol=spec.rtol, atol=spec.atol, adjoint=adjoint,
                  max_steps=spec.max_solver_steps)
        for d, (th0, Om0) in zip(datas, states)
    ])


def _residual_vector(u, model, datas, spec: _Spec):
    m, _, states = _unpack(u, model, len(datas), spec)
    return _stack_residuals(m, datas, states, spec)


@eqx.filter_jit
def _loss(u, model, datas, spec):
    return 0.5 * jnp.sum(_residual_vector(u, model, datas, spec) ** 2)


_loss_and_grad = eqx.filter_jit(jax.value_and_grad(_loss))


@eqx.filter_jit
def _residuals_and_jacobian(u, model, datas, spec):
    """Whitened residuals at ``u`` and their forward-mode Jacobian (one JVP per fitted scalar,
    batched). The single compiled program of a least-squares fit: iterations, trial points and
    the covariance all reuse it."""

    def f(u):
        r = _residual_vector(u, model, datas, spec)
        return r, r

    J, r = jax.jacfwd(f, has_aux=True)(u)
    return r, J


def _flatten(tree):
    leaves = jax.tree_util.tree_leaves(tree)
    return np.concatenate([np.asarray(x, dtype=np.float64).ravel() for x in leaves])


def _unflatten_like(flat, tree):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    out, i = [], 0
    for x in leaves:
        n = int(np.size(x))
        out.append(jnp.asarray(flat[i:i + n].reshape(np.shape(x)), dtype=jnp.result_type(float)))
        i += n
    return jax.tree_util.tree_unflatten(treedef, out)


def _jacobian_matrix(J_tree, n_res):
    return np.concatenate(
        [
            np.asarray(b, dtype=np.float64).reshape(n_res, -1)
            for b in jax.tree_util.tree_leaves(J_tree)
        ],
        axis=1,
    )


def _transform_derivative(name, x):
    """du/dx of the reparametrisation u = forward(x) at the natural value x."""
    x = np.asarray(x, dtype=np.float64)
    if name == "log":
        return 1.0 / x
    if name == "softplus":
        return 1.0 / -np.expm1(-x)
    return np.ones_like(x)


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
    - `optimizer`: ``"levenberg_marquardt"`` (default) or ``"gauss_newton"`` (optimistix, least
      squares), ``"adam"`` or ``"lbfgs"`` (optax, general losses).
    - `max_steps`: iterations per stage; `tol`: relative/absolute tolerance of the least-squares
      solvers (and the stagnation test); `learning_rate`: for Adam.
    - `horizons`: staged fitting on growing fractions of each record (module docstring).
    - `solve_rtol`, `solve_atol`: tolerances of the ODE solves; `solve_max_steps`: their step
      budget (a solve that exhausts it gives infinite residuals, which the optimizer rejects).
    - `progress`: tqdm bar over iterations; `verbose`: print the loss each iteration.

    Compiled programs are cached on the model's structure, the data's shapes and these options,
    so repeated fits (bootstrap, noise studies) compile once.
    """
    start = time.perf_counter()
    datas = tuple(_as_data_list(data))
    if optimizer not in ("levenberg_marquardt", "gauss_newton", "adam", "lbfgs"):
        raise ValueError(
            "optimizer must be 'levenberg_marquardt', 'gauss_newton', 'adam' or 'lbfgs', "
            f"got {optimizer!r}."
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
    try:
        values = params(model)
    except Exception as e:  # a selector that does not match the model
        raise ValueError(f"params selector failed on the model: {e}") from e
    values = tuple(values) if isinstance(values, (tuple, list)) else (values,)
    if not values or not all(eqx.is_inexact_array(v) for v in values):
        raise ValueError(
            "params must select float array leaves of the model (e.g. m.foundation.c)."
        )
    least_squares = optimizer in ("levenberg_marquardt", "gauss_newton")
    spec = _Spec(
        paths=_leaf_paths(model, values),
        transforms=_resolve_transforms(values, transforms),
        fit_initial_state=bool(fit_initial_state),
        rtol=float(solve_rtol),
        atol=float(solve_atol),
        forward=least_squares,
        max_solver_steps=int(solve_max_steps),
    )
    u = {"p": tuple(_TRANSFORMS[n][0](jnp.asarray(v)) for n, v in zip(spec.transforms, values))}
    if fit_initial_state:
        u["x0"] = tuple((d.theta0, d.Omega0) for d in datas)

    history: list[float] = []
    total_steps = 0
    converged, message = True, "converged"
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_steps * len(horizons), desc="fit", unit="it")
    try:
        for h in horizons:
            stage = tuple(
                d if h >= 1.0 else d.truncate(float(d.t0) + h * (float(d.ts[-1]) - float(d.t0)))
                for d in datas
            )
            if least_squares:
                u, steps, converged, message = _run_least_squares(
                    u, model, stage, spec, optimizer, tol, max_steps, history, bar, verbose)
            else:
                u, steps, converged, message = _run_optax(
                    u, model, stage, spec, optimizer, learning_rate, max_steps, tol, history, bar,
                    verbose)
            total_steps += steps
    finally:
        if bar is not None:
            bar.close()

    # Gauss-Newton covariance at the optimum, w.r.t. the natural parameters: the Jacobian in
    # the reparametrised coordinates u, times du/dx (chain rule); initial states are not
    # reparametrised.
    fitted_model, natural, states = _unpack(u, model, len(datas), spec)
    r, J_tree = _residuals_and_jacobian(u, model, datas, dataclasses.replace(spec, forward=True))
    r = np.asarray(r, dtype=np.float64)
    J = _jacobian_matrix(J_tree, r.size)
    scale = [_transform_derivative(n, x).ravel() for n, x in zip(spec.transforms, natural)]
    if fit_initial_state:
        scale.append(np.ones(J.shape[1] - sum(v.size for v in scale)))
    J = J * np.concatenate(scale)[None, :]
    sizes = [int(np.size(x)) for x in natural]
    n_res, n_par = J.shape
    sigma_known = all(
        (d.sigma_theta is not None or (d.theta is None and d.Q is None))
        and (d.sigma_omega is not None or d.omega is None)
        and (d.sigma_Omega is not None or d.Omega is None)
        for d in datas
    )
    s2 = 1.0 if sigma_known else float(r @ r) / max(n_res - n_par, 1)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((n_par, n_par), np.inf)
        message += "; J^T J is singular: the parameters are not identifiable from these data"
    se_flat = np.sqrt(np.clip(np.diag(cov), 0.0, np.inf))
    offsets = np.cumsum([0] + sizes)  # the natural parameters come first in u
    se = tuple(
        se_flat[offsets[i]:offsets[i + 1]].reshape(np.shape(v)) for i, v in enumerate(natural)
    )
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
        num_steps=int(total_steps),
        converged=bool(converged),
        message=message,
        residual_rms=float(np.sqrt(np.mean(r**2))) if r.size else 0.0,
        wall_time=time.perf_counter() - start,
    )


def _log(history, loss, bar, verbose):
    history.append(float(loss))
    if bar is not None:
        bar.update(1)
        bar.set_postfix(loss=f"{float(loss):.3e}")
    if verbose:
        print(f"iteration {len(history)}: loss = {float(loss):.6e}")


_PATIENCE = 6


def _run_least_squares(u, model, datas, spec, optimizer, tol, max_steps, history, bar, verbose):
    r"""Levenberg–Marquardt (Madsen, Nielsen & Tingleff 2004, Alg. 3.16, with Marquardt's
    diagonal scaling) or damped Gauss–Newton (step halving), iterated on the host around the
    compiled :func:`_residuals_and_jacobian`.

    Why not ``optimistix.LevenbergMarquardt``: its init, step, termination and our loss and
    covariance evaluations are separate compiled programs, each one containing the ODE solve and
    its forward-mode derivative (~4 compilations of tens of seconds per fit structure); here one
    program serves everything, and the p×p linear algebra runs in NumPy.
    """
    x = _flatten(u)
    r, J_tree = _residuals_and_jacobian(u, model, datas, spec)
    r = np.asarray(r, dtype=np.float64)
    J = _jacobian_matrix(J_tree, r.size)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise FloatingPointError(
            "the residuals or their Jacobian are not finite at the starting point: check the "
            "starting parameters and initial states (the simulation may fail there: a singular "
            "point, the foundation's domain, or the step budget solve_max_steps)."
        )
    F = 0.5 * float(r @ r)
    _log(history, F, bar, verbose)
    A = J.T @ J
    g = J.T @ r
    gauss_newton = optimizer == "gauss_newton"
    mu = 0.0 if gauss_newton else 1e-3 * float(np.max(np.diag(A)))
    nu = 2.0
    stalled = 0
    for steps in range(1, max_steps + 1):
        if F == 0.0 or not np.any(g):
            return _unflatten_like(x, u), steps - 1, True, "converged (zero residual or gradient)"
        D = np.diag(np.maximum(np.diag(A), 1e-30))
        try:
            h = np.linalg.solve(A + mu * D, -g)
        except np.linalg.LinAlgError:
            h = np.linalg.lstsq(A + mu * D, -g, rcond=None)[0]
        if np.linalg.norm(h) <= tol * (np.linalg.norm(x) + tol):
            return _unflatten_like(x, u), steps - 1, True, "converged (step below tolerance)"
        factor = 1.0
        accepted = False
        for _ in range(12 if gauss_newton else 1):
            x_new = x + factor * h
            r_new, J_new = _residuals_and_jacobian(_unflatten_like(x_new, u), model, datas, spec)
            r_new = np.asarray(r_new, dtype=np.float64)
            F_new = 0.5 * float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            predicted = 0.5 * float((factor * h) @ (mu * D @ (factor * h) - g))
            rho = (F - F_new) / predicted if predicted > 0 else -np.inf
            if rho > 0 and np.isfinite(F_new):
                accepted = True
                break
            factor *= 0.5
        if accepted:
            improvement = F - F_new
            x, r, F = x_new, r_new, F_new
            J = _jacobian_matrix(J_new, r.size)
            A, g = J.T @ J, J.T @ r
            if not gauss_newton:
                mu *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                nu = 2.0
            stalled = stalled + 1 if improvement <= tol * F else 0
        else:
            if gauss_newton:
                return _unflatten_like(x, u), steps, False, "Gauss-Newton: no descent step found"
            mu *= nu
            nu *= 2.0
            stalled += 1
        _log(history, F, bar, verbose)
        if stalled >= _PATIENCE:
            return _unflatten_like(x, u), steps, True, (
                f"converged (no relative decrease of the loss above tol in {_PATIENCE} steps: a "
                "minimum, possibly local, or the noise floor of the ODE solves)"
            )
    return (
        _unflatten_like(x, u),
        max_steps,
        False,
        f"max_steps = {max_steps} reached before convergence",
    )


def _run_optax(u, model, datas, spec, optimizer, learning_rate, max_steps, tol, history, bar,
               verbose):
    opt = optax.adam(learning_rate) if optimizer == "adam" else optax.lbfgs()
    state = opt.init(u)

    @eqx.filter_jit
    def update(u, state, value, grad, model, datas):
        if optimizer == "lbfgs":
            updates, state = opt.update(grad, state, u, value=value, grad=grad,
                                        value_fn=lambda v: _loss(v, model, datas, spec))
        else:
            updates, state = opt.update(grad, state, u)
        return optax.apply_updates(u, updates), state

    value, grad = _loss_and_grad(u, model, datas, spec)
    _log(history, value, bar, verbose)
    steps = 0
    for steps in range(1, max_steps + 1):
        u, state = update(u, state, value, grad, model, datas)
        new_value, grad = _loss_and_grad(u, model, datas, spec)
        _log(history, new_value, bar, verbose)
        gnorm = float(np.sqrt(sum(float(jnp.sum(x**2)) for x in jax.tree_util.tree_leaves(grad))))
        if abs(float(value) - float(new_value)) <= tol * abs(float(value)) and gnorm <= tol:
            return u, steps, True, "converged"
        value = new_value
    return u, steps, False, f"max_steps = {max_steps} reached before convergence"
