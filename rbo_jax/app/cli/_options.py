"""The commands and options of ``rbo-jax``, built from their description as data
(``options.toml``: types, defaults and help texts in one place)."""

from __future__ import annotations

import argparse
import functools
import re
import textwrap
from importlib import resources

from ._common import floats, grid, horizons

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

_TYPES = {
    "float": float,
    "int": int,
    "str": str,
    "floats": floats,
    "grid": grid,
    "horizons": horizons,
}


# A word that starts like a number: a minus sign, then a digit, '.' and a digit, or inf, infinity or
# nan (alone or before ',' or ':'). argparse reads it as a value, not an option (before Python
# 3.14 its own matcher takes only plain numbers such as -1 and -0.5, so that `--M -0.8:0.8:41`,
# `--theta0 -0.1,0,0.2` or `--rtol -1e-3` ended in "expected one argument").
# The option's type then says what is wrong with a word such as -0.8:0.8:x. No option of rbo-jax
# looks like a number, so none is mistaken for a value.
NUMBER_LIKE = re.compile(r"-(?:\.?\d|(?:inf(?:inity)?|nan)(?![^,:]))", re.IGNORECASE)


class Parser(argparse.ArgumentParser):
    """argparse's parser with usage errors on one line (the option and what is wrong with it,
    then where the help is) instead of the usage text and the error, exit status 2; a value
    that starts with a minus sign needs no '=' (:data:`NUMBER_LIKE`: ``--M -0.8:0.8:41``,
    ``--theta0 -0.1,0,0.2``). The subparsers of its ``add_subparsers`` are of this class too
    (argparse's default ``parser_class`` is the parent's)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NUMBER_LIKE

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


@functools.cache
def table() -> dict:
    """The parsed ``options.toml``."""
    return tomllib.loads(resources.files(__package__).joinpath("options.toml").read_text())


def wrap(text: str) -> str:
    """A description paragraph rewrapped to 88 columns (the raw formatter keeps it as is)."""
    return textwrap.fill(" ".join(text.split()), width=88)


def _add_option(group, option: dict) -> None:
    kind = option.get("type", "float")
    kwargs = {"help": option["help"]}
    if kind == "flag":
        group.add_argument(*option["flags"], action="store_true", **kwargs)
        return
    kwargs["type"] = str if kind == "choice" else _TYPES[kind]
    for key in ("metavar", "choices"):
        if key in option:
            kwargs[key] = option[key]
    default = option.get("default")
    if isinstance(default, list):
        default = tuple(default)
    elif isinstance(default, str) and kind in ("grid", "horizons"):
        default = _TYPES[kind](default)
    if option["flags"][0].startswith("-"):
        kwargs["default"] = default
    group.add_argument(*option["flags"], **kwargs)


def add_group(parser, name: str, **fmt) -> None:
    """The options of group ``name`` (``[groups.NAME]``), in an argument group if it has a title
    (``fmt`` fills its description)."""
    spec = table()["groups"][name]
    group = parser
    if "title" in spec:
        description = spec.get("description")
        group = parser.add_argument_group(
            spec["title"], wrap(description.format(**fmt)) if description else None
        )
    if spec.get("exclusive"):
        group = group.add_mutually_exclusive_group(required=True)
    for option in spec["options"]:
        _add_option(group, option)


def add_command(sub, name: str, func) -> argparse.ArgumentParser:
    """The subcommand ``name`` (``[commands.NAME]``) with its groups of options, run by
    ``func(args)``."""
    spec, common = table()["commands"][name], table()
    description = spec.get("description")
    if description is not None:
        description = wrap(description + (" " + common["units"] if spec.get("units") else ""))
    epilog = spec.get("epilog")
    if spec.get("negative"):
        epilog = (epilog + "\n\n" if epilog else "") + wrap(common["negative"])
    p = sub.add_parser(
        name,
        help=spec["help"],
        description=description,
        epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    for group in spec["groups"]:
        add_group(p, group, model_role=spec.get("model_role", ""))
    p.set_defaults(func=func)
    return p
