"""The one place that reads equinox's enumeration internals.

Statuses and classifications are :class:`equinox.Enumeration` items (``SolveStatus``,
``EquilibriumStatus``, ``StabilityKind``, ...). Storing them in datasets needs what equinox does
not expose publicly: the integer code of an item (``item._value``), the enumeration of an item
(``item._enumeration``) and the ordered names of an enumeration (``cls._name_to_item``). Every
module of rbo_jax goes through the functions below, and ``tests/test_enumeration.py`` fails
loudly if a new equinox changes these internals.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["is_item", "code", "enumeration_of", "names", "name", "label", "from_code"]


def is_item(x) -> bool:
    """Whether ``x`` is an item of an :class:`equinox.Enumeration` (possibly batched/traced)."""
    return hasattr(x, "_enumeration") and hasattr(x, "_value")


def code(item):
    """The integer code of an item (an int32 array, batched like the item)."""
    return item._value


def enumeration_of(item):
    """The :class:`equinox.Enumeration` class an item belongs to."""
    return item._enumeration


def names(cls) -> tuple[str, ...]:
    """The names of an enumeration's items, ordered by their codes (index = code)."""
    items = sorted(cls._name_to_item.items(), key=lambda kv: int(np.asarray(kv[1]._value)))
    return tuple(n for n, _ in items)


def name(item) -> str:
    """The name of a concrete, unbatched item, e.g. ``"singular_point"``."""
    return names(enumeration_of(item))[int(np.asarray(code(item)))]


def label(cls) -> str:
    """The name of an enumeration stored with datasets: ``rbo_jax.Name`` for the package's
    public enumerations (independent of the module that defines them), else
    ``module.QualifiedName``."""
    import rbo_jax

    if getattr(rbo_jax, cls.__qualname__, None) is cls:
        return f"rbo_jax.{cls.__qualname__}"
    return f"{cls.__module__}.{cls.__qualname__}"


def from_code(cls, value):
    """The item of ``cls`` with integer code ``value`` (an int scalar or array, traced or not):
    the inverse of :func:`code`. Codes outside the enumeration are not checked here."""
    value = jnp.asarray(value, dtype=jnp.int32)
    first = cls._name_to_item[names(cls)[0]]
    return type(first)(value, cls)
