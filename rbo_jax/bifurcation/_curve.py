r"""Continuation of a Hopf point in two parameters: the flutter boundary.

The Hopf system of :mod:`._hopf` (equilibrium, eigenvalue pair $\pm i\omega$, normalisation) is
solved at successive values of a second parameter, each solve starting from the previous
solution (natural continuation in a ``lax.scan`` around the one Hopf program of
:mod:`._system`: one compiled program per model structure, differentiable, and
vmapped over any further parameters given as arrays, e.g. the critical follower moment against
the friction coefficient $b$ for several ratios $A_3/A_1$ at once). Natural continuation cannot
pass a turning point of the boundary in the second parameter; there the status turns to
``not_converged`` and the rest of the curve is NaN.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .._programs import jit
from ..kinematics import _as_vector
from ..model import RigidBodyOscillator
from ._hopf import HopfStatus, Static, canonical, finish, solution

_SUCCESSFUL = int(np.asarray(enum.code(HopfStatus.successful)))
_NOT_CONVERGED = int(np.asarray(enum.code(HopfStatus.not_converged)))

__all__ = ["continue_hopf"]


def _curve(static, t, p, guess, values, theta_guess):
    """The boundary over ``values`` of the last entry of ``static.names`` (the parameter
    ``along``): one scan around the Hopf program (:mod:`._system`), each step started from the
    last successful solution."""
    dtype = p.dtype

    def step(carry, value):
        u, w, alive, first = carry
        q = jnp.concatenate([p, value[None]])
        raw = solution(static, q, guess, theta_guess, t, u, w, ~first)
        good = alive & (raw.status == _SUCCESSFUL)
        v = raw.u[5:11], raw.u[11:17]
        n2 = v[0] @ v[0] + v[1] @ v[1]
        w_new = jnp.concatenate([v[0], v[1]]) / n2  # w^H v = 1 at the new solution
        status = jnp.where(alive, raw.status, _NOT_CONVERGED)
        carry = (jnp.where(good, raw.u, u), jnp.where(good, w_new, w), good, jnp.zeros((), bool))
        return carry, finish(raw._replace(status=status.astype(raw.status.dtype)))

    init = (jnp.zeros(17, dtype), jnp.zeros(12, dtype), jnp.ones((), bool), jnp.ones((), bool))
    _, points = jax.lax.scan(step, init, values)
    return points


_curve_jit = jit(_curve, small=True)


def _batched(others: dict) -> list[str]:
    return [k for k, v in others.items() if jnp.ndim(v) == 1]


def continue_hopf(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    guess,
    along: str,
    values,
    *,
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    t=0.0,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 64,
):
    r"""The Hopf boundary $\alpha_H(\beta)$ of ``parameter`` = α against ``along`` = β, for β
    in ``values`` (module docstring), as an :class:`xarray.Dataset`.

    ``params`` holds the fixed parameters of ``model_fn``; an entry given as a 1-D array is a
    batch axis (vmapped; one curve per value, each started from ``guess``). The first point
    starts from ``guess`` exactly as :func:`rbo_jax.hopf_point`, the next ones from the previous
    solution; order ``values`` from the end where the guess is good.

    **Returns** a Dataset over the batch axes and ``along`` with the critical ``value`` (named
    ``parameter``), ``frequency``, ``first_lyapunov``, ``transversality``, ``theta``
    (component) and ``status`` (int8 codes of :class:`rbo_jax.bifurcation.HopfStatus`, names in
    ``flag_meanings``); ``attrs`` name the ``parameter``, ``along`` and the ``batch`` axes.
    Differentiable with respect to the fixed parameters (``jax.grad`` of
    the underlying :func:`rbo_jax.hopf_point` solves).
    """
    import xarray as xr

    from .. import _enumeration as enum

    others = {
        str(k): jnp.asarray(v, dtype=jnp.result_type(float))
        for k, v in params.items()
        if k not in (parameter, along)
    }
    batch = _batched(others)
    for name in others:
        if jnp.ndim(others[name]) > 1 or (jnp.ndim(others[name]) == 1 and others[name].size == 0):
            raise ValueError(f"params[{name!r}] must be a scalar or a non-empty 1-D array.")
    values = jnp.asarray(values, dtype=jnp.result_type(float))
    if values.ndim != 1 or values.size < 1:
        raise ValueError(f"values of {along!r} must be a non-empty 1-D array.")
    guess = jnp.asarray(guess, dtype=jnp.result_type(float))
    theta_guess = jnp.zeros(3) if theta_guess is None else _as_vector(theta_guess, "theta_guess")

    def run(**point):
        names = tuple(point) + (along,)
        shapes = tuple(jnp.shape(v) for v in point.values()) + ((),)
        static = Static(
            canonical(model_fn),
            canonical(theta_eq_fn),
            parameter,
            names,
            shapes,
            float(rtol),
            float(atol),
            int(max_steps),
        )
        parts = [jnp.ravel(v) for v in point.values()]
        p = jnp.concatenate(parts) if parts else jnp.zeros(0, values.dtype)
        return _curve_jit(static, jnp.asarray(t, dtype=values.dtype), p, guess, values, theta_guess)

    fn = run
    for name in reversed(batch):
        fn = _vmap_named(fn, name)
    points = fn(**others)
    dims = tuple(batch) + (along,)
    coords = {name: np.asarray(others[name]) for name in batch}
    coords[along] = np.asarray(values)
    ds = xr.Dataset(
        {
            parameter: (dims, np.asarray(points.value)),
            "frequency": (dims, np.asarray(points.frequency)),
            "first_lyapunov": (dims, np.asarray(points.first_lyapunov)),
            "transversality": (dims, np.asarray(points.transversality)),
            "theta": (dims + ("component",), np.asarray(points.theta)),
            "status": (dims, np.asarray(enum.code(points.status)).astype(np.int8)),
        },
        coords={**coords, "component": ["x", "y", "z"]},
        attrs={"parameter": parameter, "along": along, "batch": " ".join(batch)},
    )
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    ds[parameter].attrs["long_name"] = f"critical {parameter} (Hopf point)"
    return ds


def _vmap_named(fn, name):
    def batched(**point):
        value = point.pop(name)
        return jax.vmap(lambda v: fn(**point, **{name: v}))(value)

    return batched
