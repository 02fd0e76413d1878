"""``rbo-jax stability-map``: the Nikolai map (4.57)-(4.62), (4.69) over a grid of M, c, d, A3."""

from __future__ import annotations

import argparse
import math
import time

from .._io import DATASET_SUFFIXES, netcdf_engine, write_dataset
from .._outputs import save_figure
from ._common import (
    Failure,
    check_count,
    check_devices,
    check_number,
    check_output,
    model_spec,
    pyplot_or_fail,
)
from ._memory import BYTES_PER_MAP_POINT, check_memory

AXES = ("M", "c", "d", "A3")
K = (0.0, 0.0, 1.0)


def _spec(args, axes):
    """The Nikolai model (4.57)-(4.62) with the grid parameters as axis references."""
    table = {
        "axis": list(K),
        "inertia": {"A1": args.A1, "A3": "A3"},
        "foundation": {"type": "quadratic", "c": "c", "d": "d"},
        "loads": [{"type": "follower", "M": "M"}],
    }
    options = {
        "[model.inertia] A1": "--A1",
        "[model.inertia] A3": "--A3",
        "[model.foundation] c": "--c",
        "[model.foundation] d": "--d",
        "[model.loads][0] M": "--M",
        "[model.loads][1] b": "--friction",
    }
    if args.friction is not None:
        table["loads"].append({"type": "friction", "b": args.friction})
    return model_spec(table, options, axes=axes)


def _check_options(args, ranged, n):
    if args.out is not None:
        kind = check_output(args.out, "--out", DATASET_SUFFIXES)
        if kind == ".nc" and netcdf_engine() is None:
            raise Failure(
                "--out .nc needs a NetCDF engine for xarray (pip install netCDF4, "
                "h5netcdf or scipy); or write .zarr."
            )
        if kind == ".zarr":
            import importlib.util

            if importlib.util.find_spec("zarr") is None:
                raise Failure("--out .zarr needs zarr (pip install 'zarr>=3'); or write .nc.")
    plt = None
    if args.plot is not None:
        check_output(args.plot, "--plot", (".png", ".pdf", ".svg"))
        if args.out is not None and _same_file(args.out, args.plot):
            raise Failure(f"--plot {args.plot} is the file of --out; give two names.")
        if len(ranged) < 2:
            raise Failure(
                "--plot draws a map over two axes: give at least two of --M, --c, "
                "--d, --A3 as ranges start:stop:num."
            )
        plt = pyplot_or_fail("rbo-jax stability-map")
    check_count(args.chunk_size, "--chunk-size")
    check_devices(args.devices)
    check_number(args.rtol, "--rtol", above=0)
    sizes = " x ".join(f"--{name} {getattr(args, name).size:,}" for name in AXES)
    check_memory(
        n * BYTES_PER_MAP_POINT,
        f"the grid ({sizes} values: {n:,} points)",
        "give fewer points (--M, --c, --d, --A3), or run the map as a sweep with a "
        "store, written chunk by chunk (rbo-jax sweep CONFIG.toml, quantity "
        "spectral_abscissa; examples/nikolai_stability.toml)",
    )
    return plt


def _same_file(a: str, b: str) -> bool:
    import os

    return os.path.abspath(a) == os.path.abspath(b)


def _summary(ds, args, axes):
    """Counts of the classification, range of max Re p and (without friction) the deviation
    from the closed form (4.69)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ... import nikolai_spectrum
    from ...batch import STABILITY_KIND_NAMES

    kind = np.asarray(ds["kind"].values).ravel()
    counts = {name: int(np.sum(kind == i)) for i, name in enumerate(STABILITY_KIND_NAMES)}
    print(
        "classification (Lyapunov's first method, rbo_jax.classify, rtol "
        f"{args.rtol:g}): " + ", ".join(f"{name} {c}" for name, c in counts.items() if c)
    )
    a = np.asarray(ds["spectral_abscissa"].values)
    finite = a[np.isfinite(a)]
    if finite.size:
        print(f"spectral abscissa max Re p: min {finite.min():.6e}, max {finite.max():.6e}")
    if args.friction is None:
        grids = [jnp.asarray(g.ravel()) for g in np.meshgrid(*axes.values(), indexing="ij")]
        roots = jax.vmap(lambda M, c, d, A3: nikolai_spectrum(args.A1, A3, c, d, M))(*grids)
        closed = np.max(np.real(np.asarray(roots)), axis=1)
        ds.attrs["max_deviation_from_4_69"] = float(np.max(np.abs(closed - a.ravel())))
        print(
            "closed form (4.69): max |max Re p - max Re (4.69) roots| = "
            f"{ds.attrs['max_deviation_from_4_69']:.1e}"
        )


def _figure(plt, ds, args, axes, ranged):
    from ...plotting import plot_stability_map

    x, y = ranged[:2]
    select = {name: float(axes[name][axes[name].size // 2]) for name in ranged[2:]}
    where = ", ".join(f"{name} = {v:g}" for name, v in select.items())
    ax = plot_stability_map(
        ds,
        x,
        y,
        select=select or None,
        title=f"Nikolai problem: max Re p over ({x}, {y})" + (f" at {where}" if where else ""),
    )
    save_figure(ax.figure, args.plot, dpi=120, bbox_inches="tight")
    plt.close(ax.figure)
    print(f"figure -> {args.plot}")


def stability_map_command(args: argparse.Namespace) -> int:
    """``rbo-jax stability-map``: the Nikolai map (4.57)-(4.62), (4.69) over a grid."""
    from ... import nikolai_equilibrium, stability_map
    from ...batch import SweepError

    axes = {name: getattr(args, name) for name in AXES}
    ranged = [n for n, v in axes.items() if v.size > 1]
    n = math.prod(v.size for v in axes.values())
    plt = _check_options(args, ranged, n)
    spec = _spec(args, axes)

    def model_fn(M, c, d, A3):
        return spec.build({"M": M, "c": c, "d": d, "A3": A3})

    def theta_eq_fn(M, c, d, A3):
        return nikolai_equilibrium(M, d, K)  # (4.62); friction vanishes at rest

    fixed = ", ".join(f"{name} = {axes[name][0]:g}" for name in AXES if name not in ranged)
    print(
        f"Nikolai problem (4.57)-(4.62): {spec.describe()}; equilibrium theta = (M/d) k "
        "(4.62), spectrum of (4.63)-(4.67)"
    )
    grid_ = " x ".join(f"{name} ({axes[name].size})" for name in ranged)
    print(
        f"grid: {grid_ + f' = {n} points' if grid_ else 'a single point'}"
        + (f"; fixed {fixed}" if fixed else "")
    )
    start = time.perf_counter()
    try:
        ds = stability_map(
            model_fn,
            axes,
            theta_eq_fn=theta_eq_fn,
            chunk_size=args.chunk_size,
            rtol=args.rtol,
            progress=args.progress,
            devices=args.devices,
        )
    except SweepError as e:  # the sweep's own memory guard, should the estimate above pass
        raise Failure(str(e)) from None
    elapsed = time.perf_counter() - start
    ds = ds.squeeze([name for name in AXES if name not in ranged])
    ds.attrs.update(
        description="Nikolai problem (4.57)-(4.62): spectra of the equilibrium "
        "theta = (M/d) k under a follower moment M on the quadratic foundation (4.50)",
        model=spec.describe(),
        A1=args.A1,
        command="rbo-jax " + " ".join(args.argv),
    )
    if args.friction is not None:
        ds.attrs["friction_b"] = args.friction
    _summary(ds, args, axes)
    print(f"wall time {elapsed:.2f} s (compilation included)")
    if args.out is not None:
        write_dataset(ds, args.out)
        print(f"map -> {args.out}")
    if plt is not None:
        _figure(plt, ds, args, axes, ranged)
    return 0
