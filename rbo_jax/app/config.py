r"""Declarative sweeps: the TOML configuration of ``rbo-jax sweep CONFIG.toml``.

:func:`load_config` validates a configuration — model, axes or points, quantity, chunk size,
output, and for the Bloch quantities a lattice — with messages naming the file and the key at
fault, describes the model as a :class:`~rbo_jax.app.spec.ModelSpec` (and the lattice as a
:class:`~rbo_jax.app.spec.LatticeSpec`) and builds the quantity (:mod:`rbo_jax.app.quantities`);
:func:`run_config` runs it with :func:`rbo_jax.sweep` and draws the map with
:func:`rbo_jax.plot_sweep`. Examples: ``examples/*.toml``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import json
import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._validation import FINITE, POSITIVE
from ..batch import POINT_DIM, summary_line, sweep
from ..plotting import plot_sweep, pyplot
from ._cluster import dask_client
from ._outputs import save_figure
from ._reader import Reader, SpecError
from .quantities import (
    DEFAULT_PLOT,
    INTEGRATORS,
    LATTICE,
    OUTPUTS,
    QUANTITIES,
    ROD,
    SIMULATION,
    Settings,
    make_quantity,
)
from .rodspec import RodSpec
from .spec import LatticeSpec, ModelSpec

__all__ = ["QUANTITIES", "ConfigError", "SweepConfig", "load_config", "run_config"]

_TABLES = (
    "sweep",
    "axes",
    "points",
    "model",
    "lattice",
    "rod",
    "initial",
    "solver",
    "equilibrium",
    "stability",
)
# the quantities that read a table; the others ([model], [equilibrium]) every quantity but the
# rods' reads
_USED_BY = {
    "rod": ROD,
    "stability": ("rod_stability", "rod_critical_load"),
    "lattice": LATTICE,
    "initial": SIMULATION,
    "solver": SIMULATION + ("rod_motion",),
}
# what a required table holds, for the message that asks for it
_CONTENTS = {
    "rod": "n, length, bending, ..., loads",
    "lattice": "kind, n or shape, periodic, kappa_b, kappa_t, q",
}


class ConfigError(ValueError):
    """A sweep configuration is invalid; the message names the file and the key."""


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """A validated sweep configuration (from :func:`load_config`).

    Fields: ``source`` (the file), ``quantity_name``, ``quantity`` (the function of one point),
    ``axes`` or ``points`` (``{name: values}``), ``chunk_size``, ``output`` (the store),
    ``png`` (the figure, or None), ``plot`` (the variable drawn), ``dims`` (per-point dimension
    names), ``canonical`` (the parsed configuration as canonical JSON, stored with the results
    so that ``--resume`` refuses a changed configuration), ``model`` (the
    :class:`~rbo_jax.app.spec.ModelSpec`), ``lattice`` (the
    :class:`~rbo_jax.app.spec.LatticeSpec` of the Bloch quantities, else None), ``rod`` (the
    :class:`~rbo_jax.app.rodspec.RodSpec` of the rod quantities, else None; ``model`` is None
    then).
    """

    source: Path
    quantity_name: str
    quantity: Callable[..., Any]
    axes: dict | None
    points: dict | None
    chunk_size: int | None
    output: Path
    png: Path | None
    plot: str
    dims: dict
    canonical: str
    model: ModelSpec | None = None
    lattice: LatticeSpec | None = None
    rod: RodSpec | None = None


def _axis_values(r: Reader, spec, where: str, grid: bool) -> np.ndarray:
    if isinstance(spec, list):
        if not spec or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in spec
        ):
            r.fail(where, "must be a non-empty list of numbers.")
        return np.asarray(spec, dtype=np.float64)
    if not (isinstance(spec, Mapping) and grid):
        form = "a list of numbers or {start, stop, num[, log]}" if grid else "a list of numbers"
        r.fail(where, f"must be {form}, got {spec!r}.")
    r.keys(spec, ("start", "stop", "num", "log"), where, required=("start", "stop", "num"))
    start, stop, num, log = spec["start"], spec["stop"], spec["num"], spec.get("log", False)
    for k, x in (("start", start), ("stop", stop)):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            r.fail(f"{where}.{k}", f"must be a finite number, got {x!r}.")
    if isinstance(num, bool) or not isinstance(num, int) or num < 1:
        r.fail(f"{where}.num", f"must be an integer >= 1, got {num!r}.")
    if not isinstance(log, bool):
        r.fail(f"{where}.log", f"must be true or false, got {log!r}.")
    if log:
        if not (start > 0 and stop > 0):
            r.fail(where, "log = true needs start, stop > 0.")
        return np.geomspace(float(start), float(stop), num)
    return np.linspace(float(start), float(stop), num)


def _read_axes(cfg: Mapping) -> tuple[str, dict]:
    r = Reader()
    if ("axes" in cfg) == ("points" in cfg):
        r.fail(
            "config",
            "give exactly one of the tables [axes] (a grid) or [points] (a list of points).",
        )
    key = "axes" if "axes" in cfg else "points"
    table = cfg[key]
    if not isinstance(table, Mapping) or not table:
        r.fail(f"[{key}]", "must be a non-empty table of parameters.")
    values = {}
    for name, spec in table.items():
        where = f"[{key}] {name}"
        if not name.isidentifier() or name in (POINT_DIM, "status") or name.startswith("_"):
            r.fail(where, "not a valid (or a reserved) parameter name.")
        values[name] = _axis_values(r, spec, where, key == "axes")
    if key == "points":
        sizes = {n: v.size for n, v in values.items()}
        if len(set(sizes.values())) != 1:
            r.fail("[points]", f"every parameter needs the same number of values, got {sizes}.")
    return key, values


def _refuse_unused(r: Reader, cfg: Mapping, name: str, tables) -> None:
    """Each of ``tables`` that the configuration has must be one that quantity ``name`` reads."""
    for table in tables:
        users = _USED_BY.get(table, tuple(q for q in QUANTITIES if q not in ROD))
        if table not in cfg or name in users:
            continue
        if name in ROD:
            r.fail(f"[{table}]", f"is not used by quantity {name!r} (of a [rod]); remove it.")
        if table in ("rod", "stability", "lattice"):
            r.fail(
                f"[{table}]",
                f"is only used by the quantities {', '.join(users)}; quantity {name!r} is of "
                "one body.",
            )
        r.fail(f"[{table}]", f"is not used by quantity {name!r}; remove it.")


def _required(r: Reader, cfg: Mapping, name: str, table: str) -> Mapping:
    if table not in cfg:
        r.fail(
            "config",
            f"missing required key {table!r}: quantity {name!r} needs a [{table}] table "
            f"({_CONTENTS[table]}).",
        )
    return cfg[table]


def _only_for(r: Reader, table: Mapping, key: str, where: str, name: str, user: str) -> None:
    if key in table and name != user:
        r.fail(f"{where} {key}", f"is only used by quantity {user!r}.")


def _read_settings(r: Reader, cfg: Mapping, name: str) -> Settings:
    if name == "rod_motion":
        return _read_rod_solver(r, cfg)
    if name in ROD:
        return _read_stability(r, cfg, name)
    eq = r.table(cfg, "equilibrium", "config", required=False)
    r.keys(eq, ("theta_guess", "classify_rtol"), "[equilibrium]")
    guess = r.vector(eq, "theta_guess", "[equilibrium]", default=(0.0, 0.0, 0.0))
    _refuse_unused(r, cfg, name, ("initial", "solver"))
    _only_for(r, eq, "classify_rtol", "[equilibrium]", name, "spectral_abscissa")
    if name not in SIMULATION:
        crtol = r.number(
            eq, "classify_rtol", "[equilibrium]", default=1e-9, requirement=POSITIVE, axis=False
        )
        return Settings(theta_guess=guess, classify_rtol=crtol)
    init = r.table(cfg, "initial", "config", required=False)
    r.keys(init, ("theta0", "Omega0", "about_equilibrium"), "[initial]")
    about_eq = r.boolean(init, "about_equilibrium", "[initial]", default=False)
    if eq and not about_eq:
        r.fail("[equilibrium]", "is only used with [initial] about_equilibrium = true.")
    solver = r.table(cfg, "solver", "config", required=True)
    where = "[solver]"
    r.keys(
        solver,
        ("t1", "rtol", "atol", "max_steps", "samples", "integrator"),
        where,
        required=("t1",),
    )
    if "samples" in solver and name == "final_state":
        r.fail(f"{where} samples", "is not used by quantity 'final_state' (it keeps t1 only).")
    return Settings(
        theta0=r.vector(init, "theta0", "[initial]", default=(0.0, 0.0, 0.0)),
        Omega0=r.vector(init, "Omega0", "[initial]", default=(0.0, 0.0, 0.0)),
        about_equilibrium=about_eq,
        theta_guess=guess,
        t1=r.number(solver, "t1", where, requirement=POSITIVE),
        rtol=r.number(solver, "rtol", where, default=1e-8, requirement=POSITIVE, axis=False),
        atol=r.number(solver, "atol", where, default=1e-8, requirement=POSITIVE, axis=False),
        max_steps=r.integer(solver, "max_steps", where, default=100_000),
        samples=r.integer(solver, "samples", where, default=101, minimum=2),
        integrator=r.string(
            solver, "integrator", where, default="fast_simulate", choices=INTEGRATORS
        ),
    )


def _read_rod_solver(r: Reader, cfg: Mapping) -> Settings:
    """The ``[solver]`` table of ``rod_motion`` (:mod:`rbo_jax.app.quantities`): ``t1``
    (required), ``samples`` (101), ``dt`` (the midpoint rule's step; default the shorter of
    ``t1/1000`` and the samples' spacing), ``rtol`` (1e-8) and ``atol`` (1e-10) of its Newton
    iterations, ``max_steps`` (100,000)."""
    solver = r.table(cfg, "solver", "config", required=True)
    where = "[solver]"
    r.keys(solver, ("t1", "dt", "rtol", "atol", "max_steps", "samples"), where, required=("t1",))
    dt = r.number(solver, "dt", where, requirement=POSITIVE, axis=False) if "dt" in solver else None
    return Settings(
        t1=r.number(solver, "t1", where, requirement=POSITIVE),
        dt=dt,
        rtol=r.number(solver, "rtol", where, default=1e-8, requirement=POSITIVE, axis=False),
        atol=r.number(solver, "atol", where, default=1e-10, requirement=POSITIVE, axis=False),
        max_steps=r.integer(solver, "max_steps", where, default=100_000),
        samples=r.integer(solver, "samples", where, default=101, minimum=2),
    )


def _read_stability(r: Reader, cfg: Mapping, name: str) -> Settings:
    """The ``[stability]`` table of a rod quantity (:mod:`rbo_jax.app.quantities`): ``rtol``
    (default 1e-9; a small damping needs a smaller one, e.g. 1e-14, see
    :func:`rbo_jax.lattice.critical_load`), ``steps`` (Newton's load steps, default 1); for
    ``rod_critical_load`` also ``load_max`` (required), ``load_min`` (0), ``n_scan`` (32),
    ``n_bisect`` (40)."""
    t = r.table(cfg, "stability", "config", required=name == "rod_critical_load")
    where = "[stability]"
    critical = ("load_max", "load_min", "n_scan", "n_bisect")
    if name == "rod_critical_load":
        r.keys(t, ("rtol", "steps", *critical), where, required=("load_max",))
    else:
        for k in critical:
            _only_for(r, t, k, where, name, "rod_critical_load")
        r.keys(t, ("rtol", "steps"), where)
    s = Settings(
        classify_rtol=r.number(t, "rtol", where, default=1e-9, requirement=POSITIVE, axis=False),
        steps=r.integer(t, "steps", where, default=1),
    )
    if name != "rod_critical_load":
        return s
    lo = r.number(t, "load_min", where, default=0.0, requirement=FINITE, axis=False)
    hi = r.number(t, "load_max", where, requirement=FINITE, axis=False)
    if not hi > lo:
        r.fail(f"{where} load_max", f"must exceed load_min ({lo:g}), got {hi:g}.")
    return dataclasses.replace(
        s,
        load_max=hi,
        load_min=lo,
        n_scan=r.integer(t, "n_scan", where, default=32),
        n_bisect=r.integer(t, "n_bisect", where, default=40, minimum=0),
    )


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
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot be read: {e}") from None


def _read_sweep_table(r: Reader, cfg: Mapping) -> dict:
    sw = r.table(cfg, "sweep", "config", required=True)
    r.keys(
        sw,
        ("quantity", "output", "chunk_size", "plot", "png"),
        "[sweep]",
        required=("quantity", "output"),
    )
    if not isinstance(sw["quantity"], str) or sw["quantity"] not in QUANTITIES:
        r.fail(
            "[sweep] quantity", f"must be one of {', '.join(QUANTITIES)}; got {sw['quantity']!r}."
        )
    for k in ("output", "png"):
        if k in sw and (not isinstance(sw[k], str) or not sw[k]):
            r.fail(f"[sweep] {k}", f"must be a path (a string), got {sw[k]!r}.")
    # no chunk_size: rbo_jax.sweep's default, CHUNK_PER_DEVICE points per local device
    sw["chunk_size"] = (
        r.integer(sw, "chunk_size", "[sweep]", default=None) if "chunk_size" in sw else None
    )
    name = sw["quantity"]
    sw.setdefault("plot", DEFAULT_PLOT[name])
    if not isinstance(sw["plot"], str) or sw["plot"] not in OUTPUTS[name]:
        r.fail(
            "[sweep] plot",
            f"must be an output of {name!r}: {', '.join(OUTPUTS[name])}; got {sw['plot']!r}.",
        )
    return sw


def _read_model(r: Reader, cfg: Mapping, name: str):
    """``(model, lattice)`` of the quantity: the :class:`RodSpec` of ``[rod]`` and None, or the
    :class:`ModelSpec` of ``[model]`` and, for the Bloch quantities, the :class:`LatticeSpec`
    of ``[lattice]`` (else None)."""
    _refuse_unused(r, cfg, name, ("rod", "stability"))
    if name in ROD:
        table = _required(r, cfg, name, "rod")
        _refuse_unused(r, cfg, name, ("model", "lattice", "initial", "solver", "equilibrium"))
        _refuse_unused(r, cfg, name, ("stability",))
        return RodSpec.from_mapping(table, reader=r), None
    model = ModelSpec.from_mapping(r.table(cfg, "model", "config", required=True), reader=r)
    _refuse_unused(r, cfg, name, ("lattice",))
    if name not in LATTICE:
        return model, None
    return model, LatticeSpec.from_mapping(_required(r, cfg, name, "lattice"), reader=r)


def _check_table_names(cfg: Mapping):
    for k in cfg:
        if k not in _TABLES:
            near = difflib.get_close_matches(k, _TABLES, n=1)
            hint = f" (did you mean [{near[0]}]?)" if near else ""
            raise SpecError(
                "config",
                f"unknown table [{k}]{hint}; allowed: {', '.join(f'[{a}]' for a in _TABLES)}.",
            )


def load_config(path: str | os.PathLike) -> SweepConfig:
    """Read and validate a sweep configuration (TOML); see ``examples/*.toml``.

    Tables: ``[sweep]`` (``quantity``, ``output``, optional ``chunk_size``, ``plot``, ``png``);
    ``[axes]`` (a grid: ``name = [values]`` or ``{start, stop, num[, log]}``) or ``[points]``
    (equal-length lists); ``[model]`` (the table form of
    :class:`~rbo_jax.app.spec.ModelSpec`: ``axis``, ``inertia`` ``{A1, A3}`` or ``{moments}``,
    ``foundation`` ``{type = "quadratic", c, d}`` or ``{type = "barrier", c, d, alpha, beta}``
    or a list of such terms, ``loads`` a list of ``{type = "follower"|"dead", M}``,
    ``{type = "semi_tangential", M, l1, l2}``, ``{type = "friction", b}``); for simulation
    quantities ``[solver]`` (``t1``, ``rtol``, ``atol``, ``max_steps``, ``samples``,
    ``integrator`` = ``"fast_simulate"`` (the default) or ``"simulate"``) and
    ``[initial]`` (``theta0``, ``Omega0``, ``about_equilibrium``); ``[equilibrium]``
    (``theta_guess``, ``classify_rtol``). The rod quantities (``rod_stability``,
    ``rod_critical_load``, ``rod_motion``) take a ``[rod]`` table
    (:class:`~rbo_jax.app.rodspec.RodSpec`) and a ``[stability]`` table, or for
    ``rod_motion`` a ``[solver]`` table (``t1``, ``dt``, ``rtol``, ``atol``, ``max_steps``,
    ``samples``; :mod:`rbo_jax.app.quantities`), instead of ``[model]`` and the others.

    Every number of ``[model]``, ``[initial]``, ``[solver]`` and ``[equilibrium]`` may instead be
    the name of an axis (a string); every axis must be used. Relative paths are relative to the
    configuration file's folder. Raises :class:`ConfigError` naming the key at fault.
    """
    path = Path(path)
    cfg = _parse_toml(path)
    try:
        _check_table_names(cfg)
        key, values = _read_axes(cfg)
        r = Reader(values)
        sw = _read_sweep_table(r, cfg)
        name = sw["quantity"]
        model, lattice = _read_model(r, cfg, name)
        settings = _read_settings(r, cfg, name)
        unused = [n for n in values if n not in r.used]
        if unused:
            r.fail(
                f"[{key}] {unused[0]}",
                "this axis is not used by any parameter; refer to it "
                f'by name, e.g. c = "{unused[0]}" in '
                + ("[rod]." if name in ROD else "[model.foundation]."),
            )
    except SpecError as e:
        raise ConfigError(f"{path}: {e}") from None
    quantity, dims = make_quantity(name, model, settings, lattice)
    output = path.parent / sw["output"]
    png = path.parent / sw["png"] if "png" in sw else output.with_suffix(".png")
    return SweepConfig(
        source=path,
        quantity_name=name,
        quantity=quantity,
        axes=values if key == "axes" else None,
        points=values if key == "points" else None,
        chunk_size=sw["chunk_size"],
        output=output,
        png=png,
        plot=sw["plot"],
        dims=dims,
        canonical=json.dumps(cfg, sort_keys=True),
        model=None if name in ROD else model,
        lattice=lattice,
        rod=model if name in ROD else None,
    )


def run_config(
    config: SweepConfig | str | os.PathLike,
    *,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    output=None,
    png=None,
    plot: bool = True,
    retry_errors: bool = False,
    scheduler: str | None = None,
    workers: int | None = None,
    client=None,
    devices: int | None = None,
):
    """Run a configured sweep (:func:`load_config`): write the store and, on process 0, the PNG
    of the map. ``output`` / ``png`` override the configured paths; ``retry_errors`` (with
    ``resume``) computes again the points of status ``error`` (:func:`rbo_jax.sweep`). On Dask
    (``pip install 'rbo_jax[dask]'``): ``scheduler`` the address ``tcp://HOST:PORT`` of a running
    scheduler, or ``workers`` a local cluster of that many processes (closed at the end), or
    ``client`` a :class:`distributed.Client` (at most one of the three); this process still
    writes the store. ``devices``: the number of local devices (each worker's, on Dask) to
    compute on (default all). Returns ``(dataset, png path or None)``."""
    cfg = config if isinstance(config, SweepConfig) else load_config(config)
    out = Path(output) if output is not None else cfg.output
    if client is not None and (scheduler is not None or workers is not None):
        raise ValueError("give a client, a scheduler or workers, not several.")
    with (
        contextlib.nullcontext(client)
        if client is not None
        else dask_client(scheduler, workers) as client
    ):
        ds = sweep(
            cfg.quantity,
            cfg.axes,
            points=cfg.points,
            chunk_size=cfg.chunk_size,
            store=out,
            resume=resume,
            overwrite=overwrite,
            progress=progress,
            dims=cfg.dims,
            retry_errors=retry_errors,
            attrs={"quantity": cfg.quantity_name, "config": cfg.canonical},
            desc=cfg.quantity_name,
            client=client,
            devices=devices,
        )
    png_path = None
    if plot and jax.process_index() == 0:
        png_path = (
            Path(png)
            if png is not None
            else (out.with_suffix(".png") if output is not None else cfg.png)
        )
        plt = pyplot()
        fig, ax = plt.subplots(figsize=(6.4, 4.8))
        what = cfg.plot if cfg.plot == cfg.quantity_name else f"{cfg.quantity_name}: {cfg.plot}"
        plot_sweep(
            ds, cfg.plot, ax=ax, title=f"{what}   ({summary_line(ds.attrs['status_counts'])})"
        )
        fig.tight_layout()
        save_figure(fig, png_path, dpi=120)  # whole or not at all
        plt.close(fig)
    return ds, png_path
