"""MkDocs hook: every public name of rbo_jax has an entry on the API pages.

The public names are the ``__all__`` of the packages in ``api_names.PACKAGES``. Each must be
documented by a ``::: identifier`` line of a page under ``docs/api/`` (the identifier of
``api_names.identifier``: the defining module, since the packages export lazily) and carry an
anchor ``[](){#package.name}`` so that ``package.name`` can be linked. A missing entry or anchor
fails the build. After the build, ``site/api-names.json`` lists every public name with its page
and its two anchors, for ``tests/test_docs_browser.py``.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from api_names import identifier, public_names  # noqa: E402
from mkdocs.exceptions import PluginError  # noqa: E402

_ENTRY = re.compile(r"^::: *([\w.]+)", re.M)
_ANCHOR = re.compile(r"\[\]\(\)\{#([\w.]+)\}")
_manifest: dict[str, dict[str, str]] = {}


def on_files(files, config):
    entries: dict[str, str] = {}  # identifier -> page
    anchors: dict[str, str] = {}  # anchor -> page
    for file in files.documentation_pages():
        if not file.src_uri.startswith("api/"):
            continue
        text = Path(file.abs_src_path).read_text(encoding="utf-8")
        for ident in _ENTRY.findall(text):
            entries[ident] = file.src_uri
        for anchor in _ANCHOR.findall(text):
            anchors[anchor] = file.src_uri
    missing = []
    _manifest.clear()
    for package, name in public_names():
        public = f"{package}.{name}"
        ident = identifier(package, name)
        if ident not in entries:
            missing.append(f"{public}: no '::: {ident}' on an API page (docs/api/*.md)")
        elif anchors.get(public) != entries[ident]:
            missing.append(f"{public}: no anchor '[](){{#{public}}}' beside '::: {ident}'")
        else:
            page = files.get_file_from_path(entries[ident])
            _manifest[public] = {"page": page.url, "anchor": public, "entry": ident}
    if missing:
        raise PluginError("API reference incomplete:\n  " + "\n  ".join(missing))
    return files


def on_post_build(config):
    path = Path(config["site_dir"]) / "api-names.json"
    path.write_text(json.dumps(_manifest, indent=1, sort_keys=True), encoding="utf-8")
