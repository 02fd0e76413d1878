"""MkDocs hook: the notebooks of ``notebooks/`` as pages, executed at build time.

The notebooks are stored without outputs. Each is executed top to bottom (nbclient, the
``python3`` kernel of this environment, at the notebooks' default small sizes, two at a time),
converted to Markdown with its figures (nbconvert), and added to the site as
``notebooks/NAME.md`` with ``notebooks/NAME_files/*.png`` (and ``notebooks/figures/X.png`` for
a cell whose metadata says ``"figure": "X"``: a stable path for the topic pages); the Markdown
then goes through the same extensions as every page (the equations of ``math.py`` included). A
cell that raises fails the build. Executed notebooks are kept in ``.cache/docs-notebooks/``,
keyed by the notebook and the package's sources, so an unchanged notebook is not run again;
``tests/test_notebooks.py`` stores there the notebooks it executes (:func:`store`), so that
``make docs`` after ``make test-slow`` (CI's order) converts them without running them twice.
"""

from __future__ import annotations

import hashlib
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
CACHE = ROOT / ".cache" / "docs-notebooks"


def _key(path: Path) -> str:
    digest = hashlib.sha256(path.read_bytes())
    for source in sorted((ROOT / "rbo_jax").rglob("*")):
        if source.suffix in (".py", ".toml"):
            digest.update(source.relative_to(ROOT).as_posix().encode())
            digest.update(source.read_bytes())
    return digest.hexdigest()[:20]


def store(path: Path, nb) -> Path:
    """Keep ``nb``, the notebook ``path`` executed top to bottom at its default sizes, as this
    hook's executed copy of it (replacing older ones); the file written."""
    import nbformat

    cached = CACHE / f"{path.stem}-{_key(path)}.ipynb"
    CACHE.mkdir(parents=True, exist_ok=True)
    for old in CACHE.glob(f"{path.stem}-*.ipynb"):
        old.unlink()
    nbformat.write(nb, cached)
    return cached


def _execute(path: Path):
    import nbclient
    import nbformat

    cached = CACHE / f"{path.stem}-{_key(path)}.ipynb"
    if cached.is_file():
        return nbformat.read(cached, as_version=4)
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
    )
    client.execute()  # raises CellExecutionError with the traceback if a cell fails
    store(path, nb)
    return nb


def _markdown(nb, stem: str) -> tuple[str, dict[str, bytes]]:
    from nbconvert import MarkdownExporter

    for cell in nb.cells:  # figures and text, not the HTML reprs (xarray's carries styles)
        for output in cell.get("outputs", []):
            data = output.get("data", {})
            if "text/html" in data and len(data) > 1:
                del data["text/html"]
    exporter = MarkdownExporter()
    body, resources = exporter.from_notebook_node(
        nb, resources={"output_files_dir": f"{stem}_files", "unique_key": stem}
    )
    return body, {**resources.get("outputs", {}), **_named_figures(nb)}


def _named_figures(nb) -> dict[str, bytes]:
    """The figure of each cell whose metadata names it (``"figure": "fitting-rig"``) under a
    stable path, ``figures/fitting-rig.png``, for the topic pages to show."""
    import base64

    out = {}
    for cell in nb.cells:
        name = cell.get("metadata", {}).get("figure")
        pngs = [
            o["data"]["image/png"]
            for o in cell.get("outputs", [])
            if "image/png" in o.get("data", {})
        ]
        if name and pngs:
            out[f"figures/{name}.png"] = base64.b64decode(pngs[-1])
    return out


def on_files(files, config):
    from mkdocs.structure.files import File

    os.environ.pop("RBO_NOTEBOOK_FULL", None)  # the default, small sizes
    paths = sorted(NOTEBOOKS.glob("*.ipynb"))
    with ThreadPoolExecutor(max_workers=2) as pool:
        executed = list(pool.map(_execute, paths))
    for path, nb in zip(paths, executed):
        body, outputs = _markdown(nb, path.stem)
        files.append(File.generated(config, f"notebooks/{path.stem}.md", content=body))
        for name, data in outputs.items():
            files.append(File.generated(config, f"notebooks/{name}", content=data))
    return files
