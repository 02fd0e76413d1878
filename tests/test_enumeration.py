"""rbo_jax._enumeration, the only reader of equinox's enumeration internals: if a new equinox
changes them, these tests fail first and say where to look."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import rbo_jax as rbo
from rbo_jax import _enumeration as enum

HINT = "equinox changed its Enumeration internals: update rbo_jax/_enumeration.py"


class Colour(eqx.Enumeration):
    red = "the first"
    green = ""
    blue = "the last"


def test_the_internals_rbo_jax_reads_still_exist():
    item = Colour.green
    assert hasattr(item, "_value") and hasattr(item, "_enumeration"), HINT
    assert isinstance(Colour._name_to_item, dict), HINT
    assert np.asarray(item._value).dtype.kind == "i", HINT


def test_names_codes_and_round_trip():
    assert enum.names(Colour) == ("red", "green", "blue")
    for i, name in enumerate(enum.names(Colour)):
        item = getattr(Colour, name)
        assert enum.is_item(item) and not enum.is_item(jnp.int32(i))
        assert int(enum.code(item)) == i and enum.name(item) == name
        assert enum.enumeration_of(item) is Colour
        back = enum.from_code(Colour, i)
        assert bool(back == item) and Colour[back] == Colour[item]


def test_batched_and_traced_items():
    codes = jnp.array([2, 0, 1])
    items = jax.vmap(lambda c: enum.from_code(Colour, c))(codes)
    np.testing.assert_array_equal(np.asarray(enum.code(items)), np.asarray(codes))
    selected = jax.jit(lambda c: Colour.where(c > 0, Colour.blue, Colour.red))(jnp.int32(1))
    assert enum.name(selected) == "blue"


def test_labels_name_the_public_class():
    assert enum.label(rbo.SolveStatus) == "rbo_jax.SolveStatus"
    assert enum.label(rbo.StabilityKind) == "rbo_jax.StabilityKind"
    assert enum.label(Colour) == f"{__name__}.Colour"
