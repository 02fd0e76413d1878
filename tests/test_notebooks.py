"""The notebooks in ``notebooks/`` run top to bottom (nbclient, at their default small sizes) and
are stored without outputs. Each notebook asserts its own key results, so a wrong number fails
here as an error in the executed cell."""

from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOK_DIR = ROOT / "notebooks"
NOTEBOOKS = [
    "01_kinematics.ipynb",
    "02_nikolai_paradox.ipynb",
    "03_precession_and_integrability.ipynb",
    "04_fitting.ipynb",
    "05_bifurcation.ipynb",
    "06_lattice.ipynb",
    "07_rods.ipynb",
]
KERNEL = "python3"


def _read(name):
    import nbformat  # test extra

    path = NOTEBOOK_DIR / name
    assert path.is_file(), f"missing notebook {path}"
    return nbformat.read(path, as_version=4)


def _docs_hook():
    """docs/_hooks/notebooks.py, the site's notebook pages (its cache of executed notebooks)."""
    spec = importlib.util.spec_from_file_location(
        "_docs_notebooks", ROOT / "docs/_hooks/notebooks.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _check_kernel():
    """The ``python3`` kernel must run this interpreter (ipykernel installed in this environment
    provides it); nothing is installed here."""
    import ipykernel  # noqa: F401  (test extra: provides the kernel)
    from jupyter_client.kernelspec import KernelSpecManager, NoSuchKernel

    try:
        spec = KernelSpecManager().get_kernel_spec(KERNEL)
    except NoSuchKernel:
        pytest.fail(f"no {KERNEL!r} Jupyter kernel for {sys.executable} (pip install ipykernel)")
    exe = spec.argv[0]
    # jupyter_client replaces a bare "python" with sys.executable when it starts the kernel
    if exe not in ("python", "python3") and Path(exe).resolve() != Path(sys.executable).resolve():
        pytest.fail(f"the {KERNEL!r} kernel runs {exe}, not {sys.executable}")


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_is_stored_without_outputs(name):
    nb = _read(name)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code, f"{name} has no code cells"
    for i, cell in enumerate(code):
        assert cell.get("outputs", []) == [], f"{name}: code cell {i} has stored outputs"
        assert cell.get("execution_count") is None, f"{name}: code cell {i} has an execution count"
    # parameters first, then `import rbo_jax` (it enables float64) before anything else of JAX
    assert "RBO_NOTEBOOK_FULL" in code[0].source, f"{name}: the first code cell sets the sizes"
    assert code[1].source.lstrip().startswith("import rbo_jax"), f"{name}: import rbo_jax first"


@pytest.mark.slow  # integration: the notebooks executed, 23-444 s each from a cold cache
@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_executes(name, monkeypatch):
    """Each notebook runs without an error. The executed notebook is then kept in the docs
    build's cache (docs/_hooks/notebooks.py, keyed by the notebook and the package's sources):
    `make docs` after `make test-slow`, CI's order, converts it without running it again."""
    import nbclient  # test extra

    _check_kernel()
    nb = _read(name)
    monkeypatch.delenv("RBO_NOTEBOOK_FULL", raising=False)  # the default, small sizes
    client = nbclient.NotebookClient(
        nb,
        timeout=600,  # a cell's limit (a hang), as the docs build's
        kernel_name=KERNEL,
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    start = time.perf_counter()
    client.execute()  # raises CellExecutionError (with the traceback) if any cell fails
    elapsed = time.perf_counter() - start
    print(f"{name}: executed in {elapsed:.1f} s")
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors, f"{name}: {errors[0].get('ename')}: {errors[0].get('evalue')}"
    _docs_hook().store(NOTEBOOK_DIR / name, nb)
