"""The program store (rbo_jax._programs): traced programs kept on disk with ``jax.export``, so a
second process skips tracing; keys that separate every static difference; unsafe keys (memory
addresses) and unexportable programs fall back to tracing."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbo_jax import _programs

TRACES = []


class Params(eqx.Module):
    x: jax.Array
    label: str = eqx.field(static=True)
    fn: object = eqx.field(static=True, default=None)


@_programs.stored
@eqx.filter_jit
def program(params, scale, y):
    TRACES.append(params.label)
    out = params.x * scale + jnp.sin(y).astype(params.x.dtype)
    if params.fn is not None:
        out = params.fn(out)
    return {"a": out, "b": (jnp.sum(out), y)}


@pytest.fixture
def store(tmp_path):
    _programs.enable_program_store(tmp_path / "programs")
    jax.clear_caches()
    TRACES.clear()
    yield tmp_path / "programs"
    _programs.enable_program_store(None)


def _new_process():
    """What a second process starts with: no program in memory, none traced."""
    _programs.enable_program_store(_programs.program_store())
    jax.clear_caches()


def test_second_process_loads_the_program_without_tracing(store):
    p = Params(jnp.array([1.0, 2.0]), "k")
    y = jnp.array([0.5, -0.25])
    first = program(p, 3.0, y)
    assert TRACES == ["k"] and len(list(store.iterdir())) == 1
    _new_process()
    again = program(p, 3.0, y)
    assert TRACES == ["k"], "the stored program was traced again"
    _programs.enable_program_store(None)
    expected = program(p, 3.0, y)  # the plain jitted function
    assert TRACES == ["k", "k"]
    for a, b, c in zip(*(jax.tree.leaves(t) for t in (expected, first, again))):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a))
        np.testing.assert_array_equal(np.asarray(c), np.asarray(a))
    _programs.enable_program_store(store)
    assert jax.tree.structure(again) == jax.tree.structure(expected)
    # new array values, same structure: the same program
    other = program(Params(jnp.array([-1.0, 4.0]), "k"), 3.0, y)
    np.testing.assert_allclose(np.asarray(other["a"]), [-3.0, 12.0] + np.sin(np.asarray(y)))
    assert TRACES == ["k", "k"]


@pytest.mark.parametrize("change", ["static field", "python scalar", "shape", "dtype"])
def test_every_static_difference_is_a_new_program(store, change):
    p, scale, y = Params(jnp.array([1.0, 2.0]), "k"), 3.0, jnp.array([0.5, -0.25])
    program(p, scale, y)
    if change == "static field":
        p = Params(p.x, "other")
    elif change == "python scalar":
        scale = 3.0000000000000004  # the next float: repr tells them apart
    elif change == "shape":
        p, y = Params(jnp.ones(3), "k"), jnp.ones(3)
    else:
        y = y.astype(jnp.float32)
    _new_process()
    out = program(p, scale, y)
    assert len(TRACES) == 2 and len(list(store.iterdir())) == 2
    np.testing.assert_allclose(np.asarray(out["a"]),
                               np.asarray(p.x) * scale + np.sin(np.asarray(y, dtype=np.float64)),
                               rtol=1e-6)


def test_a_static_callable_is_traced_not_stored(store):
    """``<function … at 0x…>`` may name another function in another process: never stored."""
    p = Params(jnp.array([1.0, 2.0]), "f", fn=lambda z: 2.0 * z)
    out = program(p, 1.0, jnp.zeros(2))
    np.testing.assert_allclose(np.asarray(out["a"]), [2.0, 4.0])
    assert not store.exists() or not list(store.iterdir())


def test_store_off_and_a_damaged_entry(store):
    p, y = Params(jnp.array([1.0]), "k"), jnp.array([0.0])
    program(p, 2.0, y)
    (entry,) = store.iterdir()
    entry.write_bytes(b"not a program")
    _new_process()
    with pytest.warns(RuntimeWarning, match="cannot read"):
        out = program(p, 2.0, y)
    np.testing.assert_allclose(np.asarray(out["a"]), [2.0])
    assert len(TRACES) == 2 and entry.read_bytes() != b"not a program"  # exported again
    _programs.enable_program_store(None)
    jax.clear_caches()
    program(p, 2.0, y)
    assert len(TRACES) == 3  # off: the plain jitted function


def test_a_program_that_cannot_be_exported_is_tried_once(store, monkeypatch):
    """A host callback (here ``jax.debug.callback``; in the package, diffrax's checks) cannot be
    exported: the function runs as the plain jitted one, and the export is not tried again on
    every call (each try traces), nor in the next process (a marker in the store)."""
    seen, tries = [], []
    export = _programs._export
    monkeypatch.setattr(_programs, "_export", lambda *a: tries.append(1) or export(*a))

    @_programs.stored
    @eqx.filter_jit
    def with_callback(x):
        jax.debug.callback(lambda v: seen.append(float(v)), x[0])
        return 2.0 * x

    for v in (1.0, 3.0, 5.0):
        np.testing.assert_allclose(np.asarray(with_callback(jnp.array([v]))), [2.0 * v])
    assert seen == [1.0, 3.0, 5.0] and tries == [1]
    assert [p.suffix for p in store.iterdir()] == [".unexportable"]
    _new_process()
    np.testing.assert_allclose(np.asarray(with_callback(jnp.array([7.0]))), [14.0])
    assert seen[-1] == 7.0 and tries == [1]
