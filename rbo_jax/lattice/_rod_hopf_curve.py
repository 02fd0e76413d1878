r"""The flutter boundary of a rod in two parameters by natural continuation (what
:func:`rbo_jax.continue_hopf` does for a rod): the flutter point of :mod:`._rod_hopf` at each
value of the second parameter, started from the last load found, in one compiled scan, and
vmapped over batch axes spread over every local device; ``method="arclength"`` hands the curve
to :mod:`._rod_hopf_arclength`."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .. import _programs
from .._sharding import map_points
from ..bifurcation._system import HopfStatus
from ._rod import Rod
from ._rod_hopf import _SUCCESSFUL, _check_unused, _prepare, _solve
from ._rod_hopf_arclength import rod_continue_hopf_arclength
from ._rod_hopf_system import Options, Static

__all__ = ["rod_continue_hopf"]


def _curve(static: Static, options: Options, guess, others, along: str, values):
    """Natural continuation over ``values`` of ``along``: one scan around the solve, each point
    from the eigenvalues at the last flutter load found (the first from ``guess``)."""

    def step(start, value):
        raw = _solve(static, options, start, {**others, along: value})
        good = raw.status == _SUCCESSFUL
        return jnp.where(good, raw.value, start), (raw.value, raw.frequency, raw.num_steps,
                                                   raw.status)  # fmt: skip

    return jax.lax.scan(step, guess, values)[1]


_curve_program = _programs.jit(_curve, fast_compile=True)

FIELDS = ("value", "frequency", "num_steps", "status")  # of a curve, in this order


def rod_continue_hopf(
    model_fn: Callable[..., Rod],
    params: Mapping[str, object],
    parameter: str,
    guess,
    along: str,
    values,
    *,
    method: str = "natural",
    # keywords shared with rod_hopf_point (a public, documented signature)
    kind: str = "auto",
    steps: int = 1,
    cluster: float = 1e-5,
    frequency=None,
    multiplicity: int = 2,
    theta_eq_fn=None,
    theta_guess=None,
    t=0.0,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 32,
    ds: float | None = None,
    ds_min: float | None = None,
    ds_max: float | None = None,
    max_points: int = 200,
    progress: bool = False,
):
    r"""The flutter boundary of a rod, the load ``parameter`` against ``along`` (what
    :func:`rbo_jax.continue_hopf` does for a rod): natural continuation, the flutter point
    (:func:`rod_hopf_point`, with the same keywords) at each of ``values`` in order, started
    from the last load found (the first from ``guess``), in one compiled scan. The kind
    (``"auto"``) is chosen once, at the first point. An entry of ``params`` given as a 1-D
    array is a batch axis (one curve per value, ``jax.vmap``). **Returns** an
    :class:`xarray.Dataset` over the batch axes and ``along`` with the critical
    ``parameter``, ``frequency``, ``num_steps`` and ``status`` (int8 codes of
    :class:`rbo_jax.bifurcation.HopfStatus`; NaN values where it failed, and the next point
    starts from the last good one); ``attrs``: ``parameter``, ``along``, ``batch``,
    ``method``, ``kind``. Differentiable (``jax.grad`` of :func:`rod_hopf_point`) point by
    point; the Dataset itself is not.

    ``method="arclength"``: pseudo-arclength continuation of the boundary in the plane of
    ``parameter`` and ``along``, which passes its turning points in ``along``
    (:mod:`rbo_jax.lattice._rod_hopf_arclength`): from the flutter point at ``values[0]``,
    first towards ``values[1]``, until ``along`` leaves ``[min(values), max(values)]``, after
    ``max_points`` points, or when the step falls below ``ds_min``; ``ds``, ``ds_min``,
    ``ds_max`` and ``progress`` as for a rigid body (:func:`rbo_jax.continue_hopf`), the
    arclength measured in all the unknowns (the eigenvector's too). No batch axes. **Returns**
    a Dataset over ``point`` with ``parameter`` and ``along`` as data variables,
    ``frequency``, ``num_steps``, ``status``, and over ``special`` the turning points
    (``special_type``, ``special_value``: ``along`` there, ``special_parameter``,
    ``special_index``: the point before it); ``attrs``: ``parameter``, ``along``, ``method``,
    ``kind``, ``stop_reason``. The first Lyapunov coefficient and the codimension-two points
    of a rigid body's boundary are not computed for rods.
    """
    _check_unused(theta_eq_fn, theta_guess, t)
    values, batch = _checked(params, parameter, along, values, method)
    scalars = {k: v for k, v in params.items() if k != along and np.ndim(v) == 0}
    first = {**scalars, **{k: np.ravel(params[k])[0] for k in batch}}
    options = (rtol, atol, max_steps, cluster, frequency, multiplicity)
    static, options, _, guess = _prepare(model_fn, first, parameter, guess, kind, steps, options,
                                         along=(along, float(values[0])))  # fmt: skip
    dtype = guess.dtype
    others = {
        str(k): jnp.asarray(v, dtype) for k, v in params.items() if k not in (parameter, along)
    }
    if method == "arclength":
        return rod_continue_hopf_arclength(
            static, options, guess, others, along, values, ds=ds, ds_min=ds_min, ds_max=ds_max,
            max_points=max_points, progress=progress,
        )  # fmt: skip
    grid = jnp.asarray(values, dtype)

    def curve(**point):
        out = _curve_program(static, options, guess, {**others, **point}, along, grid)
        return dict(zip(FIELDS, out))

    if batch:  # a grid over the batch axes, spread over every local device
        axes = np.meshgrid(*(np.asarray(params[k], float) for k in batch), indexing="ij")
        flat = map_points(curve, {k: g.ravel() for k, g in zip(batch, axes)})
        out = [flat[k].reshape(axes[0].shape + flat[k].shape[1:]) for k in FIELDS]
    else:
        out = list(curve().values())
    coords = {along: values, **{k: np.asarray(params[k], float) for k in batch}}
    return _dataset(out, static, along, batch, coords)


def _checked(params, parameter: str, along: str, values, method: str):
    """The checked ``values`` (a NumPy array) and the batch axes (names)."""
    if method not in ("natural", "arclength"):
        raise ValueError(
            f'continue_hopf of a rod: method must be "natural" or "arclength", got {method!r}.'
        )
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.size < 1 or not np.all(np.isfinite(values)):
        raise ValueError("continue_hopf of a rod: values must be a 1-D array of finite values.")
    batch = [str(k) for k, v in params.items() if k not in (parameter, along) and np.ndim(v) == 1]
    for name, v in params.items():
        if name not in (parameter, along) and (
            np.ndim(v) > 1 or (np.ndim(v) == 1 and np.size(v) == 0)
        ):
            raise ValueError(f"continue_hopf of a rod: params[{name!r}] must be a scalar or a "
                             "non-empty 1-D array.")  # fmt: skip
    if method == "arclength" and batch:
        raise ValueError(
            'method="arclength" follows one curve: params '
            + ", ".join(repr(name) for name in batch)
            + " given as arrays (batch axes) must be scalars; loop over their values."
        )
    return values, batch


def _dataset(out, static: Static, along: str, batch: list, coords: dict):
    """The natural continuation's Dataset from the curves' fields (:data:`FIELDS`)."""
    import xarray as xr

    value, freq, num_steps, status = (np.asarray(x) for x in out)
    dims = (*batch, along)
    ds = xr.Dataset(
        {
            static.parameter: (dims, value),
            "frequency": (dims, freq),
            "num_steps": (dims, num_steps.astype(np.int32)),
            "status": (dims, status.astype(np.int8)),
        },
        coords=coords,
        attrs={
            "parameter": static.parameter,
            "along": along,
            "batch": " ".join(batch),
            "method": "natural",
            "kind": static.kind,
        },  # fmt: skip
    )
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    return ds
