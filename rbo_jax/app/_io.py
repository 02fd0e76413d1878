"""Files of the command line: xarray Datasets written as netCDF or zarr (and trajectories as CSV),
and observed trajectories read back for fitting.

netCDF has no complex type and only strings, numbers and arrays as attributes, so complex
variables are written as ``NAME_real``/``NAME_imag``, mapping and list attributes (e.g. a
lattice's ``shape``) as JSON text and boolean attributes as 0 or 1; zarr
format 3 specifies variable-length strings only, so string coordinates (``component = x, y, z``)
are written as such. Zarr stores are written with consolidated metadata, so
``xarray.open_zarr`` opens them directly.
"""

from __future__ import annotations

import importlib.util
import json
import os
import warnings

import numpy as np

__all__ = ["DATASET_SUFFIXES", "netcdf_engine", "write_dataset", "read_trajectory_file"]

DATASET_SUFFIXES = (".nc", ".zarr")


def netcdf_engine() -> str | None:
    """An installed netCDF engine of xarray (netCDF4, h5netcdf or scipy), or None."""
    for module, engine in (("netCDF4", "netcdf4"), ("h5netcdf", "h5netcdf"), ("scipy", "scipy")):
        if importlib.util.find_spec(module) is not None:
            return engine
    return None


def suffix(path) -> str:
    return os.path.splitext(str(path).rstrip("/"))[1].lower()


def _netcdf_attr(v, containers=(dict, list)):
    """An attribute netCDF can store: mappings and lists as JSON text, booleans as 0 or 1."""
    if isinstance(v, containers):
        return json.dumps(v)
    if isinstance(v, (bool, np.bool_)):
        return int(v)
    return v


def _for_netcdf(ds):
    ds = ds.copy()
    for name in list(ds.data_vars):
        if np.iscomplexobj(ds[name].values):
            v = ds[name]
            ds = ds.drop_vars(name).assign({f"{name}_real": v.real, f"{name}_imag": v.imag})
    ds.attrs = {k: _netcdf_attr(v) for k, v in ds.attrs.items()}
    for name in ds.variables:
        ds[name].attrs = {k: _netcdf_attr(v, dict) for k, v in ds[name].attrs.items()}
    return ds


def _for_zarr(ds):
    """Fixed-width strings (numpy ``<U``) have no zarr format 3 specification yet (zarr warns);
    variable-length strings (object dtype) do: convert."""
    ds = ds.copy()
    for name in list(ds.variables):
        if ds[name].dtype.kind in "US":
            ds[name] = ds[name].astype(object)
    return ds


def write_dataset(ds, path) -> None:
    """Write ``ds`` as netCDF (``.nc``) or zarr (``.zarr``), chosen by the suffix of ``path``."""
    kind = suffix(path)
    if kind == ".nc":
        engine = netcdf_engine()
        if engine is None:
            raise RuntimeError("writing .nc needs a netCDF engine for xarray: pip install "
                               "netCDF4, h5netcdf or scipy; or write .zarr.")
        _for_netcdf(ds).to_netcdf(path, engine=engine)
    elif kind == ".zarr":
        # zarr notes that consolidated metadata is not yet in the format 3 specification; zarr
        # and xarray read it, and xarray.open_zarr warns without it.
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")
            _for_zarr(ds).to_zarr(path, mode="w", zarr_format=3, consolidated=True)
    else:
        raise ValueError(f"{path}: unknown dataset format {kind!r}; use .nc or .zarr.")


def write_trajectory_csv(ds, path) -> None:
    """A trajectory Dataset (:meth:`rbo_jax.Trajectory.to_xarray`) as CSV: columns t,
    theta_x..z, Omega_x..z, energy."""
    t = np.asarray(ds["t"].values)
    cols = [t, np.asarray(ds["theta"].values), np.asarray(ds["Omega"].values),
            np.asarray(ds["energy"].values)]
    np.savetxt(path, np.column_stack(cols), delimiter=",", comments="", fmt="%.17g",
               header="t,theta_x,theta_y,theta_z,Omega_x,Omega_y,Omega_z,energy")


def read_trajectory_file(path) -> dict:
    """The arrays of an observed trajectory: ``t`` and any of ``theta``, ``Q``, ``Omega``,
    ``omega`` (and ``theta0``, ``Omega0``), from a dataset written by ``rbo-jax simulate --out``
    (``.nc``, ``.zarr``) or from an ``.npz`` file with arrays of those names. Raises
    ``ValueError``/``OSError`` with the reason."""
    kind = suffix(path)
    if kind == ".npz":
        with np.load(path, allow_pickle=False) as f:
            arrays = {name: f[name] for name in f.files}
        if "t" not in arrays and "ts" in arrays:
            arrays["t"] = arrays["ts"]
        return arrays
    import xarray as xr

    if kind == ".zarr":
        ds = xr.open_zarr(path, consolidated=None)
    elif kind == ".nc":
        ds = xr.open_dataset(path, engine=netcdf_engine())
    else:
        raise ValueError(f"unknown format {kind or '(no suffix)'!r}; use .nc, .zarr or .npz.")
    with ds:
        arrays = {name: np.asarray(ds[name].values) for name in ds.variables}
        if "reached" in arrays:  # samples after a solver failure are not observations
            keep = arrays["reached"].astype(bool)
            arrays = {k: v[keep] if v.ndim and v.shape[0] == keep.size else v
                      for k, v in arrays.items()}
    return arrays
