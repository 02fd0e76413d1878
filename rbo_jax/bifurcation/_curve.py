r"""Continuation of a Hopf point in two parameters: the flutter boundary.

``method="natural"`` (the default): the Hopf system of :mod:`._hopf` (equilibrium, eigenvalue
pair $\pm i\omega$, normalisation) is solved at successive values of a second parameter, each
solve starting from the previous solution (natural continuation in a ``lax.scan`` around the one
Hopf program of :mod:`._system`: one compiled program per model structure, differentiable, and
vmapped over any further parameters given as arrays, e.g. the critical follower moment against
the friction coefficient $b$ for several ratios $A_3/A_1$ at once). Natural continuation cannot
pass a turning point of the boundary in the second parameter (there the Jacobian of the Hopf
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
from ..kinematics import _as_vector
from ..model import RigidBodyOscillator
from ._hopf import HopfStatus, Static, canonical, finish, solution
from ._interface import model_solver
from ._system import normalisation_vector

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
        w_new = normalisation_vector(raw.u)  # w^H v = 1 at the new solution
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
    # keywords shared with hopf_point, bautin_point (a public, documented signature)
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    t=0.0,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 64,
    method: str = "natural",
    ds: float | None = None,
    ds_min: float | None = None,
    ds_max: float | None = None,
    max_points: int = 200,
    progress: bool = False,
    **options,
):
    r"""The Hopf boundary of ``parameter`` = α against ``along`` = β (module docstring), as an
    :class:`xarray.Dataset`.

    ``params`` holds the fixed parameters of ``model_fn``. The first point starts from
    ``guess`` (a value of α) exactly as :func:`rbo_jax.hopf_point` at β = ``values[0]``.

    **method="natural"**: $\alpha_H(\beta)$ for β in ``values``, each point started from the
    previous solution; order ``values`` from the end where the guess is good. An entry of ``params``
    given as a 1-D array is a batch axis (one curve per value; the curves are spread over every
    local device). Where the boundary turns back in β (a turning point, e.g. a minimum of β along
    it) the solve fails: ``status`` is ``not_converged`` from there on and the values are NaN;
    follow such a boundary with ``method="arclength"``. **Returns** a Dataset over the batch axes
    and ``along`` with the critical ``value`` (named ``parameter``), ``frequency``,
    ``first_lyapunov``, ``transversality``, ``theta`` (component) and ``status`` (int8 codes of
    :class:`rbo_jax.bifurcation.HopfStatus`, names in ``flag_meanings``); ``attrs`` name the
    ``parameter``, ``along``, the ``batch`` axes and the ``method``. Differentiable with respect to
    the fixed parameters (``jax.grad`` of the underlying :func:`rbo_jax.hopf_point` solves).

    **method="arclength"**: Keller's pseudo-arclength continuation of the curve
    $(\alpha, \beta)$ (:mod:`rbo_jax.bifurcation._hopf_curve`): it starts at β = ``values[0]``,
    goes first towards ``values[1]`` and ends when β leaves ``[min(values), max(values)]``,
    after ``max_points`` points, at a Bogdanov–Takens point, or when the step falls below
    ``ds_min`` (default ``1e-6`` of the span of ``values``). The arclength step (in the 18
    unknowns: θ, α, ω, the eigenvector, β) starts at ``ds`` (default ``0.02`` of the span),
    grows ×1.5 up to ``ds_max`` (default ``0.1`` of the span) after corrections of at most
    three Newton steps, and halves after failures. ``progress``: a tqdm bar. No batch axes
    (every entry of ``params`` a scalar). **Returns** a Dataset over ``point`` with
    ``parameter`` (α) and ``along`` (β) as data variables, ``frequency``, ``first_lyapunov``,
    ``transversality``, ``theta`` (component), ``status``, and over ``special`` (as
    :func:`rbo_jax.continue_equilibria`): ``special_type`` (``"turning_point"``: β turns
    back; ``"bautin"``: $\ell_1$ changes sign; ``"bogdanov_takens"``: the frequency tends to
    0), ``special_value`` (β there), ``special_parameter`` (α there), ``special_index`` (the
    point before it), ``special_frequency`` and ``special_first_lyapunov`` (NaN where not
    computed); ``attrs``: ``parameter``, ``along``, ``method`` and ``stop_reason``. Not
    differentiable (a loop in Python around compiled steps).

    **Other models.** A ``model_fn`` that returns a :class:`rbo_jax.lattice.Rod` is handed to
    :func:`rbo_jax.lattice.rod_continue_hopf` (both methods; the arclength method without the
    first Lyapunov coefficient and the codimension-two points; with ``options`` such as
    ``kind=`` and ``steps=``; protocol of
    :func:`rbo_jax.bifurcation._interface.model_solver`). ``options`` are refused for a rigid
    body oscillator.
    """
    # the model at one point: a batch axis (a 1-D entry of params) at its first value
    first = {k: np.ravel(np.asarray(v))[0] if np.ndim(v) == 1 else v for k, v in params.items()}
    first = {**first, parameter: guess, along: np.ravel(np.asarray(values))[0]}
    own = model_solver(model_fn, first, "rbo_continue_hopf")
    if own is not None:
        shared = dict(theta_eq_fn=theta_eq_fn, theta_guess=theta_guess, t=t, rtol=rtol)
        steps = dict(ds=ds, ds_min=ds_min, ds_max=ds_max, max_points=max_points,
                     progress=progress)  # fmt: skip
        return own(model_fn, params, parameter, guess, along, values, method=method, **shared,
                   atol=atol, max_steps=max_steps, **steps, **options)  # fmt: skip
    if options:
        raise TypeError(
            f"continue_hopf: unexpected keyword arguments {sorted(options)} for a "
            "RigidBodyOscillator (they are the options of other models' solvers, e.g. a rod's)."
        )
    others, batch, values, guess, theta_guess = _arguments(
        params, parameter, along, values, guess, theta_guess
    )
    if method == "arclength":
        options = dict(ds=ds, ds_min=ds_min, ds_max=ds_max, max_points=int(max_points))
        return _arclength(
            model_fn, params, parameter, guess, along, values, batch, others, theta_eq_fn,
            theta_guess, t, rtol, atol, max_steps, {**options, "progress": progress},
        )  # fmt: skip
    if method != "natural":
        raise ValueError(f'method must be "natural" or "arclength", got {method!r}.')
    static_args = (canonical(model_fn), canonical(theta_eq_fn), float(rtol), float(atol))
    return _natural(static_args, int(max_steps), parameter, along, values, guess, theta_guess,
                    batch, others, t)  # fmt: skip


def _arguments(params, parameter, along, values, guess, theta_guess):
    """The checked arguments: ``(others, batch, values, guess, theta_guess)``."""
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
    return others, batch, values, guess, theta_guess


def _natural(
    static_args, max_steps, parameter, along, values, guess, theta_guess, batch, others, t
):
    """``method="natural"``: the scan of :func:`_curve`, vmapped over the batch axes."""
    import xarray as xr

    model_fn, theta_eq_fn, rtol, atol = static_args

    def run(**point):
        names = tuple(point) + (along,)
        shapes = tuple(jnp.shape(v) for v in point.values()) + ((),)
        static = Static(model_fn, theta_eq_fn, parameter, names, shapes, rtol, atol, max_steps)
        parts = [jnp.ravel(v) for v in point.values()]
        p = jnp.concatenate(parts) if parts else jnp.zeros(0, values.dtype)
        return _curve_jit(static, jnp.asarray(t, dtype=values.dtype), p, guess, values, theta_guess)

    points = _on_every_device(run, batch, others) if batch else run(**others)
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
            "status": (dims, _codes(points).astype(np.int8)),
        },
        coords={**coords, "component": ["x", "y", "z"]},
        attrs={
            "parameter": parameter,
            "along": along,
            "batch": " ".join(batch),
            "method": "natural",
        },
    )
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    ds[parameter].attrs["long_name"] = f"critical {parameter} (Hopf point)"
    return ds


class _Points:
    """The fields of the curves spread over the devices (NumPy arrays)."""

    def __init__(self, out):
        for name in ("value", "frequency", "first_lyapunov", "transversality", "theta"):
            setattr(self, name, out[name])
        self.status_code = out["status_code"]


def _codes(points) -> np.ndarray:
    if isinstance(points, _Points):
        return np.asarray(points.status_code)
    return np.asarray(enum.code(points.status))


def _on_every_device(run, batch, others):
    """The curves of every point of the batch axes, spread over every local device
    (:func:`rbo_jax._sharding.map_points`), where the vmapped program ran on one."""
    fixed = {k: v for k, v in others.items() if k not in batch}

    def curve(**point):
        r = run(**point, **fixed)
        return {
            "value": r.value,
            "frequency": r.frequency,
            "first_lyapunov": r.first_lyapunov,
            "transversality": r.transversality,
            "theta": r.theta,
            "status_code": jnp.asarray(enum.code(r.status), jnp.int32),
        }

    grids = np.meshgrid(*(np.asarray(others[name]) for name in batch), indexing="ij")
    shape = grids[0].shape
    out = map_points(curve, {name: g.ravel() for name, g in zip(batch, grids)})
    return _Points({k: v.reshape(shape + v.shape[1:]) for k, v in out.items()})


def _arclength(
    model_fn, params, parameter, guess, along, values, batch, others, theta_eq_fn, theta_guess,
    t, rtol, atol, max_steps, options,
):  # fmt: skip
    """``method="arclength"``: checks, then :func:`._hopf_curve.continue_hopf_arclength`."""
    from ._hopf_curve import arclength_steps, continue_hopf_arclength

    if batch:
        raise ValueError(
            'method="arclength" follows one curve: params '
            + ", ".join(repr(name) for name in batch)
            + " given as arrays (batch axes) must be scalars; loop over their values."
        )
    arclength_steps(values, along, options["ds"], options["ds_min"], options["ds_max"])
    if options["max_points"] < 1:
        raise ValueError(f"max_points must be at least 1, got {options['max_points']}.")
    static = Static(
        canonical(model_fn),
        canonical(theta_eq_fn),
        parameter,
        tuple(others) + (along,),
        tuple(jnp.shape(v) for v in others.values()) + ((),),
        float(rtol),
        float(atol),
        int(max_steps),
    )
    context = (static.model_fn, {k: v for k, v in params.items()}, parameter, along)
    return continue_hopf_arclength(
        static, context, others, guess, np.asarray(values), theta_guess, t, **options
    )
