r"""Continuation of a flutter point in two parameters: the flutter boundary, for every model.

``method="natural"`` (the default): the flutter system of :mod:`._hopf_system` (equilibrium,
eigenvalue pair $\pm i\omega$ or Krein collision, normalisation) is solved at successive values
of a second parameter, each solve starting from the previous solution (its configuration,
unknowns and normalisation: natural continuation in a ``lax.scan`` around the one flutter
program, one compiled program per model structure, differentiable, and vmapped over any further
parameters given as arrays, e.g. the critical follower moment against the friction coefficient
$b$ for several ratios $A_3/A_1$ at once, spread over every local device). Natural continuation
cannot pass a turning point of the boundary in the second parameter (there the Jacobian of the
system in its unknowns is singular, and beyond it the boundary has no point at the next value);
there the status turns to ``not_converged`` and the rest of the curve is NaN: continue such a
boundary with ``method="arclength"``.

``method="arclength"``: Keller's pseudo-arclength continuation of the same system in the plane
of the two parameters (:mod:`._hopf_curve`), which passes turning points and reports them, the
Bautin points ($\ell_1 = 0$) and a Bogdanov–Takens end (frequency $\to 0$) of the boundary.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .._programs import jit
from .._sharding import map_points
from ..mechanics import AbstractMechanics
from ._hopf import cold_start, finish, hopf_keywords, prepare, solution
from ._hopf_system import HopfStatus, Spec, code_of, model_at

__all__ = ["continue_hopf"]

FIELDS = ("value", "frequency", "first_lyapunov", "transversality", "theta", "num_steps", "status")


def _curve(spec: Spec, model: AbstractMechanics, t, p, alpha0, guess, values, frequency):
    """The boundary over ``values`` of ``along`` (the last entry of the flat parameters): one
    scan around the flutter program, each step started from the last successful solution."""
    u0, C0 = (jnp.asarray(x) for x in cold_start(spec, model, p.dtype))
    failed = code_of(HopfStatus.not_converged)

    def step(carry, value):
        config, u, C, alive, first = carry
        q = jnp.concatenate([p, value[None]])
        y, raw = solution(spec, q, t, alpha0, config, ~first, u, C, frequency)
        good = alive & (raw.status == 0)
        status = jnp.where(alive, raw.status, failed).astype(raw.status.dtype)
        point = finish(spec, model, y, raw._replace(status=status))
        keep = lambda new, old: jax.tree_util.tree_map(  # noqa: E731
            lambda a, b: jnp.where(good, a, b), new, old
        )
        carry = (keep(y[0], config), keep(y[1], u), keep(y[2], C), good, jnp.zeros((), bool))
        out = {name: getattr(point, name) for name in FIELDS}
        out["status"] = enum.code(point.status)
        return carry, out

    guess = model_at(spec, alpha0, jnp.concatenate([p, values[:1]])).configuration(guess)
    init = (guess, u0, C0, jnp.ones((), bool), jnp.ones((), bool))
    _, points = jax.lax.scan(step, init, values)
    return points


_curve_program = jit(_curve, small=True)


def _batched(params: Mapping, parameter: str, along: str) -> list[str]:
    return [str(k) for k, v in params.items() if k not in (parameter, along) and np.ndim(v) == 1]


def continue_hopf(
    model_fn: Callable[..., AbstractMechanics],
    params: Mapping[str, object],
    parameter: str,
    guess,
    along: str,
    values,
    *,
    method: str = "natural",
    ds: float | None = None,
    ds_min: float | None = None,
    ds_max: float | None = None,
    max_points: int = 200,
    progress: bool = False,
    **hopf_options,
):
    r"""The flutter boundary of ``parameter`` = α against ``along`` = β (module docstring), as
    an :class:`xarray.Dataset`; any model.

    ``params`` holds the fixed parameters of ``model_fn``. The first point starts from
    ``guess`` (a value of α) exactly as :func:`rbo_jax.hopf_point` at β = ``values[0]``;
    ``hopf_options`` are its keywords (``kind``, ``theta_eq_fn``, ``theta_guess``, ``t``,
    ``rtol``, ``atol``, ``max_steps``, ``steps``, ``cluster``, ``frequency``,
    ``multiplicity``, ``lyapunov``), with its defaults, for every point of the curve.

    **method="natural"**: $\alpha_H(\beta)$ for β in ``values``, each point started from the
    previous solution; order ``values`` from the end where the guess is good. An entry of
    ``params`` given as a 1-D array is a batch axis (one curve per value; the curves are spread
    over every local device). Where the boundary turns back in β (a turning point, e.g. a
    minimum of β along it) the solve fails: ``status`` is ``not_converged`` from there on and
    the values are NaN; follow such a boundary with ``method="arclength"``. **Returns** a
    Dataset over the batch axes and ``along`` with the critical ``value`` (named
    ``parameter``), ``frequency``, ``first_lyapunov``, ``transversality`` (NaN where not
    computed: :func:`rbo_jax.hopf_point`'s ``lyapunov``), ``theta`` (the critical
    equilibrium's turn-vectors: ``component``, and ``body`` for a lattice or a rod),
    ``num_steps`` and ``status`` (int8 codes of :class:`rbo_jax.bifurcation.HopfStatus`,
    names in ``flag_meanings``); ``attrs`` name the ``parameter``, ``along``, the ``batch``
    axes, the ``method`` and the ``kind``. Differentiable with respect to the fixed parameters
    (``jax.grad`` of the underlying :func:`rbo_jax.hopf_point` solves).

    **method="arclength"**: Keller's pseudo-arclength continuation of the curve
    $(\alpha, \beta)$ (:mod:`rbo_jax.bifurcation._hopf_curve`): it starts at β = ``values[0]``,
    goes first towards ``values[1]`` and ends when β leaves ``[min(values), max(values)]``,
    after ``max_points`` points, at a Bogdanov–Takens point, or when the step falls below
    ``ds_min`` (default ``1e-6`` of the span of ``values``). The arclength step (in every
    unknown: the configuration's increments, α, ω, the eigenvector, β) starts at ``ds``
    (default ``0.02`` of the span), grows ×1.5 up to ``ds_max`` (default ``0.1`` of the span)
    after corrections of at most three Newton steps, and halves after failures. ``progress``:
    a tqdm bar. No batch axes (every entry of ``params`` a scalar). **Returns** a Dataset over
    ``point`` with ``parameter`` (α) and ``along`` (β) as data variables, ``frequency``,
    ``first_lyapunov``, ``transversality``, ``theta``, ``num_steps``, ``status``, and over
    ``special`` (as :func:`rbo_jax.continue_equilibria`): ``special_type``
    (``"turning_point"``: β turns back; ``"bautin"``: $\ell_1$ changes sign;
    ``"bogdanov_takens"``: the frequency tends to 0), ``special_value`` (β there),
    ``special_parameter`` (α there), ``special_index`` (the point before it),
    ``special_frequency`` and ``special_first_lyapunov`` (NaN where not computed); ``attrs``:
    ``parameter``, ``along``, ``method``, ``kind`` and ``stop_reason``. Not differentiable
    (a loop in Python around compiled steps).
    """
    if method not in ("natural", "arclength"):
        raise ValueError(f'method must be "natural" or "arclength", got {method!r}.')
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.size < 1 or not np.all(np.isfinite(values)):
        raise ValueError(f"values of {along!r} must be a non-empty 1-D array of finite values.")
    for name, v in params.items():
        if name not in (parameter, along) and (
            np.ndim(v) > 1 or (np.ndim(v) == 1 and np.size(v) == 0)
        ):
            raise ValueError(f"params[{name!r}] must be a scalar or a non-empty 1-D array.")
    batch = _batched(params, parameter, along)
    options = hopf_keywords(hopf_options, "continue_hopf")
    scalars = {k: v for k, v in params.items() if k not in (along, *batch)}
    first = {**scalars, **{k: np.ravel(params[k])[0] for k in batch}}
    if method == "arclength":
        if batch:
            raise ValueError(
                'method="arclength" follows one curve: params '
                + ", ".join(repr(name) for name in batch)
                + " given as arrays (batch axes) must be scalars; loop over their values."
            )
        from ._hopf_curve import continue_hopf_arclength

        steps_ = dict(ds=ds, ds_min=ds_min, ds_max=ds_max, max_points=int(max_points),
                      progress=progress)  # fmt: skip
        return continue_hopf_arclength(model_fn, first, parameter, guess, along, values, options,
                                       **steps_)  # fmt: skip
    spec, model, p0, alpha0, config, t = prepare(
        model_fn, first, parameter, guess, options, along=(along, values[0])
    )
    names = spec.names[:-1]  # the others (sorted), then along
    frequency = options["frequency"]
    grid = jnp.asarray(values, p0.dtype)

    def curve(**point):
        flat = [jnp.ravel(jnp.asarray({**first, **point}[n], p0.dtype)) for n in names]
        p = jnp.concatenate(flat) if flat else jnp.zeros(0, p0.dtype)
        return _curve_program(spec, model, t, p, alpha0, config, grid, frequency)

    if batch:  # a grid over the batch axes, spread over every local device
        axes = np.meshgrid(*(np.asarray(params[k], float) for k in batch), indexing="ij")
        flat = map_points(curve, {k: g.ravel() for k, g in zip(batch, axes)})
        out = {k: v.reshape(axes[0].shape + v.shape[1:]) for k, v in flat.items()}
    else:
        out = {k: np.asarray(v) for k, v in curve().items()}
    coords = {along: values, **{k: np.asarray(params[k], float) for k in batch}}
    return _dataset(out, spec, along, batch, coords)


def _dataset(out, spec: Spec, along: str, batch: list, coords: dict):
    """The natural continuation's Dataset."""
    import xarray as xr

    dims = (*batch, along)
    theta = np.asarray(out["theta"])
    turn = ("component",) if theta.ndim == len(dims) + 1 else ("body", "component")
    ds = xr.Dataset(
        {
            spec.parameter: (dims, np.asarray(out["value"])),
            "frequency": (dims, np.asarray(out["frequency"])),
            "first_lyapunov": (dims, np.asarray(out["first_lyapunov"])),
            "transversality": (dims, np.asarray(out["transversality"])),
            "theta": (dims + turn, theta),
            "num_steps": (dims, np.asarray(out["num_steps"]).astype(np.int32)),
            "status": (dims, np.asarray(out["status"]).astype(np.int8)),
        },
        coords={**coords, "component": ["x", "y", "z"]},
        attrs={
            "parameter": spec.parameter,
            "along": along,
            "batch": " ".join(batch),
            "method": "natural",
            "kind": spec.kind,
        },
    )
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    ds[spec.parameter].attrs["long_name"] = f"critical {spec.parameter} (flutter point)"
    return ds
