"""Residuals of a fit and the reparametrisation of its parameters; the compiled programs every
solver of :func:`rbo_jax.fit` uses.

diffrax and :func:`rbo_jax.simulate` are imported when a fit integrates with ``simulate`` (the
optax optimizers, or ``integrator="simulate"``): the least-squares fits integrate with
:func:`rbo_jax.fast_simulate`, and a process that loads their program from the program store
never traces it, nor imports diffrax.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .._programs import program
from ..ensemble import fast_simulate
from ..kinematics import turn_tensor, turn_vector
from ..models.rigid_body import RigidBodyOscillator
from ..solvers import value_and_jacfwd
from ..trajectory import Trajectory
from ._data import TrajectoryData

__all__ = ["residuals", "Spec", "TRANSFORMS", "INTEGRATORS"]


INTEGRATORS = ("fast_simulate", "simulate")


def residuals(
    model: RigidBodyOscillator,
    data: TrajectoryData,
    theta0=None,
    Omega0=None,
    *,
    rtol=1e-10,
    atol=1e-10,
    adjoint=None,
    max_steps=100_000,
    integrator: str = "simulate",
    Omega_bias=None,
    dense: bool = False,
) -> jax.Array:
    r"""The whitened residual vector of one trajectory (see the package docstring).

    ``Omega_bias``: the gyroscope's bias (3,) where the data fits it (``Omega_bias="fit"``):
    the model's reading is then $\Omega + b$; a known bias comes with the data.

    ``integrator``: ``"simulate"`` (diffrax; ``adjoint`` chooses how it is differentiated,
    reverse mode by default) or ``"fast_simulate"`` (DOP853, forward mode only: ``jax.jvp``,
    ``jax.jacfwd``; ``adjoint`` must be None). Both integrate the right form (4.55)–(4.56).
    ``dense``: ``simulate`` samples ``ts`` from its dense output (:func:`rbo_jax.simulate`'s
    ``dense``; its memory grows with ``max_steps``)."""
    theta0 = data.theta0 if theta0 is None else theta0
    Omega0 = data.Omega0 if Omega0 is None else Omega0
    if integrator == "simulate":
        from ..simulate import simulate

        traj = simulate(
            model,
            theta0,
            Omega0,
            data.ts,
            t0=data.t0,
            rtol=rtol,
            atol=atol,
            adjoint=adjoint,
            max_steps=max_steps,
            throw=False,
            dense=dense,
        )
    elif integrator == "fast_simulate":
        if adjoint is not None:
            raise ValueError(
                "fast_simulate is differentiated in forward mode only: adjoint "
                "must be None (use integrator='simulate' for an adjoint)."
            )
        traj = fast_trajectory(model, theta0, Omega0, data, rtol, atol, max_steps)
    else:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}.")
    out = []
    if data.Q is not None or (data.theta is not None and data.theta_weight is None):
        Q_obs = data.Q if data.Q is not None else jax.vmap(turn_tensor)(data.theta)
        Q_mod = jax.vmap(turn_tensor)(traj.theta)
        if data.attitude_weight is not None:  # a missing sample: compared with itself (r = 0,
            # a finite derivative), then weighed 0
            seen = data.attitude_weight[:, None, None] > 0
            Q_obs = jnp.where(seen, Q_obs, jax.lax.stop_gradient(Q_mod))
        r = jax.vmap(lambda a, b: turn_vector(a.T @ b))(Q_obs, Q_mod)
        if data.attitude_weight is not None:
            r = data.attitude_weight[:, None] * r
        out.append(r / (data.sigma_theta or 1.0))
    elif data.theta is not None:
        out.append(data.theta_weight * (traj.theta - data.theta) / (data.sigma_theta or 1.0))
    if data.omega is not None:
        w = 1.0 if data.omega_weight is None else data.omega_weight
        out.append(w * (traj.omega - data.omega) / (data.sigma_omega or 1.0))
    if data.Omega is not None:
        w = 1.0 if data.Omega_weight is None else data.Omega_weight
        reading = traj.Omega
        if data.fit_Omega_bias:
            if Omega_bias is None:
                raise ValueError("the data fits Omega_bias: give the bias (Omega_bias=...).")
            reading = reading + jnp.asarray(Omega_bias)[None, :]
        elif data.Omega_bias is not None:
            reading = reading + data.Omega_bias[None, :]
        out.append(w * (reading - data.Omega) / (data.sigma_Omega or 1.0))
    return jnp.concatenate([o.ravel() for o in out])


def fast_trajectory(model, theta0, Omega0, data: TrajectoryData, rtol, atol, max_steps):
    """The model's trajectory at ``data.ts`` from the state at ``data.t0`` by
    :func:`rbo_jax.fast_simulate`, which starts at its first time: it is given
    ``[t0, ts[0], ts[1:]]``, or, when ``t0 = ts[0]`` (traced, so not known here),
    ``[ts[0], (ts[0] + ts[1])/2, ts[1:]]`` — an extra dense-output sample, which does not change
    the steps — and the samples at ``ts`` are picked from the result."""
    ts, t0 = data.ts, data.t0.astype(data.ts.dtype)
    at_start = t0 >= ts[0]  # TrajectoryData refuses t0 > ts[0]
    between = (ts[0] + ts[1]) / 2 if ts.shape[0] > 1 else ts[0] + 1.0
    times = jnp.concatenate([t0[None], jnp.where(at_start, between, ts[0])[None], ts[1:]])
    traj = fast_simulate(
        model, theta0, Omega0, times, rtol=rtol, atol=atol, max_steps=max_steps, throw=False
    )

    def pick(x):
        return jnp.concatenate([jnp.where(at_start, x[0], x[1])[None], x[2:]])

    return Trajectory(
        ts=ts,
        theta=pick(traj.theta),
        Omega=pick(traj.Omega),
        model=model,
        status=traj.status,
        num_steps=traj.num_steps,
    )


def _transforms(xp):
    r"""The reparametrisations in the array module ``xp``: natural x -> unconstrained u, back,
    and du/dx. ``log``; ``softplus``, $u = \log(e^x - 1)$ and back $x = \log(1 + e^u)$."""
    return {
        "log": (xp.log, xp.exp, lambda x: 1.0 / x),
        "softplus": (
            lambda x: x + xp.log(-xp.expm1(-x)),
            lambda u: xp.logaddexp(u, 0.0),
            lambda x: 1.0 / -xp.expm1(-x),
        ),
        "identity": (lambda x: x, lambda u: u, xp.ones_like),
    }


TRANSFORMS = _transforms(jnp)
# The same maps in NumPy, for concrete values on the host (the start and the result of a fit):
# each jnp call on a concrete value would be a small program compiled eagerly.
_NUMPY_TRANSFORMS = _transforms(np)


def transform(name: str, x, inverse: bool = False):
    """The transform ``name`` (natural -> unconstrained, or back with ``inverse``): in NumPy for a
    concrete value (float64 where x64 is on), in JAX for a traced one."""
    if isinstance(x, jax.core.Tracer):
        return TRANSFORMS[name][int(inverse)](x)
    return _NUMPY_TRANSFORMS[name][int(inverse)](np.asarray(x, dtype=jnp.result_type(float)))


def resolve_transforms(values, transforms):
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
        if t not in TRANSFORMS:
            raise ValueError(f"unknown transform {t!r}; choose from {sorted(TRANSFORMS)}.")
        if t in ("log", "softplus") and not np.all(np.asarray(v) > 0):
            raise ValueError(
                f"a {t} transform needs a positive starting value, got {np.asarray(v)}."
            )
    return transforms


@dataclasses.dataclass(frozen=True)
class Spec:
    """Static description of a fit (hashable: one compilation per structure, reused across
    calls)."""

    paths: tuple
    transforms: tuple
    fit_initial_state: bool
    rtol: float
    atol: float
    forward: bool
    max_solver_steps: int = 100_000
    integrator: str = "simulate"
    fit_bias: bool = False
    # > 0: ``simulate`` samples from its dense output, with this step budget (the posterior)
    dense_steps: int = 0


def param_names(spec: Spec) -> tuple:
    """The fitted parameters' names: their paths in the model, ``"foundation.c"``,
    ``"loads[0].b"``."""
    return tuple(jax.tree_util.keystr(p).lstrip(".") for p in spec.paths)


def scalar_names(names, values) -> list:
    """One name per fitted scalar: ``name`` for a scalar, ``name[i]`` (flat index) for an
    element of an array parameter."""
    out = []
    for name, v in zip(names, values):
        size = int(np.size(v))
        out += [name] if np.ndim(v) == 0 else [f"{name}[{i}]" for i in range(size)]
    return out


def leaf_paths(model, values) -> tuple:
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


def leaf_at(tree, path):
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


def with_params(model, spec: Spec, natural):
    return eqx.tree_at(lambda m: tuple(leaf_at(m, p) for p in spec.paths), model, tuple(natural))


def unpack(u, model, n_data, spec: Spec):
    natural = tuple(transform(n, x, inverse=True) for n, x in zip(spec.transforms, u["p"]))
    states = u["x0"] if spec.fit_initial_state else ((None, None),) * n_data
    return with_params(model, spec, natural), natural, states


def stack_residuals(model, datas, states, spec: Spec, bias=None):
    if spec.integrator == "fast_simulate":
        adjoint = None  # forward mode only (custom_jvp)
    else:
        import diffrax

        # with the small step budget of a dense solve, a checkpoint per step: reverse mode
        # then recomputes nothing (measured 12 % faster, and quicker to compile)
        dense = spec.dense_steps > 0
        checkpoints = spec.dense_steps if dense else None
        adjoint = (
            diffrax.ForwardMode()
            if spec.forward
            else diffrax.RecursiveCheckpointAdjoint(checkpoints=checkpoints)
        )
    dense = spec.dense_steps > 0 and spec.integrator == "simulate"
    return jnp.concatenate(
        [
            residuals(
                model,
                d,
                th0,
                Om0,
                rtol=spec.rtol,
                atol=spec.atol,
                adjoint=adjoint,
                max_steps=spec.dense_steps if dense else spec.max_solver_steps,
                integrator=spec.integrator,
                Omega_bias=bias,
                dense=dense,
            )
            for d, (th0, Om0) in zip(datas, states)
        ]
    )


def residual_vector(u, model, datas, spec: Spec):
    m, _, states = unpack(u, model, len(datas), spec)
    return stack_residuals(m, datas, states, spec, u.get("p_bias"))


class SensorResiduals(eqx.Module):
    """The whitened residuals of a fit of sensor data as a function of the flat vector x of its
    unconstrained coordinates (``template``'s, the fit's u, flattened): the problem that
    :func:`rbo_jax.profile_likelihood` and :func:`rbo_jax.posterior` share with a rod's
    (:class:`rbo_jax.fitting.constants.Residuals`). The model's and the data's arrays are traced,
    ``spec`` static."""

    model: RigidBodyOscillator
    datas: tuple
    template: dict
    spec: Spec = eqx.field(static=True)

    def unravel(self, x):
        return ravel_pytree(self.template)[1](x)

    def __call__(self, x):
        return residual_vector(self.unravel(x), self.model, self.datas, self.spec)


@eqx.filter_jit
def loss(u, model, datas, spec):
    return 0.5 * jnp.sum(residual_vector(u, model, datas, spec) ** 2)


loss_and_grad = eqx.filter_jit(jax.value_and_grad(loss))


def residuals_and_jacobian(u, model, datas, spec):
    """Whitened residuals at ``u`` and their forward-mode Jacobian (one JVP per fitted scalar,
    batched). The single compiled program of a least-squares fit: iterations, trial points and
    the covariance all reuse it. With the program store on
    (:func:`rbo_jax.enable_compilation_cache`, the command line), a second process loads it
    traced and compiled (:mod:`rbo_jax._programs`)."""
    return value_and_jacfwd(lambda v: residual_vector(v, model, datas, spec), u)


# XLA's options for small programs: an iteration takes milliseconds, the compilation seconds
residuals_and_jacobian = program(residuals_and_jacobian, small=True)


def transform_derivative(name, x):
    """du/dx of the reparametrisation u = forward(x) at the natural value x."""
    return _NUMPY_TRANSFORMS[name][2](np.asarray(x, dtype=np.float64))


def observed_components(datas) -> list:
    """``(count, sigma)`` of each observed channel: the residual components that count (missing
    samples do not) and the noise level (None: not given)."""
    out = []
    for d in datas:
        n = d.num_samples
        if d.Q is not None or (d.theta is not None and d.theta_weight is None):
            seen = n if d.attitude_weight is None else np.sum(np.asarray(d.attitude_weight) > 0)
            out.append((3 * int(seen), d.sigma_theta))
        elif d.theta is not None:
            out.append((int(np.sum(np.asarray(d.theta_weight) > 0)), d.sigma_theta))
        for x, w, sigma in (
            (d.omega, d.omega_weight, d.sigma_omega),
            (d.Omega, d.Omega_weight, d.sigma_Omega),
        ):
            if x is not None:
                out.append((3 * n if w is None else int(np.sum(np.asarray(w) > 0)), sigma))
    return out


def observed_count(datas) -> int:
    """The number of residual components that are observed (a missing sample's give 0)."""
    return sum(count for count, _ in observed_components(datas))
