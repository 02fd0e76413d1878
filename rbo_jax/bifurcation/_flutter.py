r"""The engineer's picture of flutter: where it is soft or hard over two parameters (with the
Bautin curve between), and the hysteresis loop of a quasi-static load.

**Flutter map.** Over a grid of two parameters $(\beta, \gamma)$ (e.g. $A_3$ and the friction
$b$ of the damped Nikolai problem (4.57), (4.84)), the Hopf point in the load $\alpha$
(:func:`rbo_jax.hopf_point`, one compiled program for the whole grid) gives the critical load and
the first Lyapunov coefficient $\ell_1$: soft flutter where $\ell_1 < 0$ (a small stable cycle
grows from $\alpha_H$), hard where $\ell_1 > 0$ (the resting body jumps to a large cycle). For
each $\gamma$ the sign change of $\ell_1$ along $\beta$ is located exactly by
:func:`rbo_jax.bautin_point`: the Bautin curve $\beta_B(\gamma)$.

**Hysteresis loop.** One long run of :func:`rbo_jax.fast_simulate` with a piecewise-constant load
$\alpha_j$ (up, then down), each value held for ``dwell`` time units and started from the state
the previous one ended in (one ``lax.scan``, one compiled program). A small disturbance
``kick`` (a turn about the first axis) is added at every change of the load, as imperfections do
in an experiment: without it the resting state, once unstable, would take arbitrarily long to
leave. The amplitude at each load is $\max_t|\theta(t) - \bar\theta|$ over the second half of the
dwell (the definition of :func:`rbo_jax.continue_limit_cycles`), so the loop can be drawn over
the continued branch: on the hard side the body stays at rest up to $\alpha_H$ (a little beyond:
a slow loss of stability), jumps to the large cycle, and on the way down stays on it until the
fold of cycles, where it falls back to rest.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .._programs import jit
from ..ensemble import fast_simulate
from ..models.rigid_body import RigidBodyOscillator
from ..trajectory import SolveStatus
from ._bautin import bautin_point
from ._hopf import hopf_point
from ._models import rigid_model as _build

__all__ = ["flutter_map", "hysteresis_loop"]


def flutter_map(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    guess,
    axes: Mapping[str, object],
    *,
    bautin: bool = True,
    theta_eq_fn: Callable[..., object] | None = None,
):
    r"""Soft and hard flutter over two parameters (module docstring), as an
    :class:`xarray.Dataset` over the two ``axes`` (``{name: 1-D values}``, the first is
    $\beta$, along which the Bautin points are sought): the critical ``parameter`` (Hopf point
    from ``guess``), ``frequency``, ``first_lyapunov``, ``hard`` ($\ell_1 > 0$) and ``status``
    (codes of :class:`rbo_jax.bifurcation.HopfStatus`); with ``bautin``, over the second axis,
    ``bautin_<beta>`` and ``bautin_<parameter>`` (NaN where $\ell_1$ does not change sign along
    $\beta$) and ``second_lyapunov``.

    Example: ``flutter_map(lambda M, b, A3: nikolai_model(M, 1.0, 2.0, A3=A3, friction=b), {},
    "M", 0.2, {"A3": np.linspace(0.5, 2.5, 21), "b": np.linspace(0.05, 0.2, 7)})``.
    """
    import xarray as xr

    from .. import _enumeration as enum
    from ._hopf import HopfStatus

    if len(axes) != 2:
        raise ValueError(f"axes must name two parameters, got {list(axes)}.")
    (beta, bs), (gamma, gs) = ((str(k), np.asarray(v, float)) for k, v in axes.items())
    for name, values in ((beta, bs), (gamma, gs)):
        if values.ndim != 1 or values.size < 2:
            raise ValueError(f"axes[{name!r}] must be a 1-D array of at least two values.")
    fields = ("value", "frequency", "first_lyapunov")
    out = {f: np.full((bs.size, gs.size), np.nan) for f in fields}
    status = np.zeros((bs.size, gs.size), np.int8)
    for j, g in enumerate(gs):
        for i, b in enumerate(bs):
            start = out["value"][i - 1, j] if i else out["value"][0, j - 1] if j else np.nan
            start = start if np.isfinite(start) else guess  # the neighbour's Hopf point
            point = {**params, beta: b, gamma: g}
            h = hopf_point(model_fn, point, parameter, start, theta_eq_fn=theta_eq_fn)
            for f in fields:
                out[f][i, j] = float(getattr(h, f))
            status[i, j] = int(np.asarray(enum.code(h.status)))
    dims = (beta, gamma)
    ds = xr.Dataset(
        {
            parameter: (dims, out["value"]),
            "frequency": (dims, out["frequency"]),
            "first_lyapunov": (dims, out["first_lyapunov"]),
            "hard": (dims, out["first_lyapunov"] > 0),
            "status": (dims, status),
        },
        coords={beta: bs, gamma: gs},
        attrs={"parameter": parameter, "beta": beta, "gamma": gamma},
    )
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    if bautin:
        ds = ds.assign(_bautin_curve(model_fn, params, parameter, beta, gamma, ds, theta_eq_fn))
    return ds


def _bautin_curve(model_fn, params, parameter, beta, gamma, ds, theta_eq_fn) -> dict:
    """The Bautin point for each value of ``gamma``, started where $\\ell_1$ changes sign along
    ``beta`` on the grid (linear interpolation)."""
    bs, gs = ds[beta].values, ds[gamma].values
    found = {k: np.full(gs.size, np.nan) for k in (beta, parameter, "second_lyapunov")}
    for j, g in enumerate(gs):
        l1 = ds["first_lyapunov"].values[:, j]
        change = np.nonzero(np.sign(l1[:-1]) * np.sign(l1[1:]) < 0)[0]
        if change.size == 0:
            continue
        i = int(change[0])
        b0 = bs[i] - l1[i] * (bs[i + 1] - bs[i]) / (l1[i + 1] - l1[i])
        a0 = 0.5 * (ds[parameter].values[i, j] + ds[parameter].values[i + 1, j])
        point = bautin_point(
            model_fn, {**params, gamma: g}, (parameter, beta), (a0, b0), theta_eq_fn=theta_eq_fn
        )
        if bool(point.ok):
            found[parameter][j], found[beta][j] = (float(v) for v in point.value)
            found["second_lyapunov"][j] = float(point.second_lyapunov)
    return {
        f"bautin_{beta}": ((gamma,), found[beta]),
        f"bautin_{parameter}": ((gamma,), found[parameter]),
        "second_lyapunov": ((gamma,), found["second_lyapunov"]),
    }


@functools.partial(jit, small=False)
def _loop(model_fn, parameter, others, values, x0, kick, dwell, samples, solver):
    """The piecewise-constant run (module docstring): per load value, the amplitude over the
    second half of the dwell, the end state and whether the solve succeeded."""
    ts = jnp.concatenate([jnp.zeros(1), jnp.linspace(0.5, 1.0, samples)]) * dwell

    def step(x, value):
        model = _build(model_fn, {**others, parameter: value})
        theta = x[:3] + jnp.asarray([kick, 0.0, 0.0], x.dtype)
        traj = fast_simulate(model, theta, x[3:], ts, throw=False, **solver)
        th = traj.theta[1:]
        amplitude = jnp.max(jnp.linalg.norm(th - jnp.mean(th, axis=0, keepdims=True), axis=1))
        end = jnp.concatenate([traj.theta[-1], traj.Omega[-1]])
        ok = traj.status == SolveStatus.successful
        return jnp.where(ok, end, x), (amplitude, end, ok)

    _, (amplitude, ends, ok) = jax.lax.scan(step, x0, values)
    return amplitude, ends, ok


def hysteresis_loop(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    values,
    theta0,
    Omega0,
    *,
    dwell: float = 2000.0,
    kick: float = 0.02,
    samples: int = 512,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 1_000_000,
):
    r"""The response to a quasi-static load (module docstring): ``values`` of ``parameter`` in
    the order applied (e.g. up, then down), each held for ``dwell``, starting from
    $(\theta_0, \Omega_0)$, with the disturbance ``kick`` (rad) at every change of the load.

    **Returns** an :class:`xarray.Dataset` over ``step``: ``parameter``, ``direction`` (+1
    where the load rose to this value, −1 where it fell; the first step +1), ``amplitude``
    ($\max_t|\theta - \bar\theta|$ over the second half of the dwell), the end ``theta`` and
    ``Omega`` (component) and ``ok`` (the solve succeeded; a failed step keeps its start state).
    """
    import xarray as xr

    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.size < 2:
        raise ValueError("values must be a 1-D array of at least two load values.")
    if not dwell > 0 or not samples >= 2:
        raise ValueError("dwell must be > 0 and samples >= 2.")
    others = {str(k): jnp.asarray(v, dtype=float) for k, v in params.items() if k != parameter}
    x0 = jnp.concatenate([jnp.asarray(theta0, float), jnp.asarray(Omega0, float)])
    solver = dict(rtol=float(rtol), atol=float(atol), max_steps=int(max_steps))
    amplitude, ends, ok = _loop(
        model_fn, parameter, others, jnp.asarray(values), x0, float(kick), float(dwell),
        int(samples), solver,
    )  # fmt: skip
    direction = np.sign(np.diff(values, prepend=values[0] - 1.0)).astype(np.int8)
    ends = np.asarray(ends)
    return xr.Dataset(
        {
            parameter: ("step", values),
            "direction": ("step", direction),
            "amplitude": ("step", np.asarray(amplitude)),
            "theta": (("step", "component"), ends[:, :3]),
            "Omega": (("step", "component"), ends[:, 3:]),
            "ok": ("step", np.asarray(ok)),
        },
        coords={"component": ["x", "y", "z"]},
        attrs={"parameter": parameter, "dwell": float(dwell), "kick": float(kick)},
    )
