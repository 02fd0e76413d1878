"""Files of the command line: xarray Datasets written as netCDF or zarr (and trajectories as CSV),
and observed trajectories read back for fitting.

netCDF has no complex type and only strings, numbers and arrays as attributes, so complex
variables are written as ``NAME_real``/``NAME_imag``, mapping and list attributes (e.g. a
lattice's ``shape``) as JSON text and boolean attributes as 0 or 1; zarr
format 3 specifies variable-length strings only, so string coordinates (``component = x, y, z``)
are written as such. Zarr stores are written with consolidated metadata, so
``xarray.open_zarr`` opens them directly.

Every file is written whole (:func:`rbo_jax.app._outputs.replacing`: a temporary beside the target,
renamed into place), and a file that cannot be read as a trajectory gives a ``ValueError`` that
says what is wrong with it, whatever the reader library raised.
"""

from __future__ import annotations

import importlib.util
import json
import os
import warnings
from pathlib import Path

import numpy as np

from ._outputs import replacing

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
            raise RuntimeError(
                "writing .nc needs a netCDF engine for xarray: pip install "
                "netCDF4, h5netcdf or scipy; or write .zarr."
            )
        with replacing(path) as tmp:
            _for_netcdf(ds).to_netcdf(tmp, engine=engine)
    elif kind == ".zarr":
        # zarr notes that consolidated metadata is not yet in the format 3 specification; zarr
        # and xarray read it, and xarray.open_zarr warns without it.
        with warnings.catch_warnings(), replacing(path) as tmp:
            warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")
            _for_zarr(ds).to_zarr(tmp, mode="w", zarr_format=3, consolidated=True)
    else:
        raise ValueError(f"{path}: unknown dataset format {kind!r}; use .nc or .zarr.")


def write_trajectory_csv(ds, path) -> None:
    """A trajectory Dataset (:meth:`rbo_jax.Trajectory.to_xarray`) as CSV: columns t,
    theta_x..z, Omega_x..z, energy."""
    t = np.asarray(ds["t"].values)
    cols = [
        t,
        np.asarray(ds["theta"].values),
        np.asarray(ds["Omega"].values),
        np.asarray(ds["energy"].values),
    ]
    with replacing(path) as tmp:
        np.savetxt(
            tmp,
            np.column_stack(cols),
            delimiter=",",
            comments="",
            fmt="%.17g",
            header="t,theta_x,theta_y,theta_z,Omega_x,Omega_y,Omega_z,energy",
        )


# the arrays a trajectory file may hold, all of real numbers
TRAJECTORY_ARRAYS = ("t", "ts", "theta", "Q", "Omega", "omega", "theta0", "Omega0")
_SIGNATURES = {
    ".npz": (b"PK\x03\x04", b"PK\x05\x06"),  # a zip archive (numpy.savez)
    ".nc": (b"CDF\x01", b"CDF\x02", b"CDF\x05", b"\x89HDF\r\n\x1a\n"),
}
_FORMATS = {".npz": ".npz archive (numpy.savez)", ".nc": "netCDF file", ".zarr": "zarr store"}


def _check_container(path: Path, kind: str) -> None:
    """The file exists, is of the right kind (file or folder) and starts like its format."""
    if not path.exists():
        raise ValueError("no such file")
    if kind == ".zarr":
        if not path.is_dir():
            raise ValueError("not a zarr store (a .zarr store is a folder)")
        return
    if path.is_dir():
        raise ValueError("is a folder, not a file")
    if not os.access(path, os.R_OK):
        raise ValueError("not readable (permissions)")
    with open(path, "rb") as f:
        head = f.read(8)
    if not head:
        raise ValueError("an empty file")
    if not head.startswith(_SIGNATURES[kind]):
        raise ValueError(f"not a {_FORMATS[kind]} (its first bytes are {head[:4]!r})")
    if head.startswith(b"\x89HDF") and netcdf_engine() not in ("netcdf4", "h5netcdf"):
        raise ValueError(
            "a netCDF 4 (HDF5) file, which needs the netCDF4 or h5netcdf package to "
            "be read (pip install netCDF4); 'rbo-jax simulate --out' writes netCDF 3"
        )


def _read_arrays(path, kind: str) -> dict:
    if kind == ".npz":
        # the file opened here, so that it is closed also when numpy fails to read it
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as f:
            arrays = {name: f[name] for name in f.files}
        if "t" not in arrays and "ts" in arrays:
            arrays["t"] = arrays["ts"]
        return arrays
    import xarray as xr

    if kind == ".zarr":
        ds = xr.open_zarr(path, consolidated=None)
    else:
        ds = xr.open_dataset(path, engine=netcdf_engine())
    with ds:
        arrays = {name: np.asarray(ds[name].values) for name in ds.variables}
        if "reached" in arrays:  # samples after a solver failure are not observations
            keep = arrays["reached"].astype(bool)
            arrays = {
                k: v[keep] if v.ndim and v.shape[0] == keep.size else v for k, v in arrays.items()
            }
    return arrays


def _reason(e: Exception) -> str:
    """An exception as a short phrase of one line."""
    text = " ".join(str(e).split())
    if len(text) > 200:
        text = text[:197] + "..."
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def read_trajectory_file(path) -> dict:
    """The arrays of an observed trajectory: ``t`` and any of ``theta``, ``Q``, ``Omega``,
    ``omega`` (and ``theta0``, ``Omega0``), from a dataset written by ``rbo-jax simulate --out``
    (``.nc``, ``.zarr``) or from an ``.npz`` file with arrays of those names. Raises
    ``ValueError`` with the reason (a missing, empty, corrupt or foreign file, arrays that are
    not real numbers), never the reader library's own error."""
    kind = suffix(path)
    if kind not in _FORMATS:
        raise ValueError(f"unknown format {kind or '(no suffix)'!r}; use .nc, .zarr or .npz.")
    _check_container(Path(path), kind)
    try:
        arrays = _read_arrays(path, kind)
    except MemoryError:
        raise
    except Exception as e:  # whatever numpy, xarray, zarr or the netCDF engine raise
        raise ValueError(f"not a readable {_FORMATS[kind]} ({_reason(e)})") from None
    for name in TRAJECTORY_ARRAYS:
        if name in arrays and arrays[name].dtype.kind not in "fiu":
            raise ValueError(
                f"array {name!r} must hold real numbers, got dtype {arrays[name].dtype}"
            )
    return arrays
