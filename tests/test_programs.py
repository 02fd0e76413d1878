"""The program store (rbo_jax._programs): traced programs kept on disk with ``jax.export``, so a
second process skips tracing; keys that separate every static difference; unsafe keys (memory
addresses) and unexportable programs fall back to tracing."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbo_jax
from rbo_jax import _cache, _programs

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
    before = _programs.program_store()  # on for the whole run with $RBO_JAX_COMPILATION_CACHE
    _programs.enable_program_store(tmp_path / "programs")
    jax.clear_caches()
    TRACES.clear()
    yield tmp_path / "programs"
    _programs.enable_program_store(before)


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
    np.testing.assert_allclose(
        np.asarray(out["a"]),
        np.asarray(p.x) * scale + np.sin(np.asarray(y, dtype=np.float64)),
        rtol=1e-6,
    )


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


class _Unregistered(eqx.Module):
    y: jax.Array


def test_an_output_that_cannot_be_serialised_is_traced_as_usual(store):
    """An output of a pytree type ``jax.export`` cannot serialise (an equinox module) exports,
    then fails to serialise: the call returns the plain jitted function's result and the store
    marks the program, instead of raising."""

    @_programs.stored
    @eqx.filter_jit
    def module_out(x):
        return _Unregistered(2.0 * x)

    out = module_out(jnp.array([1.5]))
    assert isinstance(out, _Unregistered)
    np.testing.assert_allclose(np.asarray(out.y), [3.0])
    assert [p.suffix for p in store.iterdir()] == [".unexportable"]


def test_the_rods_midpoint_program_is_stored_and_loaded_without_tracing(store, monkeypatch):
    """``lattice.simulate(rod, ..., method="midpoint")`` with concrete inputs: its program is
    kept by the store, and a second process runs it without tracing the rod's equations, to
    the same bits."""
    from rbo_jax import lattice
    from rbo_jax.lattice import _rod_midpoint

    rod = lattice.rod(4, 1.0, bending=1.0, torsion=1.0, shear=1e3, stretch=1e3, mass=1.0,
                      rotary=1e-3)  # fmt: skip
    s = rod.straight()
    state0 = lattice.RodState(s.theta, s.r, s.Omega, s.v.at[1:, 0].set(0.01))
    ts = np.linspace(0.0, 0.2, 5)
    first = lattice.simulate(rod, state0, ts, method="midpoint", dt=0.05)  # steps at the samples
    assert any(p.suffix == ".jaxexport" for p in store.iterdir())
    traced = []
    field = _rod_midpoint._field_undamped
    monkeypatch.setattr(_rod_midpoint, "_field_undamped", lambda *a: traced.append(1) or field(*a))
    _new_process()
    again = lattice.simulate(rod, state0, ts, method="midpoint", dt=0.05)
    assert traced == [], "the stored program was traced again"
    for a, b in zip(jax.tree.leaves(first.states), jax.tree.leaves(again.states)):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a))
    # its states are packed into one array and unpacked: the first sample is state0, field
    # by field (the store's results are the plain program's bits: the tests above)
    for name in ("theta", "r", "Omega", "v"):
        got = np.asarray(getattr(again.states, name)[0])
        np.testing.assert_array_equal(got, np.asarray(getattr(state0, name)))


def test_a_new_environment_is_a_new_program(store, monkeypatch):
    """Entries of other sources or versions (the environment in the key) are never used."""
    p, y = Params(jnp.array([1.0]), "k"), jnp.array([0.0])
    program(p, 2.0, y)
    monkeypatch.setattr(_programs, "_environment", lambda: "other sources")
    _new_process()
    program(p, 2.0, y)
    assert len(TRACES) == 2 and len(list(store.iterdir())) == 2


@pytest.fixture
def jax_cache_settings():
    """Restores JAX's cache settings and the store after a test that changes them."""
    names = (
        "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs",
        "jax_persistent_cache_min_entry_size_bytes",
    )
    saved = {n: getattr(jax.config, n) for n in names}
    saved_dir, saved_store = _cache._JAX_DIR, _cache.program_store()
    yield
    _cache._set_jax_dir(saved["jax_compilation_cache_dir"])
    for n in names[1:]:
        jax.config.update(n, saved[n])
    _cache._JAX_DIR = saved_dir
    _programs.enable_program_store(saved_store)


def test_enable_compilation_cache(tmp_path, monkeypatch, jax_cache_settings):
    path = _cache.enable_compilation_cache(tmp_path / "c")
    assert path == tmp_path / "c" and (path / "programs").is_dir()
    assert _programs.program_store() == path / "programs"
    assert jax.config.jax_compilation_cache_dir == str(path)
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0
    assert jax.config.jax_persistent_cache_min_entry_size_bytes == 0
    assert _cache.enable_compilation_cache("off") is None
    assert _programs.program_store() is None and jax.config.jax_compilation_cache_dir is None
    # the environment variable, then the user's cache directory
    monkeypatch.setenv("RBO_JAX_COMPILATION_CACHE", str(tmp_path / "env"))
    assert _cache.enable_from_environment() == tmp_path / "env"
    monkeypatch.setenv("RBO_JAX_COMPILATION_CACHE", " False ")
    assert _cache.enable_compilation_cache() is None and _programs.program_store() is None
    monkeypatch.delenv("RBO_JAX_COMPILATION_CACHE")
    assert _cache.enable_from_environment() is None and _programs.program_store() is None
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert _cache.enable_compilation_cache() == tmp_path / "xdg" / "rbo_jax" / "jax-cache"
    # a directory that cannot be made: a warning, both off, nothing fails
    (tmp_path / "file").write_text("")
    with pytest.warns(RuntimeWarning, match="compilation cache off"):
        assert _cache.enable_compilation_cache(tmp_path / "file" / "sub") is None
    assert _programs.program_store() is None and jax.config.jax_compilation_cache_dir is None
    with pytest.raises(TypeError, match="path must be"):
        _cache.enable_compilation_cache(3.0)


SECOND_PROCESS = """
import logging, sys
import numpy as np
import jax
import rbo_jax
from rbo_jax import _cache

_cache.enable_compilation_cache(sys.argv[1])
K = np.array([0.0, 0.0, 1.0])
model = rbo_jax.RigidBodyOscillator(rbo_jax.transversely_isotropic_inertia(1.0, 0.5, K),
                                    rbo_jax.QuadraticFoundation(1.0, 1.5, K),
                                    rbo_jax.FollowerMoment(0.3, K))
traj = rbo_jax.fast_simulate(model, np.array([1e-3, -5e-4, 0.2]), np.zeros(3),
                             np.linspace(0.0, 5.0, 11), rtol=1e-8, atol=1e-10)
diffrax_traj = rbo_jax.simulate(model, np.array([1e-3, -5e-4, 0.2]), np.zeros(3),
                                np.linspace(0.0, 5.0, 11), rtol=1e-8, atol=1e-10)
ds = rbo_jax.stability_map(lambda M, c: rbo_jax.nikolai_model(M, c, 2.0, A3=0.5, k=K),
                           {"M": np.linspace(-0.8, 0.8, 5), "c": np.linspace(0.2, 2.0, 4)},
                           theta_eq_fn=lambda M, c: rbo_jax.nikolai_equilibrium(M, 2.0, K),
                           progress=False)
for a in (traj.theta, traj.Omega, diffrax_traj.theta, diffrax_traj.Omega, ds["eigenvalues"],
          ds["spectral_abscissa"]):
    print(np.asarray(a).tobytes().hex())
"""


@pytest.mark.slow  # integration: fresh processes, ~15 s
def test_a_second_process_loads_the_solves_and_the_map_without_tracing(tmp_path):
    """Two real processes sharing a cache directory: the first exports the solves of
    fast_simulate and simulate (diffrax, default throw=True) and the map's chunk program, the
    second loads all three (JAX's log shows no trace of them, and a cache hit for simulate's
    compiled program) and gives the same bits."""
    import os
    import subprocess
    import sys

    def run():
        env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
        env.update(JAX_PLATFORMS="cpu", JAX_LOG_COMPILES="1", RBO_JAX_COMPILATION_CACHE="off")
        proc = subprocess.run(
            [sys.executable, "-c", SECOND_PROCESS, str(tmp_path / "cache")],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc.stdout, proc.stderr

    first, log = run()
    assert log.count("Finished tracing _solve_export") == 2 and "Finished tracing point" in log
    assert len(list((tmp_path / "cache" / "programs").glob("*.jaxexport"))) == 3
    again, log = run()
    assert "Finished tracing _solve_export" not in log, "a solve was traced again"
    assert "Finished tracing point" not in log, "the map's quantity was traced again"
    assert "Persistent compilation cache hit for 'jit_chunk_program'" in log
    assert log.count("Persistent compilation cache hit for 'jit__solve'") == 2
    assert again == first


def _simulate_program_text(model, throw=False, **options):
    """The StableHLO of simulate's compiled solve, traced as simulate traces it (or, with
    ``trusted=False``, without leaving out diffrax's checks)."""
    import importlib

    simulate = importlib.import_module("rbo_jax.simulate")
    from rbo_jax._validation import checked_inputs_trusted
    from rbo_jax.integrate import diffeq
    from rbo_jax.trajectory import prepare_inputs

    trusted = options.pop("trusted", True)
    ts = np.linspace(0.0, 1.0, 3)
    inputs = prepare_inputs(model, np.array([0.0, 0.0, 0.2]), np.zeros(3), ts, 1e-8, 1e-8, throw)
    args = dict(
        t0=None,
        solver=None,
        rtol=1e-8,
        atol=1e-8,
        dt0=None,
        dtmin=None,
        max_steps=100,
        adjoint=None,
        stepsize_controller=None,
        singular_tol=1e-3,
        form="right",
        throw=throw,
        progress=False,
    )
    args.update(options)
    jax.clear_caches()  # trace again (the context is read at trace time)
    with checked_inputs_trusted(
        trusted
        and diffeq.trusted(model, args["solver"], args["adjoint"], args["stepsize_controller"])
    ):
        return simulate._solve_compiled.lower(
            model,
            inputs.theta0,
            inputs.Omega0,
            inputs.ts,
            inputs.bad_times,
            inputs.dtype,
            simulate._Options(**args),
        ).as_text()


@pytest.mark.slow  # cost: ~12 s of compilation
def test_simulate_programs_hold_no_host_callback_where_the_inputs_are_checked():
    """diffrax checks the sample times (and dt0) again with host callbacks (eqx.error_if), which
    keep a program out of JAX's persistent cache and the program store: simulate, having
    checked them on the host, traces its solve without them. A check inside the equations of
    motion (throw=True, SemiTangentialMoment), a user function in the model and StepTo keep
    their callbacks."""
    import diffrax

    model = rbo_jax.nikolai_model(0.3, 1.0, 1.5)
    assert "callback" in _simulate_program_text(model, trusted=False)  # diffrax's checks
    for throw in (False, True):
        assert "callback" not in _simulate_program_text(model, throw=throw)
    assert "callback" not in _simulate_program_text(
        model, dt0=0.01, solver=diffrax.Tsit5(), stepsize_controller=diffrax.ConstantStepSize()
    )
    K = np.array([0.0, 0.0, 1.0])
    semi = rbo_jax.RigidBodyOscillator(
        np.eye(3), rbo_jax.QuadraticFoundation(1.0, 1.0, K), [rbo_jax.SemiTangentialMoment(0.1, K)]
    )
    assert "callback" not in _simulate_program_text(semi, throw=False)  # NaN, not a raise
    assert "callback" in _simulate_program_text(semi, throw=True)  # (4.75)'s check is kept

    def F(s):
        return 0.5 * eqx.error_if(s, s > 100.0, "user check")

    user = rbo_jax.RigidBodyOscillator(np.eye(3), rbo_jax.IsotropicFoundation(F))
    assert "callback" in _simulate_program_text(user)  # the user's check is kept
    step_to = diffrax.StepTo(ts=np.linspace(0.0, 1.0, 11))
    assert "callback" in _simulate_program_text(model, stepsize_controller=step_to)


def test_the_environment_variable_turns_the_cache_on_at_import(tmp_path):
    import os
    import subprocess
    import sys

    code = (
        "import sys, jax, rbo_jax; from rbo_jax import _cache; "
        "assert rbo_jax.enable_compilation_cache is _cache.enable_compilation_cache; "
        "assert 'equinox' not in sys.modules; "
        "print(_cache.program_store(), jax.config.jax_compilation_cache_dir)"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update(JAX_PLATFORMS="cpu", RBO_JAX_COMPILATION_CACHE=str(tmp_path))
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == [str(tmp_path / "programs"), str(tmp_path)]


def test_a_sweep_with_a_host_callback_is_traced_as_usual(store):
    """A quantity with a host callback cannot be exported: the sweep traces it as usual (its
    output structure too: jit must not answer from the failed export's trace), in this process
    and, after the marker, in the next without trying to export it again."""
    from rbo_jax.batch import _program

    def quantity(x):
        y = jax.pure_callback(
            np.sin, jax.ShapeDtypeStruct((), jnp.float64), x, vmap_method="sequential"
        )
        return {"y": y, "z": 2.0 * x}

    axes = {"x": np.array([0.0, 0.5, 1.0])}
    for _ in range(2):  # the second time as a new process
        _program._cached_program.cache_clear()
        ds = rbo_jax.sweep(quantity, axes, progress=False)
        np.testing.assert_allclose(ds["y"], np.sin(axes["x"]))
        np.testing.assert_allclose(ds["z"], 2.0 * axes["x"])
        assert [p.suffix for p in store.iterdir()] == [".unexportable"]
        _new_process()
    _program._cached_program.cache_clear()


def test_jax_settings_that_change_a_trace_are_part_of_the_key():
    key = _programs.program_key("program")
    other = "strict" if jax.config.jax_numpy_dtype_promotion == "standard" else "standard"
    with jax.numpy_dtype_promotion(other):
        assert _programs.program_key("program") != key
    assert _programs.program_key("program") == key
    assert _programs.program_key("<function f at 0x7f00>") is None  # an address: never stored


def test_small_programs_take_xla_options_at_the_top_level_only(monkeypatch):
    """``_programs.jit(fn, small=True)`` compiles with XLA's options for small programs where it
    is compiled as a program of its own (called eagerly, or under jax.vmap alone); JAX refuses
    compiler options on a jit inside another trace, so there (traced arguments or concrete ones
    inside a jit or export) it is the plain jitted function. Same values everywhere. Where XLA
    does not know the option, no options."""
    assert _programs.small_program_options() == {"xla_cpu_use_fusion_emitters": False}

    def f(x, scale):
        return jnp.sin(x) * scale

    x = jnp.linspace(0.0, 1.0, 5)
    expected = np.sin(np.linspace(0.0, 1.0, 5)) * 2.0

    def check(small, program):
        np.testing.assert_allclose(jax.jit(small)(x, 2.0), expected, rtol=1e-15)
        np.testing.assert_allclose(jax.jit(lambda: small(x, 2.0))(), expected, rtol=1e-15)
        np.testing.assert_allclose(
            jax.jit(jax.vmap(small, (0, None)))(x[:, None], 2.0)[:, 0], expected, rtol=1e-15
        )
        exported = jax.export.export(jax.jit(lambda y: small(y, 2.0)))(
            jax.ShapeDtypeStruct(x.shape, x.dtype)
        )
        np.testing.assert_allclose(exported.call(x), expected, rtol=1e-15)
        np.testing.assert_allclose(jax.jit(lambda: program(x, 2.0))(), expected, rtol=1e-15)

    np.testing.assert_allclose(_programs.jit(f, small=True)(x, 2.0), expected, rtol=1e-15)
    vmapped = jax.vmap(_programs.jit(f, small=True), (0, None))(x[:, None], 2.0)[:, 0]
    np.testing.assert_allclose(vmapped, expected, rtol=1e-15)
    check(_programs.jit(f, small=True), _programs.program(f, small=True))
    # the options reach XLA at the top level and under vmap alone: one it does not know is
    # refused there
    monkeypatch.setattr(_programs, "small_program_options", lambda: {"xla_no_such_option": True})
    with pytest.raises(jax.errors.JaxRuntimeError, match="No such compile option"):
        _programs.jit(f, small=True)(x, 2.0)
    with pytest.raises(jax.errors.JaxRuntimeError, match="No such compile option"):
        jax.vmap(_programs.jit(f, small=True), (0, None))(x[:, None], 2.0)
    check(_programs.jit(f, small=True), _programs.program(f, small=True))
    monkeypatch.undo()
    # an XLA that does not know the option: the probe says so, and programs are plain
    monkeypatch.setattr(_programs, "_SMALL", {"xla_no_such_option": True})
    _programs.small_program_options.cache_clear()
    try:
        assert _programs.small_program_options() is None
        np.testing.assert_allclose(_programs.jit(f, small=True)(x, 2.0), expected, rtol=1e-15)
    finally:
        monkeypatch.undo()
        _programs.small_program_options.cache_clear()


def test_fast_compile_programs_take_the_small_options_and_more():
    """``fast_compile=True``: the small programs' options plus LLVM without optimisation,
    without XLA's while-loop passes and without parallel code generation (where XLA knows them),
    at the top level only; same values."""
    options = _programs.fast_compile_options()
    assert options == {
        **_programs.small_program_options(),
        "xla_backend_optimization_level": 0,
        "xla_disable_hlo_passes": "while-loop-invariant-code-motion,simplify-while-loops",
        "xla_cpu_parallel_codegen_split_count": 1,
    }

    def f(x):
        return jax.lax.fori_loop(0, 3, lambda i, y: jnp.sin(y) * 2.0, x)

    x = jnp.linspace(0.0, 1.0, 5)
    fast = _programs.jit(f, fast_compile=True)
    np.testing.assert_allclose(fast(x), f(x), rtol=1e-15)
    np.testing.assert_allclose(jax.jit(fast)(x), f(x), rtol=1e-15)
    assert _programs.program(f, fast_compile=True)(x).shape == x.shape
