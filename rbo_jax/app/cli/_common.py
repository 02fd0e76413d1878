"""What the ``rbo-jax`` commands share: option types, the model options turned into a
:class:`~rbo_jax.app.spec.ModelSpec`, exit statuses and small printing helpers. The options
themselves are data: ``options.toml``."""

from __future__ import annotations

import argparse
import math

from .._io import suffix
from .._outputs import output_problem
from .._reader import SpecError
from ..spec import ModelSpec


class Failure(Exception):
    """A command ends with ``message`` on stderr and exit status ``code`` (1: the computation
    failed; 2: invalid input)."""

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code


def flag(dest: str) -> str:
    """The option of an argparse destination: ``rod_start`` -> ``--rod-start``."""
    return "--" + dest.replace("_", "-")


def refuse_group(args: argparse.Namespace, dests, option: str, what: str, example: str) -> None:
    """Without ``option``: none of its group's options (``dests``) may be given."""
    given = [d for d in dests if getattr(args, d) is not None]
    if given:
        raise Failure(
            f"{flag(given[0])} belongs to {option} ({what}); give {option} SPEC too, "
            f"e.g. {example}."
        )


def settings(args: argparse.Namespace, defaults: dict) -> argparse.Namespace:
    """The options of a group that default to None (so that :func:`refuse_group` sees which
    were given), with their ``defaults`` filled in."""
    given = {d: getattr(args, d) for d in defaults}
    return argparse.Namespace(**{d: defaults[d] if v is None else v for d, v in given.items()})


def floats(text: str) -> tuple[float, ...]:
    """``"x,y,z"`` -> floats (any count: the model description checks the shape)."""
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers such as 0.1,0,-0.2, got {text!r}"
        ) from None


def horizons(text: str) -> tuple[float, ...]:
    """``"0.2,0.5,1"`` -> increasing fractions in (0, 1] (staged fitting of :func:`rbo_jax.fit`)."""
    values = floats(text)
    if any(not 0.0 < h <= 1.0 for h in values) or list(values) != sorted(values):
        raise argparse.ArgumentTypeError(
            f"expected increasing fractions in (0, 1] such as 0.2,0.5,1, got {text!r}"
        )
    return values


# the most values of one axis of a grid (800 MB of float64 for the axis alone; a map of more
# points than this is a sweep's job, with a store)
MAX_AXIS = 10**8


def grid(text: str):
    """``"start:stop:num"`` (inclusive linspace), ``"a,b,c"`` or ``"a"`` -> 1-D float array."""
    import numpy as np

    try:
        if ":" in text:
            start, stop, num = text.split(":")
            n = int(num)
            if n < 1:
                raise ValueError
            if n > MAX_AXIS:
                raise argparse.ArgumentTypeError(
                    f"at most {MAX_AXIS:,} values per axis, got {n:,} in {text!r}"
                )
            values = np.linspace(float(start), float(stop), n)
        else:
            values = np.asarray([float(x) for x in text.split(",")])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a value (0.5), a list (0.1,0.2,0.5) or start:stop:num with num >= 1 "
            f"(-0.8:0.8:41), got {text!r}"
        ) from None
    if not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"values must be finite, got {text!r}")
    return values


def check_output(
    path: str,
    option: str,
    allowed: tuple[str, ...] | None = None,
    *,
    directory: bool | None = None,
    make_parents: bool = False,
) -> str:
    """An output path checked before any work (exit status 2 naming ``option``): its format
    by the suffix (``allowed``), and that it can be written (:func:`output_problem`). A
    ``.zarr`` output is a folder unless ``directory`` says otherwise. Returns the suffix."""
    ext = check_suffix(path, allowed, option) if allowed is not None else suffix(path)
    if directory is None:
        directory = ext == ".zarr"
    why = output_problem(path, directory=directory, make_parents=make_parents)
    if why is not None:
        raise Failure(f"{option} {path}: cannot be written: {why}.")
    return ext


def check_number(value, option: str, *, minimum=None, above=None, maximum=None) -> None:
    """A numeric option: finite, and ``>= minimum`` / ``> above`` / ``<= maximum`` where given
    (exit status 2 naming ``option``)."""
    bounds = []
    if minimum is not None:
        bounds.append(f">= {minimum:g}")
    if above is not None:
        bounds.append(f"> {above:g}")
    if maximum is not None:
        bounds.append(f"<= {maximum:g}")
    ok = (
        math.isfinite(value)
        and (minimum is None or value >= minimum)
        and (above is None or value > above)
        and (maximum is None or value <= maximum)
    )
    if not ok:
        need = "finite" + ("".join(f" and {b}" for b in bounds) if bounds else "")
        shown = f"{value:g}" if isinstance(value, float) else str(value)
        raise Failure(f"{option} must be {need}, got {shown}.")


def check_times(args: argparse.Namespace) -> None:
    """``--t1`` (> 0) and ``--samples`` (>= 2): the sample times of a run."""
    check_number(args.t1, "--t1", above=0)
    if args.samples < 2:
        raise Failure(f"--samples must be >= 2, got {args.samples}.")


# the largest step budget or iteration count: far above any useful one, and below every integer
# type a solver may count in
MAX_COUNT = 2**31 - 1


def check_count(value: int, option: str, minimum: int = 1) -> None:
    """An integer option between ``minimum`` and :data:`MAX_COUNT` (exit status 2)."""
    if not minimum <= value <= MAX_COUNT:
        raise Failure(f"{option} must be an integer from {minimum} to {MAX_COUNT}, got {value}.")


def check_devices(value: int | None, local: bool = True) -> None:
    """``--devices N``: at least 1 and, for this process's own devices (``local``), at most
    their number (exit status 2)."""
    if value is None:
        return
    if local:
        import jax

        n = jax.local_device_count()
        if not 1 <= value <= n:
            raise Failure(
                f"--devices must be from 1 to {n} (the local devices of this process), got {value}."
            )
    elif value < 1:
        raise Failure(f"--devices must be at least 1, got {value}.")


def check_state(value, option: str) -> None:
    """An initial vector option (``--theta0``, ``--Omega0``): three finite components."""
    if value is None:
        return
    text = ",".join(f"{x:g}" for x in value)
    if len(value) != 3:
        raise Failure(
            f"{option} must have shape (3,) (three components X,Y,Z), got {len(value)}: {text}."
        )
    if not all(math.isfinite(x) for x in value):
        raise Failure(f"{option} must be finite, got {text}.")


def check_suffix(path: str, allowed: tuple[str, ...], option: str) -> str:
    ext = suffix(path)
    if ext not in allowed:
        raise Failure(
            f"{option} {path}: unknown format {ext or '(no suffix)'!r}; use "
            + " or ".join(allowed)
            + "."
        )
    return ext


def check_vector(x, name: str):
    """A (3,) vector, or exit status 2 with the package's message naming ``name``."""
    from ...kinematics import as_vector

    try:
        return as_vector(x, name)
    except (ValueError, TypeError) as e:
        raise Failure(str(e)) from None


def table(header: list[str], rows: list[list[float]]) -> str:
    widths = [max(12, len(h)) for h in header]
    out = ["  ".join(h.rjust(w) for h, w in zip(header, widths))]
    out.append("  ".join("-" * w for w in widths))
    for r in rows:
        out.append(
            "  ".join(
                f"{v:{w}.4e}" if isinstance(v, float) else str(v).rjust(w)
                for v, w in zip(r, widths)
            )
        )
    return "\n".join(out)


def pyplot_or_fail(command: str):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise Failure(
            f"--plot needs matplotlib, which is not installed (pip install "
            f"'rbo_jax[plot]'); run {command} without --plot."
        ) from None
    return plt


# ---------------------------------------------------------------------------------------------
# The model options of simulate and fit
# ---------------------------------------------------------------------------------------------


_LOAD_OPTIONS = (("follower", "M"), ("dead", "M"), ("friction", "b"))


def model_table(args: argparse.Namespace) -> tuple[dict, dict]:
    """The model options in the table form of :class:`ModelSpec` (loads in the order follower,
    dead, friction) and the option that sets each key (for messages)."""
    if args.principal is not None and (args.A1 is not None or args.A3 is not None):
        raise Failure("--principal replaces --A1 and --A3: give one or the other.")
    if args.foundation == "barrier" and (args.alpha is None or args.beta is None):
        raise Failure(
            "--foundation barrier needs --alpha and --beta (the barriers of (4.49); "
            "'inf' switches one off)."
        )
    if args.foundation != "barrier" and (args.alpha is not None or args.beta is not None):
        raise Failure(
            f"--alpha and --beta belong to --foundation barrier (4.49); the "
            f"{args.foundation} foundation has no barriers."
        )
    options = {
        "[model] axis": "--axis",
        "[model.inertia] A1": "--A1",
        "[model.inertia] A3": "--A3",
        "[model.inertia] moments": "--principal",
    }
    if args.principal is not None:
        inertia = {"moments": list(args.principal)}
    else:
        inertia = {
            "A1": 1.0 if args.A1 is None else args.A1,
            "A3": 0.6 if args.A3 is None else args.A3,
        }
    foundation = {"type": args.foundation}
    foundation |= {
        "quadratic": {"c": args.c, "d": args.d},
        "barrier": {"c": args.c, "d": args.d},
        "cosine": {"c": args.c},
    }.get(args.foundation, {})
    if args.foundation == "barrier":
        foundation |= {"alpha": args.alpha, "beta": args.beta}
    options |= {f"[model.foundation] {n}": f"--{n}" for n in ("c", "d", "alpha", "beta")}
    loads = []
    for option, key in _LOAD_OPTIONS:
        if getattr(args, option) is not None:
            options[f"[model.loads][{len(loads)}] {key}"] = f"--{option}"
            loads.append({"type": option, key: getattr(args, option)})
    return {
        "axis": list(args.axis),
        "inertia": inertia,
        "foundation": foundation,
        "loads": loads,
    }, options


def model_spec(table_: dict, options: dict, axes=None) -> ModelSpec:
    """:meth:`ModelSpec.from_mapping`, its errors re-worded with the option at fault (exit
    status 2)."""
    try:
        return ModelSpec.from_mapping(table_, axes=axes)
    except SpecError as e:
        raise Failure(f"{options.get(e.where, e.where)}: {e.message}") from None


def spec_from_args(args: argparse.Namespace) -> ModelSpec:
    return model_spec(*model_table(args))


def load_index(spec: ModelSpec, kind: str) -> int:
    """The position of the load of type ``kind`` in the model's loads."""
    return [t.type for t in spec.loads].index(kind)
