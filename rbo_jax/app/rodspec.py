r"""``RodSpec``: a plain, validated description of a rod (:func:`rbo_jax.lattice.rod`), the
``[rod]`` table of ``rbo-jax sweep`` and of ``rbo-jax simulate --rod``.

A rod of ``n`` bodies past the base along $e_3$, its constants per unit length and its loads
(:doc:`rods </topics/rods>`); every number may be the name of a sweep axis::

    n = 8                   # bodies past the base (>= 2)
    length = 1.0            # L
    bending = 1.0           # EI      (torsion GJ, shear kappa GA, stretch EA as well)
    mass = 1.0              # rho A   (rotary: rho I per length about a transverse axis)
    damping = "eta"         # Kelvin-Voigt time of every stress resultant (s)
    shear_damping = 0.0     # another one for shear and stretch (default: damping)
    tip_mass = "Mt"         # a point mass on the tip (Pflueger's column)
    base = "clamped"        # or "pinned", "free"
    loads = [{ type = "tip_force", f = [0.0, 0.0, -1.0], scale = "P", follower = true }]

A tapered rod: each constant of :data:`PER_SEGMENT` (``bending``, ``torsion``, ``shear``,
``stretch``, ``mass``, ``rotary``, ``damping``, ``shear_damping``) may instead be a list of
exactly ``n`` values, one per segment from the base to the tip (segment ``i`` between bodies
``i`` and ``i + 1``, 0-based), each a number or an axis name and each checked as the scalar
(``[rod] bending[3]: must be > 0, got -1.``); or a linear taper ``{ base = a, tip = b }``,
sampled at the segments' middles: segment ``i`` gets $a + (b - a)(i + 1/2)/n$ (both ends
checked, so every segment's value is too)::

    bending = [2.0, 1.5, 1.0, 0.5]          # n = 4
    mass = { base = 2.0, tip = "m_tip" }     # 2 at the base to the axis m_tip at the tip

``length`` and ``tip_mass`` are scalars; a ``rotary`` list is $\rho I$ per segment (the polar
one $2\rho I$; no ``(rho_I, rho_J)`` pair).

The defaults (``length``, ``bending``, ``torsion``, ``mass`` 1; ``shear``, ``stretch`` 1e6;
``rotary`` 1e-6; no damping, no tip mass, clamped) make a nearly unshearable, inextensible
Euler–Bernoulli cantilever in units $EI = L = \rho A = 1$: loads in $EI/L^2$, times in
$\sqrt{\rho A L^4/EI}$. Loads (each ``scale`` × its vector, ``scale`` 1 by default):

- ``tip_force``: ``f`` on the tip (or ``body``), dead or ``follower`` (in the tip's frame,
  turning with it: Beck's column), :class:`rbo_jax.lattice.TipForce`;
- ``tip_moment``: ``m``, dead or ``follower``, :class:`rbo_jax.lattice.TipMoment`;
- ``gravity``: ``g`` on every mass, :class:`rbo_jax.lattice.Gravity`;
- ``distributed``: ``q`` per length, :class:`rbo_jax.lattice.DistributedForce`.

:meth:`RodSpec.build` makes the :class:`rbo_jax.lattice.Rod` at a point of the sweep (traced
values inside ``jax.vmap``; a per-segment constant as an ``(n,)`` array), with every load times
a load factor $\lambda$ if one is given (the ``rod_critical_load`` quantity searches
$\lambda$). Errors name the key (``[rod] bending: must be > 0, got -1.``); a parameter taken
from an axis is checked on every value of that axis before anything runs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._validation import NONNEGATIVE, POSITIVE, Requirement, array_namespace
from ._reader import Reader, plain, references, resolve, shown

__all__ = ["PER_SEGMENT", "ROD_KEYS", "ROD_LOADS", "RodLoadSpec", "RodSpec", "Taper"]

# key: (default, requirement); n, base and loads are read on their own
ROD_KEYS: dict[str, tuple[float | None, Requirement]] = {
    "length": (1.0, POSITIVE),
    "bending": (1.0, POSITIVE),
    "torsion": (1.0, POSITIVE),
    "shear": (1e6, POSITIVE),
    "stretch": (1e6, POSITIVE),
    "mass": (1.0, POSITIVE),
    "rotary": (1e-6, POSITIVE),
    "damping": (0.0, NONNEGATIVE),
    "tip_mass": (0.0, NONNEGATIVE),
}
# the constants rod() takes per segment (shape (n,)): a list of n values or a Taper as well
PER_SEGMENT = (
    "bending",
    "torsion",
    "shear",
    "stretch",
    "mass",
    "rotary",
    "damping",
    "shear_damping",
)
# type: (the vector's key, its default, may it follow the body and pick a body, the class of
# rbo_jax.lattice)
ROD_LOADS = {
    "tip_force": ("f", None, True, "TipForce"),
    "tip_moment": ("m", None, True, "TipMoment"),
    "gravity": ("g", (0.0, 0.0, -9.81), False, "Gravity"),
    "distributed": ("q", None, False, "DistributedForce"),
}
BASES = ("clamped", "pinned", "free")


@dataclasses.dataclass(frozen=True)
class RodLoadSpec:
    """One load of a :class:`RodSpec`: ``type`` (a key of :data:`ROD_LOADS`), ``vector`` (3
    numbers or :class:`Ref`), ``scale``, ``follower``, ``body`` (tip: -1)."""

    type: str
    vector: tuple
    scale: Any = 1.0
    follower: bool = False
    body: int = -1


@dataclasses.dataclass(frozen=True)
class Taper:
    """A constant that goes linearly from ``base`` (at the base) to ``tip`` (at the tip), both
    numbers or :class:`Ref`, sampled at the middles of the ``n`` segments."""

    base: Any
    tip: Any


def _value(x, point: Mapping[str, Any]):
    v = resolve(x, point)
    return array_namespace(v).asarray(v, dtype=jnp.result_type(float))


def _constant(x, point: Mapping[str, Any], n: int):
    """A scalar, or the ``(n,)`` array of a list (tuple) or a :class:`Taper`, at ``point``:
    NumPy where no axis is referred to (a constant stays known when traced code builds the rod:
    an undamped rod is reversible, :func:`rbo_jax.classify`), else traced."""
    if isinstance(x, tuple):
        values = [_value(e, point) for e in x]
        return array_namespace(*values).stack(values)
    if isinstance(x, Taper):
        a, b = _value(x.base, point), _value(x.tip, point)
        xp = array_namespace(a, b)
        return a + (b - a) * ((xp.arange(n, dtype=a.dtype) + 0.5) / n)
    return _value(x, point)


def _plain(x):
    if isinstance(x, Taper):
        return {"base": plain(x.base), "tip": plain(x.tip)}
    return plain(x)


def _g(x) -> str:
    if isinstance(x, tuple):
        return f"[{', '.join(map(_g, x))}]"
    if isinstance(x, Taper):
        return f"{{base = {_g(x.base)}, tip = {_g(x.tip)}}}"
    return shown(x)


def _read_constant(r: Reader, table: Mapping, key: str, where: str, n: int, default, req):
    """A constant of the rod: a number or an axis name; for a key of :data:`PER_SEGMENT` also a
    list of ``n`` of them (a tuple) or a ``{ base, tip }`` table (a :class:`Taper`)."""
    v = table.get(key)
    if key in PER_SEGMENT and isinstance(v, np.ndarray) and v.ndim == 1:
        v = v.tolist()
    if key in PER_SEGMENT and isinstance(v, (list, tuple)):
        if len(v) != n:
            r.fail(
                f"{where} {key}",
                f"must be a number, an axis name or a list of n = {n} values (one per segment, "
                f"base to tip), got a list of {len(v)}.",
            )
        return tuple(
            r.number({f"{key}[{i}]": x}, f"{key}[{i}]", where, requirement=req)
            for i, x in enumerate(v)
        )
    if key in PER_SEGMENT and isinstance(v, Mapping):
        r.keys(v, ("base", "tip"), f"{where} {key}", required=("base", "tip"))
        return Taper(
            r.number(v, "base", f"{where} {key}", requirement=req),
            r.number(v, "tip", f"{where} {key}", requirement=req),
        )
    return r.number(table, key, where, default=default, requirement=req)


def _read_load(r: Reader, table, where: str, n: int) -> RodLoadSpec:
    kind = r.kind(table, ROD_LOADS, where)
    key, default, point_load, _ = ROD_LOADS[kind]
    allowed = ("type", key, "scale") + (("follower", "body") if point_load else ())
    r.keys(table, allowed, where, required=(key,) if default is None else ())
    body = -1
    if point_load and "body" in table:
        body = table["body"]
        if isinstance(body, bool) or not isinstance(body, int) or not -n - 1 <= body <= n:
            r.fail(
                f"{where} body", f"must be an integer in -{n + 1}..{n} (-1: the tip), got {body!r}."
            )
    return RodLoadSpec(
        kind,
        r.vector(table, key, where, default=default),
        r.number(table, "scale", where, default=1.0),
        r.boolean(table, "follower", where, default=False) if point_load else False,
        body,
    )


@dataclasses.dataclass(frozen=True)
class RodSpec:
    """A rod as data (module docstring): ``n``, ``base``, ``params`` (``{key: value}`` of
    :data:`ROD_KEYS`, plus ``shear_damping`` when given; a value is a number or :class:`Ref`, or
    for a key of :data:`PER_SEGMENT` a tuple of ``n`` of them or a :class:`Taper`), ``loads``
    (:class:`RodLoadSpec`)."""

    n: int
    base: str
    params: tuple[tuple[str, Any], ...]
    loads: tuple[RodLoadSpec, ...] = ()

    @classmethod
    def from_mapping(
        cls, table: Mapping, *, reader: Reader | None = None, where: str = "[rod]"
    ) -> RodSpec:
        """Read the table form (module docstring); raises :class:`~rbo_jax.app.spec.SpecError`
        naming the key at fault."""
        r = reader or Reader()
        if not isinstance(table, Mapping):
            r.fail(where, f"must be a table, got {table!r}.")
        allowed = ("n", "base", *ROD_KEYS, "shear_damping", "loads")
        r.keys(table, allowed, where, required=("n",))
        n = r.integer(table, "n", where, default=None, minimum=2)
        base = r.string(table, "base", where, default="clamped", choices=BASES)
        params = [
            (k, _read_constant(r, table, k, where, n, d, req)) for k, (d, req) in ROD_KEYS.items()
        ]
        if "shear_damping" in table:
            sd = _read_constant(r, table, "shear_damping", where, n, None, NONNEGATIVE)
            params.append(("shear_damping", sd))
        loads = table.get("loads", [])
        if isinstance(loads, Mapping):
            loads = [loads]
        if not isinstance(loads, list):
            r.fail(f"{where} loads", f"must be a list of tables, got {loads!r}.")
        specs = tuple(
            _read_load(r, t, f"[{where.strip('[]')}.loads][{i}]", n) for i, t in enumerate(loads)
        )
        return cls(n, base, tuple(params), specs)

    def value(self, name: str):
        """The value of ``name`` (a number or :class:`Ref`; a tuple or :class:`Taper` of a
        tapered constant); ``shear_damping`` None when not given."""
        return dict(self.params).get(name)

    def to_mapping(self) -> dict:
        """The table form (axis names as strings, a per-segment constant as a list, a taper
        as ``{"base": a, "tip": b}``)."""
        out: dict[str, Any] = {"n": self.n, "base": self.base}
        out |= {k: _plain(v) for k, v in self.params}
        loads = []
        for ld in self.loads:
            key = ROD_LOADS[ld.type][0]
            t = {"type": ld.type, key: [_plain(x) for x in ld.vector], "scale": _plain(ld.scale)}
            if ROD_LOADS[ld.type][2]:
                t |= {"follower": ld.follower, "body": ld.body}
            loads.append(t)
        return out | {"loads": loads}

    def build_loads(self, point: Mapping[str, Any] | None = None, factor=None) -> tuple:
        """The :mod:`rbo_jax.lattice` loads at ``point``, each times ``factor`` if given."""
        from .. import lattice

        point = point or {}
        out = []
        for ld in self.loads:
            vec = jnp.stack([_value(x, point) for x in ld.vector]) * _value(ld.scale, point)
            if factor is not None:
                vec = vec * factor
            _, _, point_load, name = ROD_LOADS[ld.type]
            where = {"follower": ld.follower, "body": ld.body} if point_load else {}
            out.append(getattr(lattice, name)(vec, **where))
        return tuple(out)

    def build(self, point: Mapping[str, Any] | None = None, factor=None):
        """The :class:`rbo_jax.lattice.Rod` at ``point`` (``{axis: value}``, traced or not),
        every load times the load factor ``factor`` if given; a per-segment constant (list or
        taper) as an ``(n,)`` array."""
        from .. import lattice

        point = point or {}
        p = {k: _constant(v, point, self.n) for k, v in self.params}
        return lattice.rod(
            self.n,
            p.pop("length"),
            loads=self.build_loads(point, factor),
            base=self.base,
            **p,
        )

    def parameters(self) -> tuple[str, ...]:
        """The names of the sweep axes the rod refers to."""
        xs = [(v.base, v.tip) if isinstance(v, Taper) else v for _, v in self.params]
        return references((*xs, *(x for ld in self.loads for x in (*ld.vector, ld.scale))))

    def describe(self) -> str:
        """One line for people: the bodies, the constants, the loads."""
        consts = ", ".join(f"{k} = {_g(v)}" for k, v in self.params)
        loads = []
        for ld in self.loads:
            text = f"{ld.type} {_g(ld.scale)} x ({', '.join(_g(x) for x in ld.vector)})"
            if ld.follower:
                text += " follower"
            if ld.body != -1:
                text += f" on body {ld.body}"
            loads.append(text)
        return f"rod of {self.n} bodies past the {self.base} base; {consts}; loads: " + (
            "; ".join(loads) if loads else "none"
        )
