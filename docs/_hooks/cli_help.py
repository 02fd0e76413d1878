"""MkDocs hook: a line ``<!-- rbo-jax-help COMMAND -->`` of a page becomes the ``--help`` text of
``rbo-jax COMMAND`` (``<!-- rbo-jax-help -->``: of ``rbo-jax`` itself), taken at build time from
the parser that ``rbo_jax/app/cli/options.toml`` describes, so the page cannot fall behind it."""

from __future__ import annotations

import os
import re

_PLACEHOLDER = re.compile(r"^<!-- rbo-jax-help ?([\w-]*) -->$", re.M)


def _help(command: str) -> str:
    from rbo_jax.app.cli import build_parser

    os.environ["COLUMNS"] = "80"  # argparse wraps to the terminal's width; 80 fits the page
    parser = build_parser()
    if command:
        (sub,) = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
        parser = sub.choices[command]
    return f"```text\n{parser.format_help().rstrip()}\n```"


def on_page_markdown(markdown: str, page, config, files) -> str:
    return _PLACEHOLDER.sub(lambda m: _help(m.group(1)), markdown)
