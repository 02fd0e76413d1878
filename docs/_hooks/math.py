"""MkDocs hook: render the LaTeX of pages and docstrings as MathML at build time.

``pymdownx.arithmatex`` (generic mode) turns ``$...$`` and ``$$...$$`` into
``<span class="arithmatex">\\(...\\)</span>`` and ``<div class="arithmatex">\\[...\\]</div>``;
this hook replaces each with the MathML of ``latex2mathml``, which browsers render natively. No
script and no network are needed to view the equations. A formula that latex2mathml cannot read
fails the build with the page and the formula.
"""

from __future__ import annotations

import html
import re

from latex2mathml.converter import convert

_INLINE = re.compile(r'<span class="arithmatex">\\\((.*?)\\\)</span>', re.S)
_BLOCK = re.compile(r'<div class="arithmatex">\\\[(.*?)\\\]</div>', re.S)
# reStructuredText roles of the docstrings (:func:`x`, :mod:`x`, ...), shown as plain code
_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|obj|exc|ref|py:\w+):(?=<code>)")


def _render(latex: str, display: str, where: str) -> str:
    text = html.unescape(latex).strip()
    try:
        mathml = convert(text, display=display)
    except Exception as error:  # noqa: BLE001 - any failure of the converter stops the build
        raise ValueError(f"{where}: cannot render {text!r} as MathML: {error}") from error
    if display == "block":
        return f'<div class="math-display">{mathml}</div>'
    return mathml


_TITLE = re.compile(r"\\\((.*?)\\\)", re.S)  # \(...\) in a heading's entry of the table of contents


def _render_toc(items, where: str) -> None:
    for item in items:
        item.title = _TITLE.sub(lambda m: _render(m.group(1), "inline", where), item.title)
        _render_toc(item.children, where)


def on_page_content(html_text: str, page, config, files) -> str:
    where = page.file.src_uri
    _render_toc(page.toc, where)
    html_text = _BLOCK.sub(lambda m: _render(m.group(1), "block", where), html_text)
    html_text = _INLINE.sub(lambda m: _render(m.group(1), "inline", where), html_text)
    return _ROLE.sub("", html_text)
