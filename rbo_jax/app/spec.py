r"""``ModelSpec``: a plain, validated description of a rigid body oscillator.

One description serves every front end: ``rbo-jax simulate|stability-map|fit`` build it from
command-line options, ``rbo-jax sweep`` from the ``[model]`` table of a TOML file,
``rbo-jax reproduce`` and user code directly. It is data — the inertia (4.39)/(4.40), the axis
$k$, the foundation terms (4.49)/(4.50) and the loads (4.57), (4.75), (4.84), each parameter a
number or the name of a sweep axis — and becomes a :class:`rbo_jax.RigidBodyOscillator` with
:meth:`ModelSpec.build`, also inside ``jax.vmap``/``jax.jit`` (the swept parameters are then
traced values).

The table form (what :meth:`ModelSpec.from_mapping` reads and :meth:`ModelSpec.to_mapping`
writes)::

    axis = [0.0, 0.0, 1.0]                                  # k (normalised)
    inertia = { A1 = 1.0, A3 = 0.5 }                        # (4.40); or { moments = [A1, A2, A3] }
    foundation = { type = "quadratic", c = 1.0, d = 2.0 }   # (4.50); or a list of such terms
    loads = [{ type = "follower", M = "M" },                # (4.57), M from the sweep axis "M"
             { type = "friction", b = 0.05 }]               # (4.84)

Foundation types: ``quadratic`` (4.50), ``barrier`` (4.49), ``cosine``
(:class:`rbo_jax.CosineFoundation`, $U = c(1 - \cos|\theta|)$, section 4.2.3: the pendulum
among foundations, whose chains are sine-Gordon chains) and ``none``
(:class:`rbo_jax.ZeroFoundation`, a free body: Kelvin's medium in a lattice).

``LatticeSpec``: a chain or grid of copies of that body (:mod:`rbo_jax.lattice`), neighbours
coupled by the quadratic foundation (4.50) of their relative turn with the bending and torsional
stiffnesses ``kappa_b``, ``kappa_t`` about the model's axis $k$, and a wavenumber ``q`` for the
Bloch waves (:func:`rbo_jax.lattice.dispersion`); ``rbo-jax simulate --lattice chain:64`` and
the ``[lattice]`` table of a sweep describe one::

    kind = "chain"          # or "grid" with shape = [16, 16] (or three sizes)
    n = 32                  # bodies of the chain (>= 2)
    periodic = true         # the last body coupled to the first (false: free ends)
    kappa_b = 0.8           # bending stiffness of the coupling (a number or an axis name)
    kappa_t = "kt"          # torsional stiffness
    q = "q"                 # wavenumber (rad per site; a grid: one per axis)

Errors name the key (``[model.foundation] c: must be > 0, got -1.``); the requirements are the
constructors' own (:mod:`rbo_jax._validation`), and a parameter taken from an axis is checked on
every value of that axis before anything runs.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import FINITE, NONNEGATIVE, POSITIVE, POSITIVE_OR_INF, Requirement
from ..foundations import (
    BarrierFoundation,
    CosineFoundation,
    QuadraticFoundation,
    ZeroFoundation,
)
from ..inertia import principal_inertia, transversely_isotropic_inertia
from ..loads import DeadMoment, FollowerMoment, Friction, SemiTangentialMoment
from ..models.rigid_body import RigidBodyOscillator
from ._reader import Reader, Ref, SpecError, plain, references, resolve, shown

__all__ = [
    "ModelSpec",
    "LatticeSpec",
    "Term",
    "Ref",
    "SpecError",
    "FOUNDATIONS",
    "LOADS",
    "LATTICES",
]

Value = float | Ref


@dataclasses.dataclass(frozen=True)
class _Param:
    name: str
    requirement: Requirement
    meaning: str
    default: float | None = None


@dataclasses.dataclass(frozen=True)
class _Kind:
    """One ``type`` of foundation term or load: its parameters and how to build it."""

    params: tuple[_Param, ...]
    build: Any  # (values dict, k) -> object
    equation: str


FOUNDATIONS = {
    "quadratic": _Kind(
        (_Param("c", POSITIVE, "bending stiffness"), _Param("d", POSITIVE, "torsional stiffness")),
        lambda v, k: QuadraticFoundation(v["c"], v["d"], k),
        "(4.50)",
    ),
    "barrier": _Kind(
        (
            _Param("c", POSITIVE, "bending stiffness"),
            _Param("d", POSITIVE, "torsional stiffness"),
            _Param("alpha", POSITIVE_OR_INF, "bending barrier"),
            _Param("beta", POSITIVE_OR_INF, "torsion barrier"),
        ),
        lambda v, k: BarrierFoundation(v["c"], v["d"], v["alpha"], v["beta"], k),
        "(4.49)",
    ),
    "cosine": _Kind(
        (_Param("c", NONNEGATIVE, "stiffness"),),
        lambda v, k: CosineFoundation(v["c"]),
        "(section 4.2.3)",
    ),
    "none": _Kind((), lambda v, k: ZeroFoundation(), "(U = 0)"),
}
LOADS = {
    "follower": _Kind(
        (_Param("M", FINITE, "follower moment"),), lambda v, k: FollowerMoment(v["M"], k), "(4.57)"
    ),
    "dead": _Kind(
        (_Param("M", FINITE, "dead moment"),), lambda v, k: DeadMoment(v["M"], k), "(4.75)"
    ),
    "semi_tangential": _Kind(
        (
            _Param("M", FINITE, "moment"),
            _Param("l1", FINITE, "dead part", 1.0),
            _Param("l2", FINITE, "follower part", 1.0),
        ),
        lambda v, k: SemiTangentialMoment(v["M"], k, v["l1"], v["l2"]),
        "(4.75)",
    ),
    "friction": _Kind(
        (_Param("b", NONNEGATIVE, "friction coefficient"),), lambda v, k: Friction(v["b"]), "(4.84)"
    ),
}
_INERTIA = {
    "transversely_isotropic": (
        _Param("A1", POSITIVE, "transverse moment of inertia"),
        _Param("A3", POSITIVE, "axial moment of inertia"),
    ),
    "principal": (_Param("moments", POSITIVE, "principal moments of inertia"),),
}


@dataclasses.dataclass(frozen=True)
class Term:
    """One piece of a model: a ``type`` and its parameters ``((name, value), ...)``; a value is
    a number, a :class:`Ref` to a sweep axis, or (principal moments) a tuple of those."""

    type: str
    params: tuple[tuple[str, Any], ...]

    def value(self, name):
        return dict(self.params)[name]


def _resolve(x, point: Mapping[str, Any]):
    """:func:`resolve` of a slot; a tuple (a vector) as one array."""
    if not isinstance(x, tuple):
        return resolve(x, point)
    parts = [_resolve(v, point) for v in x]
    if any(isinstance(v, jax.core.Tracer) for v in parts):
        return jnp.stack([jnp.asarray(v, dtype=jnp.result_type(float)) for v in parts])
    # concrete: a NumPy vector (jnp.stack would compile two small programs eagerly)
    return np.asarray([np.asarray(v) for v in parts], dtype=jnp.result_type(float))


def _read_term(r: Reader, table: Mapping, kinds: Mapping[str, _Kind], where: str) -> Term:
    kind = r.kind(table, kinds, where)
    spec = kinds[kind]
    names = [p.name for p in spec.params]
    r.keys(
        table, ("type", *names), where, required=[p.name for p in spec.params if p.default is None]
    )
    return Term(
        kind,
        tuple(
            (p.name, r.number(table, p.name, where, default=p.default, requirement=p.requirement))
            for p in spec.params
        ),
    )


def _read_inertia(r: Reader, model: Mapping, where: str) -> Term:
    table = r.table(model, "inertia", where, required=True)
    where = f"{where[:-1]}.inertia]"
    if "moments" in table:
        r.keys(table, ("moments",), where)
        return Term(
            "principal", (("moments", r.vector(table, "moments", where, requirement=POSITIVE)),)
        )
    r.keys(table, ("A1", "A3", "moments"), where, required=("A1", "A3"))
    return Term(
        "transversely_isotropic",
        tuple(
            (p.name, r.number(table, p.name, where, requirement=p.requirement))
            for p in _INERTIA["transversely_isotropic"]
        ),
    )


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """A rigid body oscillator as data (see the module docstring): ``axis`` $k$ (three values),
    ``inertia`` (a :class:`Term` of type ``transversely_isotropic`` (4.40) or ``principal``
    (4.39)), ``foundation`` (one or more terms, summed) and ``loads``."""

    inertia: Term
    foundation: tuple[Term, ...]
    loads: tuple[Term, ...] = ()
    axis: tuple[Any, Any, Any] = (0.0, 0.0, 1.0)

    @classmethod
    def from_mapping(
        cls,
        table: Mapping,
        *,
        axes: Mapping[str, np.ndarray] | None = None,
        where: str = "[model]",
        reader: Reader | None = None,
    ) -> ModelSpec:
        """Read and validate the table form; ``axes`` are the sweep axes parameters may name
        (checked value by value). Raises :class:`SpecError` naming the key."""
        r = reader if reader is not None else Reader(axes)
        if not isinstance(table, Mapping):
            r.fail(where, f"must be a table, got {type(table).__name__}.")
        r.keys(
            table,
            ("axis", "inertia", "foundation", "loads"),
            where,
            required=("inertia", "foundation"),
        )
        axis = r.vector(table, "axis", where, default=(0.0, 0.0, 1.0))
        if all(isinstance(x, float) for x in axis) and not any(axis):
            r.fail(f"{where} axis", "must be a nonzero vector, got [0, 0, 0].")
        inertia = _read_inertia(r, table, where)
        terms = table["foundation"]
        fwhere = f"{where[:-1]}.foundation]"
        if isinstance(terms, list):
            if not terms:
                r.fail(f"{where} foundation", "must be a table or a non-empty list of tables.")
            foundation = tuple(
                _read_term(r, t, FOUNDATIONS, f"{fwhere}[{i}]") for i, t in enumerate(terms)
            )
        else:
            foundation = (_read_term(r, terms, FOUNDATIONS, fwhere),)
        loads = table.get("loads", [])
        if not isinstance(loads, list):
            r.fail(
                f"{where} loads", 'must be a list of tables, e.g. [{ type = "follower", M = 0.5 }].'
            )
        loads = tuple(
            _read_term(r, t, LOADS, f"{where[:-1]}.loads][{i}]") for i, t in enumerate(loads)
        )
        return cls(inertia, foundation, loads, axis)

    def to_mapping(self) -> dict:
        """The table form (plain numbers, axis names as strings): ``from_mapping`` of it gives
        this spec back."""
        out = {"axis": plain(self.axis), "inertia": {n: plain(v) for n, v in self.inertia.params}}
        terms = [{"type": t.type, **{n: plain(v) for n, v in t.params}} for t in self.foundation]
        out["foundation"] = terms[0] if len(terms) == 1 else terms
        out["loads"] = [{"type": t.type, **{n: plain(v) for n, v in t.params}} for t in self.loads]
        return out

    def parameters(self) -> tuple[str, ...]:
        """The names of the sweep axes the description refers to, in order of appearance."""
        terms = (self.inertia, *self.foundation, *self.loads)
        return references((tuple(self.axis), *(v for t in terms for _, v in t.params)))

    def build(self, point: Mapping[str, Any] | None = None) -> RigidBodyOscillator:
        """The :class:`rbo_jax.RigidBodyOscillator`, with the axis references filled from
        ``point`` (``{axis name: value}``; traced values are fine)."""
        point = dict(point or {})
        missing = [n for n in self.parameters() if n not in point]
        if missing:
            raise KeyError(f"ModelSpec.build: no value for the parameter(s) {missing}.")
        k = _resolve(tuple(self.axis), point)
        v = {n: _resolve(x, point) for n, x in self.inertia.params}
        if self.inertia.type == "principal":
            A = principal_inertia(v["moments"], jnp.eye(3))
        else:
            A = transversely_isotropic_inertia(v["A1"], v["A3"], k)
        terms = [
            FOUNDATIONS[t.type].build({n: _resolve(x, point) for n, x in t.params}, k)
            for t in self.foundation
        ]
        foundation = terms[0] if len(terms) == 1 else sum(terms[1:], terms[0])
        loads = [
            LOADS[t.type].build({n: _resolve(x, point) for n, x in t.params}, k) for t in self.loads
        ]
        return RigidBodyOscillator(A, foundation, loads)

    def describe(self) -> str:
        """One line for people: inertia, axis, foundation and loads with their equations."""

        def g(x):
            return ",".join(map(g, x)) if isinstance(x, tuple) else shown(x)

        def params(term):
            return ", ".join(f"{n} = {g(x)}" for n, x in term.params)

        if self.inertia.type == "principal":
            parts = [f"A = diag({g(self.inertia.value('moments'))}) (4.39)"]
        else:
            parts = [f"{params(self.inertia)} (4.40)"]
        parts.append(f"k = ({g(tuple(self.axis))})")
        parts += [
            f"{t.type} foundation {FOUNDATIONS[t.type].equation} {params(t)}".rstrip()
            for t in self.foundation
        ]
        loads = [f"{t.type} {LOADS[t.type].equation} {params(t)}" for t in self.loads]
        parts.append("loads: " + ("; ".join(loads) if loads else "none"))
        return "; ".join(parts)


LATTICES = ("chain", "grid")
_SPEC_FORM = (
    "expected chain:N, grid:NxM or grid:NxMxK, optionally followed by :free (free "
    "ends instead of periodic), e.g. chain:64 or grid:16x16:free"
)


def _sizes(text: str) -> list[int]:
    try:
        return [int(x) for x in text.lower().split("x")]
    except ValueError:
        raise ValueError(_SPEC_FORM) from None


@dataclasses.dataclass(frozen=True)
class LatticeSpec:
    r"""A chain or grid of copies of a :class:`ModelSpec`'s body (see the module docstring):
    ``kind`` (``"chain"`` or ``"grid"``), ``shape`` (the sites along each axis), ``periodic``
    (or free ends), the coupling stiffnesses ``kappa_b``, ``kappa_t`` of
    :class:`rbo_jax.QuadraticFoundation` (4.50) of the relative turn about the model's axis,
    and the wavenumber ``q`` of the Bloch quantities (one value per axis); each parameter a
    number or a :class:`Ref` to a sweep axis."""

    kind: str
    shape: tuple[int, ...]
    periodic: bool = True
    kappa_b: Any = 1.0
    kappa_t: Any = 1.0
    q: tuple[Any, ...] = (0.0,)

    @staticmethod
    def table_from_text(text: str) -> dict:
        """``chain:N``, ``grid:NxM`` or ``grid:NxMxK``, optionally ``:free`` (the form of
        ``rbo-jax simulate --lattice``) as the table form (``kind``, ``n`` or ``shape``,
        ``periodic``); the sizes are checked by :meth:`from_mapping`. Raises ``ValueError``."""
        parts = text.strip().split(":")
        if (
            parts[0] not in LATTICES
            or len(parts) not in (2, 3)
            or parts[-1] == ""
            or (len(parts) == 3 and parts[2] != "free")
        ):
            raise ValueError(_SPEC_FORM)
        sizes = _sizes(parts[1])
        if (parts[0] == "chain") != (len(sizes) == 1) or len(sizes) > 3:
            raise ValueError(_SPEC_FORM)
        table = {"kind": parts[0], "periodic": len(parts) == 2}
        table |= {"n": sizes[0]} if parts[0] == "chain" else {"shape": sizes}
        return table

    # the signature of ModelSpec.from_mapping: the readers' common interface, not shared code
    @classmethod
    def from_mapping(
        cls,
        table: Mapping,
        *,
        axes: Mapping[str, np.ndarray] | None = None,
        where: str = "[lattice]",
        reader: Reader | None = None,
    ) -> LatticeSpec:
        """Read and validate the table form (module docstring); ``axes`` as in
        :meth:`ModelSpec.from_mapping`. Raises :class:`SpecError` naming the key."""
        r = reader if reader is not None else Reader(axes)
        if not isinstance(table, Mapping):
            r.fail(where, f"must be a table, got {type(table).__name__}.")
        r.keys(
            table,
            ("kind", "n", "shape", "periodic", "kappa_b", "kappa_t", "q"),
            where,
            required=("kind",),
        )
        kind = r.string(table, "kind", where, choices=LATTICES)
        wrong, right = ("shape", "n") if kind == "chain" else ("n", "shape")
        if wrong in table:
            r.fail(f"{where} {wrong}", f"is not a key of kind = {kind!r}; give {right}.")
        if kind == "chain":
            if "n" not in table:
                r.fail(where, "missing required key 'n' (the number of bodies of the chain).")
            shape = (r.integer(table, "n", where, default=None, minimum=2),)
        else:
            v = table.get("shape")
            if not (
                isinstance(v, list)
                and len(v) in (2, 3)
                and all(isinstance(x, int) and not isinstance(x, bool) and x >= 2 for x in v)
            ):
                r.fail(
                    f"{where} shape",
                    f"must be a list of 2 or 3 integers >= 2 (the sites "
                    f"along each axis of the grid), got {v!r}.",
                )
            shape = tuple(v)
        periodic = r.boolean(table, "periodic", where, default=True)
        kappa = [
            r.number(table, key, where, default=1.0, requirement=POSITIVE)
            for key in ("kappa_b", "kappa_t")
        ]
        if kind == "chain":
            q = (r.number(table, "q", where, default=0.0),)
        elif "q" in table:
            v = table["q"]
            if not isinstance(v, list) or len(v) != len(shape):
                r.fail(
                    f"{where} q",
                    f"a grid needs one wavenumber per axis: a list of "
                    f"{len(shape)} numbers or axis names, got {v!r}.",
                )
            q = tuple(r.number({"q": x}, "q", where) for x in v)
        else:
            q = (0.0,) * len(shape)
        return cls(kind, shape, periodic, kappa[0], kappa[1], q)

    def to_mapping(self) -> dict:
        """The table form: ``from_mapping`` of it gives this spec back."""
        size = {"n": self.shape[0]} if self.kind == "chain" else {"shape": list(self.shape)}
        q = plain(self.q[0]) if self.kind == "chain" else [plain(x) for x in self.q]
        return {
            "kind": self.kind,
            **size,
            "periodic": self.periodic,
            "kappa_b": plain(self.kappa_b),
            "kappa_t": plain(self.kappa_t),
            "q": q,
        }

    def parameters(self) -> tuple[str, ...]:
        """The names of the sweep axes the lattice refers to (not the body's)."""
        return references((self.kappa_b, self.kappa_t, *self.q))

    def build(self, model: ModelSpec, point: Mapping[str, Any] | None = None):
        """The :class:`rbo_jax.lattice.Lattice` of copies of ``model``'s body, the axis
        references of both filled from ``point`` (traced values are fine)."""
        from ..lattice import chain, grid

        point = dict(point or {})
        missing = [n for n in self.parameters() if n not in point]
        if missing:
            raise KeyError(f"LatticeSpec.build: no value for the parameter(s) {missing}.")
        k = _resolve(tuple(model.axis), point)
        coupling = QuadraticFoundation(
            _resolve(self.kappa_b, point), _resolve(self.kappa_t, point), k
        )
        body = model.build(point)
        if self.kind == "chain":
            return chain(self.shape[0], body, coupling, periodic=self.periodic)
        return grid(self.shape, body, coupling, periodic=self.periodic)

    def wavenumber(self, point: Mapping[str, Any] | None = None):
        """``q`` with the axis references filled: a number for a chain, one per axis for a
        grid (as :func:`rbo_jax.lattice.dispersion` takes it)."""
        point = dict(point or {})
        q = _resolve(tuple(self.q), point)
        return q[0] if self.kind == "chain" else q

    def describe(self) -> str:
        """One line for people: topology, ends and coupling."""
        where = (
            f"chain of {self.shape[0]} bodies"
            if self.kind == "chain"
            else f"{'x'.join(map(str, self.shape))} grid of {math.prod(self.shape)} bodies"
        )
        ends = "periodic" if self.periodic else "free ends"
        return (
            f"{where} ({ends}); coupling: quadratic foundation (4.50) of the relative turn, "
            f"kappa_b = {shown(self.kappa_b)}, kappa_t = {shown(self.kappa_t)}"
        )
