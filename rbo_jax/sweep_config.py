r"""Declarative sweeps: the TOML configuration of ``rbo-jax sweep CONFIG.toml``.

:func:`load_config` validates a configuration — model, axes or points, quantity, chunk size,
output — with messages naming the file and the key at fault, and builds the quantity (a function
of one parameter point) from the package's models, :func:`rbo_jax.simulate` and the stability
functions; :func:`run_config` runs it with :func:`rbo_jax.sweep.sweep` and draws the map with
:func:`rbo_jax.sweep.plot_sweep`. Examples: ``examples/*.toml``.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .foundations import BarrierFoundation, QuadraticFoundation
from .inertia import principal_inertia, transversely_isotropic_inertia
from .loads import DeadMoment, FollowerMoment, Friction, SemiTangentialMoment
from .model import RigidBodyOscillator
from .simulate import simulate
from .stability import classify, fast_spectrum, solve_equilibrium
from .sweep import _POINT_DIM, _pyplot, _summary_line, plot_sweep, sweep

__all__ = ["QUANTITIES", "ConfigError", "SweepConfig", "load_config", "run_config"]


QUANTITIES = {
    "final_state": "theta(t1) and Omega(t1) of simulate (and the number of steps)",
    "energy_drift": "max_t |E(t) - E(0)| / |E(0)| over `samples` times of simulate",
    "max_deviation": "max_t |theta(t) - theta(0)| over `samples` times of simulate",
    "spectral_abscissa": "max Re p of the spectrum at the equilibrium (Newton from theta_guess)",
}
_DEFAULT_PLOT = {"final_state": "theta", "energy_drift": "energy_drift",
                 "max_deviation": "max_deviation", "spectral_abscissa": "spectral_abscissa"}
_SIMULATION = ("final_state", "energy_drift", "max_deviation")


class ConfigError(ValueError):
    """A sweep configuration is invalid; the message names the file and the key."""


@dataclasses.dataclass(frozen=True)
class _Ref:
    """A parameter slot filled from the sweep axis ``name``."""

    name: str


def _resolve(x, p):
    return p[x.name] if isinstance(x, _Ref) else x


def _resolve_vector(xs, p):
    return jnp.stack([jnp.asarray(_resolve(x, p), dtype=jnp.result_type(float)) for x in xs])


class _Reader:
    """Checks keys and values of the parsed TOML, with messages naming ``[table] key``."""

    def __init__(self, source: str, axis_values: Mapping[str, np.ndarray]):
        self.source, self.axes, self.used = source, axis_values, set()

    def fail(self, where: str, msg: str):
        raise ConfigError(f"{self.source}: {where}: {msg}")

    def table(self, parent: Mapping, key: str, where: str, *, required: bool) -> dict:
        if key not in parent:
            if required:
                self.fail(where, f"missing required key {key!r}.")
            return {}
        t = parent[key]
        if not isinstance(t, Mapping):
            self.fail(where, f"{key!r} must be a table, got {type(t).__name__}.")
        return dict(t)

    def keys(self, table: Mapping, allowed: Sequence[str], where: str, required=()):
        for k in table:
            if k not in allowed:
                near = difflib.get_close_matches(k, allowed, n=1)
                hint = f" (did you mean {near[0]!r}?)" if near else ""
                self.fail(where, f"unknown key {k!r}{hint}; allowed: {', '.join(allowed)}.")
        for k in required:
            if k not in table:
                self.fail(where, f"missing required key {k!r}.")

    def number(self, table, key, where, *, default=None, positive=False, nonnegative=False):
        if key not in table:
            if default is None:
                self.fail(where, f"missing required key {key!r}.")
            return default
        v = table[key]
        label = f"{where} {key}"
        if isinstance(v, str):
            if v not in self.axes:
                self.fail(label, f"{v!r} is neither a number nor an axis name (axes: "
                                 f"{', '.join(self.axes) or 'none'}).")
            self.used.add(v)
            values = self.axes[v][np.isfinite(self.axes[v])]
            if positive:
                bad = values[~(values > 0)]
            else:
                bad = values[~(values >= 0)] if nonnegative else []
            if len(bad):
                self.fail(label, f"axis {v!r} takes the value {bad[0]:g}, but {key} must be "
                                 f"{'> 0' if positive else '>= 0'}.")
            return _Ref(v)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(label, f"must be a number or an axis name, got {v!r}.")
        v = float(v)
        if positive and not v > 0:
            self.fail(label, f"must be > 0, got {v:g}.")
        if nonnegative and not v >= 0:
            self.fail(label, f"must be >= 0, got {v:g}.")
        return v

    def vector(self, table, key, where, *, default=None, positive=False):
        if key not in table:
            if default is None:
                self.fail(where, f"missing required key {key!r}.")
            return tuple(default)
        v = table[key]
        if not isinstance(v, list) or len(v) != 3:
            self.fail(f"{where} {key}", f"must be a list of 3 numbers or axis names, got {v!r}.")
        return tuple(self.number({key: x}, key, where, positive=positive) for x in v)

    def integer(self, table, key, where, *, default, minimum=1):
        v = table.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
            self.fail(f"{where} {key}", f"must be an integer >= {minimum}, got {v!r}.")
        return v

    def boolean(self, table, key, where, *, default):
        v = table.get(key, default)
        if not isinstance(v, bool):
            self.fail(f"{where} {key}", f"must be true or false, got {v!r}.")
        return v


def _read_axes(cfg: Mapping, source: str):
    has_axes, has_points = "axes" in cfg, "points" in cfg
    if has_axes == has_points:
        raise ConfigError(f"{source}: give exactly one of the tables [axes] (a grid) or [points] "
                          "(a list of points).")
    key = "axes" if has_axes else "points"
    table = cfg[key]
    if not isinstance(table, Mapping) or not table:
        raise ConfigError(f"{source}: [{key}] must be a non-empty table of parameters.")
    values = {}
    for name, spec in table.items():
        where = f"[{key}] {name}"
        if not name.isidentifier() or name in (_POINT_DIM, "status") or name.startswith("_"):
            raise ConfigError(f"{source}: {where}: not a valid (or a reserved) parameter name.")
        if isinstance(spec, list):
            if not spec or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                   for x in spec):
                raise ConfigError(f"{source}: {where}: must be a non-empty list of numbers.")
            v = np.asarray(spec, dtype=np.float64)
        elif isinstance(spec, Mapping) and key == "axes":
            allowed = ("start", "stop", "num", "log")
            for k in spec:
                if k not in allowed:
                    raise ConfigError(f"{source}: {where}: unknown key {k!r}; allowed: "
                                      f"{', '.join(allowed)}.")
            for k in ("start", "stop", "num"):
                if k not in spec:
                    raise ConfigError(f"{source}: {where}: missing required key {k!r}.")
            start, stop, num, log = spec["start"], spec["stop"], spec["num"], spec.get("log", False)
            for k, x in (("start", start), ("stop", stop)):
                if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                    raise ConfigError(f"{source}: {where}.{k}: must be a finite number, got {x!r}.")
            if isinstance(num, bool) or not isinstance(num, int) or num < 1:
                raise ConfigError(f"{source}: {where}.num: must be an integer >= 1, got {num!r}.")
            if not isinstance(log, bool):
                raise ConfigError(f"{source}: {where}.log: must be true or false, got {log!r}.")
            if log:
                if not (start > 0 and stop > 0):
                    raise ConfigError(f"{source}: {where}: log = true needs start, stop > 0.")
                v = np.geomspace(float(start), float(stop), num)
            else:
                v = np.linspace(float(start), float(stop), num)
        else:
            form = "a list of numbers or {start, stop, num[, log]}" if key == "axes" else \
                "a list of numbers"
            raise ConfigError(f"{source}: {where}: must be {form}, got {spec!r}.")
        values[name] = v
    if key == "points":
        sizes = {n: v.size for n, v in values.items()}
        if len(set(sizes.values())) != 1:
            raise ConfigError(f"{source}: [points]: every parameter needs the same number of "
                              f"values, got {sizes}.")
    return key, values


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """A validated sweep configuration (from :func:`load_config`).

    Fields: ``source`` (the file), ``quantity_name``, ``quantity`` (the function of one point),
    ``axes`` or ``points`` (``{name: values}``), ``chunk_size``, ``output`` (the store),
    ``png`` (the figure, or None), ``plot`` (the variable drawn), ``dims`` (per-point dimension
    names), ``canonical`` (the parsed configuration as canonical JSON, stored with the results
    so that ``--resume`` refuses a changed configuration).
    """

    source: Path
    quantity_name: str
    quantity: Callable[..., Any]
    axes: dict | None
    points: dict | None
    chunk_size: int
    output: Path
    png: Path | None
    plot: str
    dims: dict
    canonical: str


def _build_model(r: _Reader, model: Mapping):
    """``model_fn(p)`` from the [model] table."""
    r.keys(model, ("axis", "inertia", "foundation", "loads"), "[model]",
           required=("inertia", "foundation"))
    k = r.vector(model, "axis", "[model]", default=(0.0, 0.0, 1.0))
    inertia = r.table(model, "inertia", "[model]", required=True)
    where = "[model.inertia]"
    if "moments" in inertia:
        r.keys(inertia, ("moments",), where)
        moments = r.vector(inertia, "moments", where, positive=True)

        def make_inertia(p):
            return principal_inertia(_resolve_vector(moments, p), jnp.eye(3))
    else:
        r.keys(inertia, ("A1", "A3", "moments"), where, required=("A1", "A3"))
        A1 = r.number(inertia, "A1", where, positive=True)
        A3 = r.number(inertia, "A3", where, positive=True)

        def make_inertia(p):
            return transversely_isotropic_inertia(_resolve(A1, p), _resolve(A3, p),
                                                  _resolve_vector(k, p))

    found = r.table(model, "foundation", "[model]", required=True)
    where = "[model.foundation]"
    kind = found.get("type")
    if kind == "quadratic":
        r.keys(found, ("type", "c", "d"), where, required=("c", "d"))
        c = r.number(found, "c", where, positive=True)
        d = r.number(found, "d", where, positive=True)

        def make_foundation(p):
            return QuadraticFoundation(_resolve(c, p), _resolve(d, p), _resolve_vector(k, p))
    elif kind == "barrier":
        r.keys(found, ("type", "c", "d", "alpha", "beta"), where,
               required=("c", "d", "alpha", "beta"))
        c = r.number(found, "c", where, positive=True)
        d = r.number(found, "d", where, positive=True)
        alpha = r.number(found, "alpha", where, positive=True)
        beta = r.number(found, "beta", where, positive=True)

        def make_foundation(p):
            return BarrierFoundation(_resolve(c, p), _resolve(d, p), _resolve(alpha, p),
                                     _resolve(beta, p), _resolve_vector(k, p))
    else:
        r.fail(f"{where} type", f"must be 'quadratic' or 'barrier', got {kind!r}.")

    loads_cfg = model.get("loads", [])
    if not isinstance(loads_cfg, list):
        r.fail("[model] loads",
               'must be a list of tables, e.g. [{ type = "follower", M = 0.5 }].')
    makers = []
    for i, load in enumerate(loads_cfg):
        where = f"[model.loads][{i}]"
        if not isinstance(load, Mapping):
            r.fail(where, f"must be a table, got {load!r}.")
        kind = load.get("type")
        if kind in ("follower", "dead"):
            r.keys(load, ("type", "M"), where, required=("M",))
            M = r.number(load, "M", where)
            cls = FollowerMoment if kind == "follower" else DeadMoment
            makers.append(lambda p, cls=cls, M=M: cls(_resolve(M, p), _resolve_vector(k, p)))
        elif kind == "semi_tangential":
            r.keys(load, ("type", "M", "l1", "l2"), where, required=("M",))
            M = r.number(load, "M", where)
            l1 = r.number(load, "l1", where, default=1.0)
            l2 = r.number(load, "l2", where, default=1.0)
            makers.append(lambda p, M=M, l1=l1, l2=l2: SemiTangentialMoment(
                _resolve(M, p), _resolve_vector(k, p), _resolve(l1, p), _resolve(l2, p)))
        elif kind == "friction":
            r.keys(load, ("type", "b"), where, required=("b",))
            b = r.number(load, "b", where, nonnegative=True)
            makers.append(lambda p, b=b: Friction(_resolve(b, p)))
        else:
            r.fail(f"{where} type", "must be one of 'follower', 'dead', 'semi_tangential', "
                                    f"'friction'; got {kind!r}.")

    def model_fn(p):
        return RigidBodyOscillator(make_inertia(p), make_foundation(p), [m(p) for m in makers])

    return model_fn


def _build_quantity(r: _Reader, cfg: Mapping, name: str, model_fn):
    eq = r.table(cfg, "equilibrium", "config", required=False)
    r.keys(eq, ("theta_guess", "classify_rtol"), "[equilibrium]")
    guess = r.vector(eq, "theta_guess", "[equilibrium]", default=(0.0, 0.0, 0.0))
    if "classify_rtol" in eq and name != "spectral_abscissa":
        r.fail("[equilibrium] classify_rtol", "is only used by quantity 'spectral_abscissa'.")
    if name == "spectral_abscissa":
        for section in ("initial", "solver"):
            if section in cfg:
                r.fail(f"[{section}]", "is not used by quantity 'spectral_abscissa'; remove it.")
        crtol = r.number(eq, "classify_rtol", "[equilibrium]", default=1e-9, positive=True)
        if isinstance(crtol, _Ref):
            r.fail("[equilibrium] classify_rtol", "must be a number, not an axis.")

        def spectral_abscissa(**p):
            model = model_fn(p)
            sol = solve_equilibrium(model, _resolve_vector(guess, p))
            spec = fast_spectrum(model, sol.theta)
            spec = jnp.where(sol.ok, spec, jnp.nan + 0j)
            kind, a = classify(spec, rtol=crtol)
            return {"spectral_abscissa": a, "kind": kind, "theta_eq": sol.theta}, sol.status

        return spectral_abscissa, {"theta_eq": ("component",)}

    init = r.table(cfg, "initial", "config", required=False)
    r.keys(init, ("theta0", "Omega0", "about_equilibrium"), "[initial]")
    theta0 = r.vector(init, "theta0", "[initial]", default=(0.0, 0.0, 0.0))
    Omega0 = r.vector(init, "Omega0", "[initial]", default=(0.0, 0.0, 0.0))
    about_eq = r.boolean(init, "about_equilibrium", "[initial]", default=False)
    if eq and not about_eq:
        r.fail("[equilibrium]", "is only used with [initial] about_equilibrium = true.")
    solver = r.table(cfg, "solver", "config", required=True)
    where = "[solver]"
    r.keys(solver, ("t1", "rtol", "atol", "max_steps", "samples"), where, required=("t1",))
    t1 = r.number(solver, "t1", where, positive=True)
    tols = {}
    for key in ("rtol", "atol"):
        tol = r.number(solver, key, where, default=1e-8, positive=True)
        if isinstance(tol, _Ref):
            r.fail(f"{where} {key}", "must be a number, not an axis.")
        tols[key] = tol
    max_steps = r.integer(solver, "max_steps", where, default=100_000)
    if "samples" in solver and name == "final_state":
        r.fail(f"{where} samples", "is not used by quantity 'final_state' (it keeps t1 only).")
    samples = r.integer(solver, "samples", where, default=101, minimum=2)

    def quantity(**p):
        model = model_fn(p)
        th0 = _resolve_vector(theta0, p)
        if about_eq:
            sol = solve_equilibrium(model, _resolve_vector(guess, p))
            th0 = jnp.where(sol.ok, sol.theta + th0, jnp.nan)  # no equilibrium: nonfinite_input
        T = jnp.asarray(_resolve(t1, p), dtype=jnp.result_type(float))
        n = 2 if name == "final_state" else samples
        ts = jnp.linspace(0.0, 1.0, n) * T
        traj = simulate(model, th0, _resolve_vector(Omega0, p), ts, max_steps=max_steps,
                        throw=False, **tols)
        if name == "final_state":
            values = {"theta": traj.theta[-1], "Omega": traj.Omega[-1]}
        elif name == "energy_drift":
            E = traj.energy
            scale = jnp.where(jnp.abs(E[0]) > 0, jnp.abs(E[0]), 1.0)
            values = {"energy_drift": jnp.max(jnp.abs(E - E[0])) / scale}
        else:
            deviation = jnp.linalg.norm(traj.theta - traj.theta[:1], axis=1)
            values = {"max_deviation": jnp.max(deviation)}
        values["num_steps"] = traj.num_steps
        return values, traj.status

    quantity.__name__ = name
    dims = {"theta": ("component",), "Omega": ("component",)} if name == "final_state" else {}
    return quantity, dims


def _parse_toml(path: Path) -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file.") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None


def load_config(path: str | os.PathLike) -> SweepConfig:
    """Read and validate a sweep configuration (TOML); see ``examples/*.toml``.

    Tables: ``[sweep]`` (``quantity``, ``output``, optional ``chunk_size``, ``plot``, ``png``);
    ``[axes]`` (a grid: ``name = [values]`` or ``{start, stop, num[, log]}``) or ``[points]``
    (equal-length lists); ``[model]`` (``axis``, ``inertia`` ``{A1, A3}`` or ``{moments}``,
    ``foundation`` ``{type = "quadratic", c, d}`` or ``{type = "barrier", c, d, alpha, beta}``,
    ``loads`` a list of ``{type = "follower"|"dead", M}``, ``{type = "semi_tangential", M, l1,
    l2}``, ``{type = "friction", b}``); for simulation quantities ``[solver]`` (``t1``, ``rtol``,
    ``atol``, ``max_steps``, ``samples``) and ``[initial]`` (``theta0``, ``Omega0``,
    ``about_equilibrium``); ``[equilibrium]`` (``theta_guess``, ``classify_rtol``).

    Every number of ``[model]``, ``[initial]``, ``[solver]`` and ``[equilibrium]`` may instead be
    the name of an axis (a string); every axis must be used. Relative paths are relative to the
    configuration file's folder. Raises :class:`ConfigError` naming the key at fault.
    """
    path = Path(path)
    cfg = _parse_toml(path)
    source = str(path)
    allowed = ("sweep", "axes", "points", "model", "initial", "solver", "equilibrium")
    for k in cfg:
        if k not in allowed:
            near = difflib.get_close_matches(k, allowed, n=1)
            hint = f" (did you mean [{near[0]}]?)" if near else ""
            raise ConfigError(f"{source}: unknown table [{k}]{hint}; allowed: "
                              f"{', '.join(f'[{a}]' for a in allowed)}.")
    key, values = _read_axes(cfg, source)
    r = _Reader(source, values)
    sw = r.table(cfg, "sweep", "config", required=True)
    r.keys(sw, ("quantity", "output", "chunk_size", "plot", "png"), "[sweep]",
           required=("quantity", "output"))
    name = sw["quantity"]
    if name not in QUANTITIES:
        r.fail("[sweep] quantity", f"must be one of {', '.join(QUANTITIES)}; got {name!r}.")
    for k in ("output", "png"):
        if k in sw and (not isinstance(sw[k], str) or not sw[k]):
            r.fail(f"[sweep] {k}", f"must be a path (a string), got {sw[k]!r}.")
    chunk_size = r.integer(sw, "chunk_size", "[sweep]", default=4096)
    model_fn = _build_model(r, r.table(cfg, "model", "config", required=True))
    quantity, dims = _build_quantity(r, cfg, name, model_fn)
    unused = [n for n in values if n not in r.used]
    if unused:
        r.fail(f"[{key}] {unused[0]}", "this axis is not used by any parameter; refer to it by "
                                       f"name, e.g. c = \"{unused[0]}\" in [model.foundation].")
    plot = sw.get("plot", _DEFAULT_PLOT[name])
    outputs = {"final_state": ("theta", "Omega", "num_steps"),
               "energy_drift": ("energy_drift", "num_steps"),
               "max_deviation": ("max_deviation", "num_steps"),
               "spectral_abscissa": ("spectral_abscissa", "kind", "theta_eq")}[name]
    if plot not in outputs:
        r.fail("[sweep] plot",
               f"must be an output of {name!r}: {', '.join(outputs)}; got {plot!r}.")
    base = path.parent
    output = base / sw["output"]
    png = base / sw["png"] if "png" in sw else output.with_suffix(".png")
    return SweepConfig(
        source=path, quantity_name=name, quantity=quantity,
        axes=values if key == "axes" else None, points=values if key == "points" else None,
        chunk_size=chunk_size, output=output, png=png, plot=plot, dims=dims,
        canonical=json.dumps(cfg, sort_keys=True),
    )


def run_config(config: SweepConfig | str | os.PathLike, *, resume: bool = False,
               overwrite: bool = False, progress: bool = True, output=None, png=None,
               plot: bool = True):
    """Run a configured sweep (:func:`load_config`): write the store and, on process 0, the PNG
    of the map. ``output`` / ``png`` override the configured paths. Returns ``(dataset, png path
    or None)``."""
    cfg = config if isinstance(config, SweepConfig) else load_config(config)
    out = Path(output) if output is not None else cfg.output
    ds = sweep(
        cfg.quantity, cfg.axes, points=cfg.points, chunk_size=cfg.chunk_size, store=out,
        resume=resume, overwrite=overwrite, progress=progress, dims=cfg.dims,
        attrs={"quantity": cfg.quantity_name, "config": cfg.canonical}, desc=cfg.quantity_name,
    )
    png_path = None
    if plot and jax.process_index() == 0:
        png_path = Path(png) if png is not None else (
            out.with_suffix(".png") if output is not None else cfg.png)
        plt = _pyplot()
        fig, ax = plt.subplots(figsize=(6.4, 4.8))
        what = cfg.plot if cfg.plot == cfg.quantity_name else f"{cfg.quantity_name}: {cfg.plot}"
        plot_sweep(ds, cfg.plot, ax=ax,
                   title=f"{what}   ({_summary_line(ds.attrs['status_counts'])})")
        fig.tight_layout()
        fig.savefig(png_path, dpi=120)
        plt.close(fig)
    return ds, png_path
