"""MkDocs hook: a line ``<!-- rbo-jax-layers -->`` of a page becomes a picture of the package's
layers, drawn at build time from ``LAYERS`` of ``tests/test_architecture.py`` (the list the
architecture test enforces), so the picture cannot fall behind the code: one band per layer,
the lowest at the bottom, each module or subpackage a box; a module imports only from the
bands below it."""

from __future__ import annotations

import ast
import html
from pathlib import Path

_PLACEHOLDER = "<!-- rbo-jax-layers -->"
_ROOT = Path(__file__).resolve().parents[2]
_WIDTH, _BAND, _GAP, _CHAR = 760, 30, 6, 7.2


def layers() -> list[tuple[str, ...]]:
    """``LAYERS`` of tests/test_architecture.py, read without importing the test."""
    tree = ast.parse((_ROOT / "tests" / "test_architecture.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and [ast.unparse(t) for t in node.targets] == ["LAYERS"]:
            return [tuple(x) for x in ast.literal_eval(node.value)]
    raise ValueError("tests/test_architecture.py defines no LAYERS")


def _is_package(name: str) -> bool:
    return (_ROOT / "rbo_jax" / name / "__init__.py").exists()


def svg() -> str:
    bands = [b for b in layers() if b != ("__main__",)][::-1]  # the top layer first
    height = len(bands) * (_BAND + _GAP) + _GAP
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {_WIDTH} {height}" '
        f'width="{_WIDTH}" role="img" font-family="Helvetica, Arial, sans-serif" font-size="12">',
        "<title>The layers of rbo_jax: each imports only from the layers below it</title>",
    ]
    for row, band in enumerate(bands):
        y = _GAP + row * (_BAND + _GAP)
        out.append(f'<rect x="0" y="{y}" width="{_WIDTH}" height="{_BAND}" rx="4" fill="#eef0fa"/>')
        x = 8.0
        for name in band:
            label = f"{name}/" if _is_package(name) else name
            w = _CHAR * len(label) + 16
            fill = "#c5cae9" if _is_package(name) else "#ffffff"
            out.append(
                f'<rect x="{x:.0f}" y="{y + 4}" width="{w:.0f}" height="{_BAND - 8}" rx="3" '
                f'fill="{fill}" stroke="#3f51b5" stroke-width="0.8"/>'
            )
            out.append(
                f'<text x="{x + w / 2:.0f}" y="{y + _BAND / 2 + 4}" text-anchor="middle">'
                f"{html.escape(label)}</text>"
            )
            x += w + 8
    out.append("</svg>")
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if _PLACEHOLDER not in markdown:
        return markdown
    return markdown.replace(_PLACEHOLDER, f'<div class="rbo-layers">\n{svg()}\n</div>')
