r"""``RodSpec``: a plain, validated description of a rod (:func:`rbo_jax.lattice.rod`), the
``[rod]`` table of ``rbo-jax sweep`` and of ``rbo-jax simulate --rod``.

A rod of ``n`` bodies past the base along $e_3$, its constants per unit length (scalars) and its
loads (:doc:`rods </topics/rods>`); every number may be the name of a sweep axis::

    n = 8                   # bodies past the base (>= 2)
    length = 1.0            # L
    bending = 1.0           # EI      (torsion GJ, shear kappa GA, stretch EA as well)
    mass = 1.0              # rho A   (rotary: rho I per length about a transverse axis)
    damping = "eta"         # Kelvin-Voigt time of every stress resultant (s)
    shear_damping = 0.0     # another one for shear and stretch (default: damping)
    tip_mass = "Mt"         # a point mass on the tip (Pflueger's column)
    base = "clamped"        # or "pinned", "free"
    loads = [{ type = "tip_force", f = [0.0, 0.0, -1.0], scale = "P", follower = true }]

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
values inside ``jax.vmap``), with every load times a load factor $\lambda$ if one is given (the
``rod_critical_load`` quantity searches $\lambda$). Errors name the key
(``[rod] bending: must be > 0, got -1.``); a parameter taken from an axis is checked on every
value of that axis before anything runs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax.numpy as jnp

from .._validation import NONNEGATIVE, POSITIVE, Requirement
from ._reader import Reader, Ref

__all__ = ["ROD_KEYS", "ROD_LOADS", "RodLoadSpec", "RodSpec"]

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
# type: (the vector's key, its default, may it follow the body, may it pick a body)
ROD_LOADS = {
    "tip_force": ("f", None, True),
    "tip_moment": ("m", None, True),
    "gravity": ("g", (0.0, 0.0, -9.81), False),
    "distributed": ("q", None, False),
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


def _value(x, point: Mapping[str, Any]):
    return jnp.asarray(point[x.name] if isinstance(x, Ref) else x, dtype=jnp.result_type(float))


def _plain(x):
    return x.name if isinstance(x, Ref) else x


def _g(x) -> str:
    return f"<{x.name}>" if isinstance(x, Ref) else f"{x:g}"


def _read_load(r: Reader, table, where: str, n: int) -> RodLoadSpec:
    if not isinstance(table, Mapping):
        r.fail(where, f"must be a table, got {table!r}.")
    kind = table.get("type")
    if not isinstance(kind, str) or kind not in ROD_LOADS:
        r.fail(f"{where} type", f"must be one of {', '.join(map(repr, ROD_LOADS))}; got {kind!r}.")
    key, default, point_load = ROD_LOADS[kind]
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
    """A rod as data (module docstring): ``n``, ``base``, ``params`` (``{key: number or Ref}``
    of :data:`ROD_KEYS`, plus ``shear_damping`` when given), ``loads`` (:class:`RodLoadSpec`)."""

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
            (k, r.number(table, k, where, default=d, requirement=req))
            for k, (d, req) in ROD_KEYS.items()
        ]
        if "shear_damping" in table:
            sd = r.number(table, "shear_damping", where, requirement=NONNEGATIVE)
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
        """The number (or :class:`Ref`) of ``name``; ``shear_damping`` None when not given."""
        return dict(self.params).get(name)

    def to_mapping(self) -> dict:
        """The table form (axis names as strings)."""
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
            if ld.type == "tip_force":
                out.append(lattice.TipForce(vec, follower=ld.follower, body=ld.body))
            elif ld.type == "tip_moment":
                out.append(lattice.TipMoment(vec, follower=ld.follower, body=ld.body))
            elif ld.type == "gravity":
                out.append(lattice.Gravity(vec))
            else:
                out.append(lattice.DistributedForce(vec))
        return tuple(out)

    def build(self, point: Mapping[str, Any] | None = None, factor=None):
        """The :class:`rbo_jax.lattice.Rod` at ``point`` (``{axis: value}``, traced or not),
        every load times the load factor ``factor`` if given."""
        from .. import lattice

        point = point or {}
        p = {k: _value(v, point) for k, v in self.params}
        return lattice.rod(
            self.n,
            p.pop("length"),
            loads=self.build_loads(point, factor),
            base=self.base,
            **p,
        )

    def parameters(self) -> tuple[str, ...]:
        """The names of the sweep axes the rod refers to."""
        xs = [v for _, v in self.params]
        for ld in self.loads:
            xs += [*ld.vector, ld.scale]
        return tuple(dict.fromkeys(x.name for x in xs if isinstance(x, Ref)))

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
