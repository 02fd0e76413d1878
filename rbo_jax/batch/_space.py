"""The parameter space of a sweep: a grid (the Cartesian product of named axes) or a list of
points, cut into chunks (hyper-rectangular blocks of the grid, at most ``chunk_size`` points each;
each chunk is one compiled call)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

POINT_DIM = "point"  # the dimension of a list of points
RESERVED = (POINT_DIM, "status")


def _balanced(n: int, room: int) -> int:
    """The largest block ≤ ``room`` that cuts ``n`` into equal parts (up to one point)."""
    parts = -(-n // room)
    return -(-n // parts)


def _chunk_shape(shape: tuple[int, ...], chunk_size: int) -> tuple[int, ...]:
    """Block shape of at most ``chunk_size`` points: whole trailing axes first (C order), then a
    balanced split of the next one."""
    out = [1] * len(shape)
    room = chunk_size
    for ax in reversed(range(len(shape))):
        if room <= 1:
            break
        n = shape[ax]
        if n <= room:
            out[ax] = n
            room //= n
        else:
            out[ax] = _balanced(n, room)
            room = 1
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class Space:
    names: tuple[str, ...]  # parameter names, the quantity's keyword arguments
    values: dict  # grid: 1-D values of each axis; points: 1-D per-point values of each name
    grid: bool
    chunk_shape: tuple[int, ...]

    @property
    def dims(self) -> tuple[str, ...]:
        return self.names if self.grid else (POINT_DIM,)

    @property
    def shape(self) -> tuple[int, ...]:
        if self.grid:
            return tuple(self.values[n].size for n in self.names)
        return (self.values[self.names[0]].size,)

    @property
    def n_points(self) -> int:
        return math.prod(self.shape)

    @property
    def chunk_grid(self) -> tuple[int, ...]:
        return tuple(-(-s // c) for s, c in zip(self.shape, self.chunk_shape))

    @property
    def n_chunks(self) -> int:
        return math.prod(self.chunk_grid)

    @property
    def chunk_points(self) -> int:
        return math.prod(self.chunk_shape)

    def slices(self, chunk_id: int) -> tuple[slice, ...]:
        idx = np.unravel_index(chunk_id, self.chunk_grid)
        return tuple(
            slice(int(i) * c, min((int(i) + 1) * c, s))
            for i, c, s in zip(idx, self.chunk_shape, self.shape)
        )

    def points(self, slices: tuple[slice, ...]) -> np.ndarray:
        """The chunk's points, (m, len(names)) in C order of the block."""
        if self.grid:
            sub = [self.values[n][sl] for n, sl in zip(self.names, slices)]
            mesh = np.meshgrid(*sub, indexing="ij")
            return np.stack([g.ravel() for g in mesh], axis=1)
        return np.stack([self.values[n][slices[0]] for n in self.names], axis=1)

    def dummy(self) -> np.ndarray | None:
        """A point with finite coordinates (used for padding and for non-finite points), or None."""
        if self.grid:
            firsts = []
            for n in self.names:
                ok = np.flatnonzero(np.isfinite(self.values[n]))
                if ok.size == 0:
                    return None
                firsts.append(self.values[n][ok[0]])
            return np.asarray(firsts)
        pts = np.stack([self.values[n] for n in self.names], axis=1)
        ok = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
        return pts[ok[0]] if ok.size else None


def _as_1d(values, where: str) -> np.ndarray:
    try:
        v = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{where} must be a 1-D array of numbers.") from None
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"{where} must be a non-empty 1-D array, got shape {v.shape}.")
    return v


def _check_name(name, where: str) -> str:
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{where}: parameter name {name!r} must be a Python identifier.")
    if name in RESERVED or name.startswith("_"):
        raise ValueError(f"{where}: parameter name {name!r} is reserved; choose another.")
    return name


def make_space(axes, points, chunk_size) -> Space:
    if (axes is None) == (points is None):
        raise ValueError("give exactly one of `axes` (a grid) or `points` (a list of points).")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)):
        raise TypeError(f"chunk_size must be an integer, got {chunk_size!r}.")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}.")
    table, what = (axes, "axes") if axes is not None else (points, "points")
    if not isinstance(table, Mapping) or not table:
        raise ValueError(f"{what} must be a non-empty mapping {{name: 1-D array of values}}.")
    values = {}
    for name, v in table.items():
        _check_name(name, what)
        values[name] = _as_1d(v, f"{what}[{name!r}]")
    if points is not None:
        sizes = {n: v.size for n, v in values.items()}
        if len(set(sizes.values())) != 1:
            raise ValueError(
                f"points: every parameter needs the same number of values, got {sizes}."
            )
    names = tuple(values)
    grid = axes is not None
    shape = tuple(v.size for v in values.values()) if grid else (values[names[0]].size,)
    return Space(names, values, grid, _chunk_shape(shape, int(chunk_size)))
