r"""Continuation of a Hopf point in two parameters: the flutter boundary.

The Hopf system of :mod:`._hopf` (equilibrium, eigenvalue pair $\pm i\omega$, normalisation) is
solved at successive values of a second parameter, each solve starting from the previous
solution (natural continuation in a ``lax.scan``: one compiled program, differentiable, and
vmapped over any further parameters given as arrays, e.g. the critical follower moment against
the friction coefficient $b$ for several ratios $A_3/A_1$ at once). Natural continuation cannot
pass a turning point of the boundary in the second parameter; there the status turns to
``not_converged`` and the rest of the curve is NaN.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..kinematics import _as_vector
from ..model import RigidBodyOscillator
from ._hopf import HopfStatus, _initial_unknowns, _masked, _solve

__all__ = ["continue_hopf"]


def _curve(model_fn, theta_eq_fn, parameter, along, t, rtol, atol, max_steps, others, guess,
           values, theta_guess):
    u0, v0, eq_ok, has_pair = _initial_unknowns(
        model_fn, theta_eq_fn, parameter, {**others, along: values[0]}, guess, theta_guess, t)

    def step(carry, value):
        u, w, alive = carry
        point, u_new = _solve(model_fn, parameter, t, {**others, along: value}, u, w, rtol, atol,
                              max_steps)
        good = alive & (point.status == HopfStatus.successful)
        v = jax.lax.complex(u_new[5:11], u_new[11:17])
        w_new = v / jnp.vdot(v, v)  # w^H v = 1 at the new solution
        status = HopfStatus.where(alive, point.status, HopfStatus.not_converged)
        point = eqx.tree_at(lambda h: h.status, point, status)
        carry = (jnp.where(good, u_new, u), jnp.where(good, w_new, w), good)
        return carry, _masked(point)

    alive = eq_ok & has_pair
    _, points = jax.lax.scan(step, (u0, v0, alive), values)
    return points


_curve_jit = eqx.filter_jit(_curve)


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

    others = {str(k): jnp.asarray(v, dtype=jnp.result_type(float))
              for k, v in params.items() if k not in (parameter, along)}
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
        return _curve_jit(model_fn, theta_eq_fn, parameter, along, t, float(rtol), float(atol),
                          int(max_steps), point, guess, values, theta_guess)

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
