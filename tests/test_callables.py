"""A callable's identity by what it computes (rbo_jax._callables): a notebook cell run twice
makes new but identical lambdas, which must reuse the compiled program of stability_map, sweep
and critical_load; lambdas that differ in a closure value, a constant or a global must not."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
import pytest

import rbo_jax
from rbo_jax._callables import callable_key, stable_text
from rbo_jax.batch import _program

K = np.array([0.0, 0.0, 1.0])
D = 2.0

CELL = """
model_fn = lambda M, c: rbo_jax.nikolai_model(M, c, D, A3=0.5, k=K)
theta_eq_fn = lambda M, c: rbo_jax.nikolai_equilibrium(M, D, K)
"""


def run_cell(source=CELL, **names):
    """The functions a notebook cell defines, new objects on every run (module globals)."""
    namespace = {**globals(), **names}
    exec(compile(source, "cell.py", "exec"), namespace)
    return namespace


def make_scaled(scale, offset=1.0):
    return lambda x: scale * x + offset


def test_identical_lambdas_have_one_key_and_differences_do_not():
    a, b = run_cell(), run_cell()
    assert a["model_fn"] is not b["model_fn"]
    for name in ("model_fn", "theta_eq_fn"):
        assert callable_key(a[name]) == callable_key(b[name])
        assert hash(callable_key(a[name])) == hash(callable_key(b[name]))
        assert stable_text(a[name]) == stable_text(b[name]) is not None
    assert callable_key(make_scaled(2.0)) == callable_key(make_scaled(2.0))
    differ = [
        make_scaled(3.0),  # a closure value
        make_scaled(2),  # its type (int, not float: another trace)
        make_scaled(2.0, offset=0.0),
        make_scaled(2.0, offset=-0.0),  # -0.0 is not 0.0
        make_scaled(np.float32(2.0)),
        run_cell(CELL.replace("A3=0.5", "A3=0.6"))["model_fn"],  # a constant
        run_cell(K=np.array([0.0, 1.0, 0.0]))["model_fn"],  # a global array's values
        run_cell(K=K.astype(np.float32))["model_fn"],  # its dtype
        run_cell(D=3.0)["model_fn"],  # a global number
        run_cell(CELL.replace("lambda M, c", "lambda M, c=1.0"))["model_fn"],  # a default
    ]
    keys = [callable_key(make_scaled(2.0)), callable_key(a["model_fn"])]
    keys += [callable_key(f) for f in differ]
    assert len(set(keys)) == len(keys)
    texts = [stable_text(make_scaled(2.0)), stable_text(a["model_fn"])]
    texts += [stable_text(f) for f in differ]
    assert None not in texts and len(set(texts)) == len(texts)


def test_nested_functions_partials_and_values_changed_in_place():
    def outer(scale):
        def f(x):
            return jnp.sum(jnp.array([g(x) for g in (lambda y: scale * y,)]))

        return f

    assert callable_key(outer(2.0)) == callable_key(outer(2.0)) != callable_key(outer(5.0))
    p = functools.partial(jnp.multiply, 2.0)
    assert callable_key(p) == callable_key(functools.partial(jnp.multiply, 2.0))
    assert callable_key(p) != callable_key(functools.partial(jnp.multiply, 3.0))
    values = np.array([1.0, 2.0])
    f = make_scaled(values)
    before = callable_key(f)
    values[0] = 7.0  # the same function, a changed array: a new key
    assert callable_key(f) != before


def test_unknown_objects_by_identity_and_never_across_processes():
    class Thing:  # hashable by identity, of no module the store's key covers
        pass

    t = Thing()
    assert callable_key(make_scaled(t)) == callable_key(make_scaled(t))
    assert callable_key(make_scaled(t)) != callable_key(make_scaled(Thing()))
    assert stable_text(make_scaled(t)) is None
    unhashable = [1.0, object()]
    assert callable_key(make_scaled(unhashable)) != callable_key(make_scaled([1.0, object()]))
    assert stable_text(make_scaled(unhashable)) is None
    # library functions and classes by name across processes; a model (pytree) by its leaves
    assert "nikolai_model" in stable_text(rbo_jax.nikolai_model)
    model = rbo_jax.nikolai_model(0.3, 1.0, 2.0)
    assert stable_text(make_scaled(model)) == stable_text(
        make_scaled(rbo_jax.nikolai_model(0.3, 1.0, 2.0))
    )
    assert stable_text(make_scaled(model)) != stable_text(
        make_scaled(rbo_jax.nikolai_model(0.3, 1.0, 2.5))
    )


@pytest.fixture
def compilations(monkeypatch):
    """Counts the chunk programs the batch engine traces (none cached before the test)."""
    calls = []
    compile_program = _program._compile_program
    monkeypatch.setattr(
        _program, "_compile_program", lambda *a: calls.append(a[0]) or compile_program(*a)
    )
    _program._cached_program.cache_clear()
    yield calls
    _program._cached_program.cache_clear()


AXES = {"M": np.linspace(-0.6, 0.6, 5), "c": np.linspace(0.5, 1.5, 3)}


def stability(cell, **kwargs):
    ds = rbo_jax.stability_map(
        cell["model_fn"], AXES, theta_eq_fn=cell["theta_eq_fn"], progress=False, **kwargs
    )
    return np.asarray(ds["spectral_abscissa"])


def test_stability_map_of_a_cell_run_twice_compiles_once(compilations):
    first = stability(run_cell())
    again = stability(run_cell())
    assert len(compilations) == 1
    np.testing.assert_array_equal(again, first)
    other = stability(run_cell(D=3.0))  # another global: another program, other values
    assert len(compilations) == 2
    assert not np.array_equal(other, first)
    stability(run_cell(), rtol=1e-8)  # another setting of the map
    assert len(compilations) == 3


def test_sweep_and_critical_load_of_a_cell_run_twice_compile_once(compilations):
    source = "quantity = lambda M, c: {'x': M * c + D}\n"
    results = [rbo_jax.sweep(run_cell(source)["quantity"], AXES, progress=False) for _ in range(2)]
    assert len(compilations) == 1
    np.testing.assert_array_equal(results[1]["x"], results[0]["x"])
    shifted = rbo_jax.sweep(run_cell(source, D=5.0)["quantity"], AXES, progress=False)
    assert len(compilations) == 2
    np.testing.assert_allclose(shifted["x"] - results[0]["x"], 3.0)

    def critical(cell):
        return np.asarray(
            rbo_jax.critical_load(
                cell["model_fn"],
                {"c": np.array([0.5, 1.0])},
                "M",
                1.0,
                n_scan=4,
                n_bisect=4,
                theta_eq_fn=cell["theta_eq_fn"],
            )
        )

    first = critical(run_cell())
    np.testing.assert_array_equal(critical(run_cell()), first)
    assert len(compilations) == 3


FOUNDATION_CELL = """
foundation = rbo_jax.IsotropicFoundation(lambda s: 0.5 * kappa * s * (1 + s))
"""


def test_a_model_built_again_from_a_new_lambda_has_the_same_structure():
    """A foundation made again from a new but identical lambda (a cell run twice) is the same
    tree structure, so jitted solvers reuse their programs (solve_equilibrium's cache hit); a
    different closure value is another structure, with its own energy, and so is a closure whose
    dict changed since the first was seen; a lambda that closes over a traced value is kept as
    it is (never matched, never kept alive)."""
    import jax

    first, again = (run_cell(FOUNDATION_CELL, kappa=0.7)["foundation"] for _ in range(2))
    assert jax.tree_util.tree_structure(again) == jax.tree_util.tree_structure(first)
    other = run_cell(FOUNDATION_CELL, kappa=0.9)["foundation"]
    assert jax.tree_util.tree_structure(other) != jax.tree_util.tree_structure(first)
    theta = jnp.array([0.1, 0.2, 0.3])
    s = float(theta @ theta)
    assert float(other.energy(theta)) == pytest.approx(0.45 * s * (1 + s), rel=1e-14)
    assert float(again.energy(theta)) == pytest.approx(0.35 * s * (1 + s), rel=1e-14)

    cell = "foundation = rbo_jax.IsotropicFoundation(lambda s: params['k'] * s)\n"
    params = {"k": 1.0}
    changed = run_cell(cell, params=params)["foundation"]
    params["k"] = 2.0  # the first function seen now computes 2 s
    fresh = run_cell(cell, params={"k": 1.0})["foundation"]
    assert float(changed.energy(theta)) == pytest.approx(2.0 * s, rel=1e-14)
    assert float(fresh.energy(theta)) == pytest.approx(s, rel=1e-14)

    def traced(kappa):
        fn = lambda s: kappa * s  # noqa: E731
        foundation = rbo_jax.IsotropicFoundation(fn)
        assert foundation.F.func is fn
        return foundation.energy(theta)

    assert float(jax.jit(traced)(2.0)) == pytest.approx(2.0 * s, rel=1e-14)
