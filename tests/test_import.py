"""A light ``import rbo_jax`` (rbo_jax._lazy): the package imports JAX and enables float64; the
layers and their dependencies (equinox, diffrax, optimistix, optax, xarray, zarr, matplotlib)
load when one of their names is first used, and every public name resolves as it did when the
package imported every layer. Each check runs in a fresh interpreter: this test process has
imported everything already."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

import rbo_jax

HEAVY = ("equinox", "diffrax", "optimistix", "optax", "lineax", "xarray", "zarr", "matplotlib")
SUBPACKAGES = ("rbo_jax.batch", "rbo_jax.bifurcation", "rbo_jax.fitting")


def _fresh(code: str) -> dict:
    """Run ``code`` in a new interpreter; it prints one JSON object as its last line."""
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def _loaded(prefix: str = "") -> str:
    return f"json.dumps({{'heavy': [m for m in {HEAVY!r} if m in sys.modules]{prefix}}})"


def test_import_loads_no_layer_and_no_heavy_dependency():
    got = _fresh(f"""
        import json, sys
        import rbo_jax
        layers = sorted(m for m in sys.modules if m.startswith("rbo_jax."))
        print({_loaded(", 'layers': layers, 'x64': rbo_jax.float64_enabled()")})
    """)
    assert got["heavy"] == []
    assert set(got["layers"]) <= {
        "rbo_jax._lazy",
        "rbo_jax._precision",
        "rbo_jax._devices",  # one CPU device per core, before JAX starts
        "rbo_jax._cache",
        "rbo_jax._version",
    }, got["layers"]
    assert got["x64"] is True


@pytest.mark.parametrize(
    "statement, absent",
    [
        ("from rbo_jax import turn_tensor", HEAVY),
        (
            "from rbo_jax import nikolai_model, Trajectory, fast_simulate",
            ("diffrax", "optimistix", "optax", "xarray", "zarr", "matplotlib"),
        ),
        ("from rbo_jax.fitting import TrajectoryData", ("diffrax", "optax", "xarray", "zarr")),
        # the least-squares fit integrates with fast_simulate: diffrax and optax on demand
        ("from rbo_jax import fit", ("diffrax", "optimistix", "optax", "xarray", "zarr")),
        (
            "from rbo_jax.batch import POINT_DIM, status_counts",
            ("diffrax", "optax", "xarray", "zarr"),
        ),
    ],
)
def test_a_name_loads_only_what_it_needs(statement, absent):
    got = _fresh(f"""
        import json, sys
        {statement}
        print({_loaded()})
    """)
    assert not set(got["heavy"]) & set(absent), got["heavy"]


def test_every_public_name_resolves_in_a_fresh_process():
    got = _fresh(f"""
        import importlib, json, sys
        import rbo_jax
        missing, wrong = [], []
        for pkg in ("rbo_jax", *{SUBPACKAGES!r}):
            mod = importlib.import_module(pkg)
            for name in mod.__all__:
                if name not in dir(mod):
                    missing.append(pkg + "." + name)
                obj = getattr(mod, name)
                owner = getattr(obj, "__module__", None)
                if owner and owner.startswith("rbo_jax") and \\
                        getattr(importlib.import_module(owner), name, obj) is not obj:
                    wrong.append(pkg + "." + name)
        star = {{}}
        exec("from rbo_jax import *", star)
        import rbo_jax.simulate  # binds the submodule to rbo_jax.simulate, unless kept lazy
        print(json.dumps({{"missing": missing, "wrong": wrong, "all": rbo_jax.__all__,
                          "star": sorted(k for k in star if not k.startswith("__")),
                          "simulate": type(rbo_jax.simulate).__name__,
                          "kinematics": type(rbo_jax.kinematics).__name__}}))
    """)
    assert got["missing"] == [] and got["wrong"] == []
    assert len(got["all"]) == len(set(got["all"])) > 80
    assert got["star"] == sorted(got["all"])
    assert got["simulate"] == "function"  # the function, as before; the module is rbo_jax.simulate
    assert got["kinematics"] == "module"  # submodules load on access, as after an eager import


def test_the_namespace_in_this_process():
    assert rbo_jax.simulate is sys.modules["rbo_jax.motion"].simulate  # every model's front door
    assert rbo_jax.SolveStatus is sys.modules["rbo_jax.trajectory"].SolveStatus
    assert isinstance(rbo_jax.__version__, str) and rbo_jax.__version__
    assert {"sweep", "fit", "RigidBodyOscillator", "__version__"} <= set(dir(rbo_jax))
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        rbo_jax.no_such_name  # noqa: B018
    with pytest.raises(ImportError):
        from rbo_jax import no_such_name  # noqa: F401
    with pytest.raises(AttributeError):
        rbo_jax.batch.sweeep  # noqa: B018


def test_a_name_exported_twice_is_refused():
    with pytest.raises(ValueError, match="'x' is exported from both"):
        rbo_jax._lazy.attach("rbo_jax", {".a": ("x",), ".b": ("x",)})
