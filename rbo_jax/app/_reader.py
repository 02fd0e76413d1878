"""Checked reading of nested tables (parsed TOML, or command-line options put in the same shape),
with messages that name the key at fault: ``[model.foundation] c: must be > 0, got -1.``

Numbers may instead be the names of sweep axes (strings); such a slot becomes a :class:`Ref`, and
every value the axis takes is checked against the slot's requirement before anything runs.
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Mapping, Sequence

import numpy as np

from .._validation import FINITE, Requirement


class SpecError(ValueError):
    """Invalid input; ``where`` names the key (e.g. ``[model.foundation] c``)."""

    def __init__(self, where: str, message: str):
        super().__init__(f"{where}: {message}")
        self.where, self.message = where, message


@dataclasses.dataclass(frozen=True)
class Ref:
    """A parameter slot filled from the sweep axis ``name``."""

    name: str


def resolve(x, point: Mapping):
    """A slot's value at ``point`` (``{axis name: value}``): the axis's value for a
    :class:`Ref`, the number itself otherwise."""
    return point[x.name] if isinstance(x, Ref) else x


def plain(x):
    """A slot in the table form: the axis name of a :class:`Ref`, a tuple as a list."""
    if isinstance(x, tuple):
        return [plain(v) for v in x]
    return x.name if isinstance(x, Ref) else x


def shown(x) -> str:
    """A slot for people: ``<name>`` of a :class:`Ref`, a number as ``:g``."""
    return f"<{x.name}>" if isinstance(x, Ref) else f"{x:g}"


def references(slots) -> tuple[str, ...]:
    """The axis names of the :class:`Ref` among ``slots`` (tuples searched too), in order of
    first appearance."""
    found: dict[str, None] = {}
    for x in slots:
        if isinstance(x, tuple):
            found |= dict.fromkeys(references(x))
        elif isinstance(x, Ref):
            found[x.name] = None
    return tuple(found)


def _fmt(x) -> str:
    return f"{x:g}" if isinstance(x, float) else repr(x)


class Reader:
    """Reads values out of tables; ``axes`` are the sweep axes a number may refer to (their
    names are recorded in ``used``)."""

    def __init__(self, axes: Mapping[str, np.ndarray] | None = None):
        self.axes = dict(axes or {})
        self.used: set[str] = set()

    @staticmethod
    def fail(where: str, message: str):
        raise SpecError(where, message)

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
                near = difflib.get_close_matches(str(k), allowed, n=1)
                hint = f" (did you mean {near[0]!r}?)" if near else ""
                self.fail(where, f"unknown key {k!r}{hint}; allowed: {', '.join(allowed)}.")
        for k in required:
            if k not in table:
                self.fail(where, f"missing required key {k!r}.")

    def kind(self, table, kinds: Sequence[str], where: str) -> str:
        """The ``type`` of the table of a term or a load, one of ``kinds``."""
        if not isinstance(table, Mapping):
            self.fail(where, f"must be a table, got {table!r}.")
        kind = table.get("type")
        if not isinstance(kind, str) or kind not in kinds:
            self.fail(
                f"{where} type", f"must be one of {', '.join(map(repr, kinds))}; got {kind!r}."
            )
        return kind

    def _axis(self, name: str, key: str, label: str, requirement: Requirement) -> Ref:
        if name not in self.axes:
            self.fail(
                label,
                f"{name!r} is neither a number nor an axis name (axes: "
                f"{', '.join(self.axes) or 'none'}).",
            )
        self.used.add(name)
        values = np.asarray(self.axes[name], dtype=float)
        values = values[np.isfinite(values)]  # non-finite points are flagged by the sweep
        bad = values[~np.asarray(requirement.holds(values), dtype=bool)]
        if bad.size:
            self.fail(
                label,
                f"axis {name!r} takes the value {bad[0]:g}, but {key} must be {requirement.text}.",
            )
        return Ref(name)

    def number(
        self,
        table,
        key,
        where,
        *,
        default=None,
        requirement: Requirement = FINITE,
        axis: bool = True,
    ):
        """A number (checked against ``requirement``) or, if ``axis``, an axis name."""
        if key not in table:
            if default is None:
                self.fail(where, f"missing required key {key!r}.")
            return default
        v = table[key]
        label = f"{where} {key}"
        if isinstance(v, str) and axis:
            return self._axis(v, key, label, requirement)
        if isinstance(v, str):
            self.fail(label, "must be a number, not an axis.")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(
                label, f"must be a number{' or an axis name' if axis else ''}, got {_fmt(v)}."
            )
        v = float(v)
        if not bool(requirement.holds(np.asarray(v))):
            self.fail(label, f"must be {requirement.text}, got {_fmt(v)}.")
        return v

    def vector(self, table, key, where, *, default=None, requirement: Requirement = FINITE):
        if key not in table:
            if default is None:
                self.fail(where, f"missing required key {key!r}.")
            return tuple(default)
        v = table[key]
        if not isinstance(v, (list, tuple)) or len(v) != 3:
            self.fail(f"{where} {key}", f"must be a list of 3 numbers or axis names, got {v!r}.")
        return tuple(self.number({key: x}, key, where, requirement=requirement) for x in v)

    def integer(self, table, key, where, *, default, minimum=1, maximum=None):
        v = table.get(key, default)
        ok = not isinstance(v, bool) and isinstance(v, int) and v >= minimum
        if not ok or (maximum is not None and v > maximum):
            bound = f"an integer >= {minimum}" + (f" and <= {maximum}" if maximum else "")
            self.fail(f"{where} {key}", f"must be {bound}, got {v!r}.")
        return v

    def boolean(self, table, key, where, *, default):
        v = table.get(key, default)
        if not isinstance(v, bool):
            self.fail(f"{where} {key}", f"must be true or false, got {v!r}.")
        return v

    def string(self, table, key, where, *, default=None, choices=None):
        if key not in table and default is None:
            self.fail(where, f"missing required key {key!r}.")
        v = table.get(key, default)
        if not isinstance(v, str) or not v:
            self.fail(f"{where} {key}", f"must be a non-empty string, got {v!r}.")
        if choices is not None and v not in choices:
            self.fail(
                f"{where} {key}", f"must be one of {', '.join(map(repr, choices))}; got {v!r}."
            )
        return v
