r"""``rbo-jax simulate --rod SPEC``: the motion of a rod (:func:`rbo_jax.lattice.rod`) given by a
``[rod]`` table (:class:`~rbo_jax.app.rodspec.RodSpec`): a TOML file with that table, or its
keys inline (``--rod 'n = 8, loads = [{ type = "gravity" }]'``), as a table and a dataset.

The initial state (``--rod-start``): ``straight``, the straight reference state at rest, released
under the loads at $t = 0$ (a cantilever under gravity sags and swings); or ``equilibrium``, the
static state under the loads (:func:`rbo_jax.lattice.solve_equilibrium`, ``--rod-steps`` load
steps). Both add the perturbation $v_i = \varepsilon\,(s_i/L)\,e_1$ of the bodies' velocities,
$s_i = i\,L/N$ the arc length of body $i$ and $\varepsilon$ = ``--rod-perturbation`` (default 0
from ``straight``, 1e-3 from ``equilibrium``: an equilibrium left alone stays where it is; a
perturbed one shows whether it is stable, e.g. Beck's column above its flutter load).

The options of the ``rod`` group default to None here, so that one given without ``--rod`` is
refused; with ``--rod`` the options of one body (the model, its loads, its initial state and
integrator) and of ``--lattice`` are refused. Everything is checked before anything is
compiled.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .._io import DATASET_SUFFIXES
from .._reader import SpecError
from ..rodspec import RodSpec
from ._common import Failure, check_number, check_suffix, refuse_group, settings
from ._memory import BYTES_PER_BODY, BYTES_PER_BODY_SAMPLE, check_memory
from ._options import table
from ._samples import equilibrium, finish, solver_options

DEFAULTS = {"rod_start": "straight", "rod_perturbation": None, "rod_steps": 1, "rod_method": None}
_PERTURBATION = {"straight": 0.0, "equilibrium": 1e-3}
# one body's options that a rod does not use (their groups in options.toml)
_BODY_GROUPS = ("model", "loads", "lattice")
_BODY_OPTIONS = ("--theta0", "--Omega0", "--about-equilibrium", "--integrator", "--progress")


def refuse_rod_options(args: argparse.Namespace) -> None:
    """Without ``--rod``: none of the rod options may be given."""
    refuse_group(args, DEFAULTS, "--rod", "a rod, rbo_jax.lattice.rod", "--rod 'n = 8'")


def _options_of_one_body():
    groups = table()["groups"]
    for name in _BODY_GROUPS:
        yield from groups[name]["options"]
    yield from (o for o in groups["simulate"]["options"] if o["flags"][0] in _BODY_OPTIONS)


def _refuse_body_options(args: argparse.Namespace) -> None:
    """With ``--rod``: an option of one body (or of a lattice) set away from its default."""
    for option in _options_of_one_body():
        flag = option["flags"][0]
        dest = flag.lstrip("-").replace("-", "_")
        value, default = getattr(args, dest), option.get("default")
        if option.get("type") == "flag":
            default = False
        if isinstance(default, list):
            value = list(value)
        if value == default:
            continue
        raise Failure(
            f"{flag} is an option of one body (or of --lattice); a rod (--rod) takes its "
            f"parameters and loads from its [rod] table and starts from --rod-start."
        )


def _read_table(text: str) -> dict:
    """The ``[rod]`` table of SPEC: a TOML file (``*.toml``) or the table's keys inline."""
    from ._options import tomllib

    if text.lower().endswith(".toml"):
        try:
            cfg = tomllib.loads(Path(text).read_text())
        except OSError as e:
            raise Failure(f"--rod {text}: cannot be read: {e.strerror or e}.") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise Failure(f"--rod {text}: not valid TOML: {e}") from None
        if not isinstance(cfg.get("rod"), dict):
            raise Failure(f"--rod {text}: the file has no [rod] table.")
        return cfg["rod"]
    try:
        return tomllib.loads(f"rod = {{ {text} }}")["rod"]
    except tomllib.TOMLDecodeError as e:
        raise Failure(
            f"--rod: {text!r} is neither a FILE.toml nor the keys of a [rod] table "
            f"(TOML, e.g. --rod 'n = 8, bending = 2'): {e}"
        ) from None


def _settings(args: argparse.Namespace) -> argparse.Namespace:
    """The rod options with their defaults, checked; the body options refused."""
    _refuse_body_options(args)
    s = settings(args, DEFAULTS)
    if s.rod_perturbation is None:
        s.rod_perturbation = _PERTURBATION[s.rod_start]
    check_number(s.rod_perturbation, "--rod-perturbation", above=None)
    if s.rod_steps < 1:
        raise Failure(f"--rod-steps must be >= 1, got {s.rod_steps}.")
    if s.rod_steps != 1 and s.rod_start != "equilibrium":
        raise Failure("--rod-steps belongs to --rod-start equilibrium (Newton's load steps).")
    if args.out is not None:
        check_suffix(args.out, DATASET_SUFFIXES, "--out")  # no CSV of a rod
    return s


def _rod_spec(args) -> RodSpec:
    try:
        return RodSpec.from_mapping(_read_table(args.rod))
    except SpecError as e:
        raise Failure(f"--rod: {e}") from None


def _initial_state(rod, s):
    """The state of --rod-start plus the perturbation of the velocities, and a line."""
    import jax.numpy as jnp

    from ...lattice import RodState

    if s.rod_start == "equilibrium":
        sol = equilibrium(rod, "--rod-start equilibrium", steps=s.rod_steps)
        state = sol.state
        what = (
            f"the equilibrium under the loads (Newton, {int(sol.iterations)} steps, residual "
            f"{float(sol.residual):.1e})"
        )
    else:
        state, what = rod.straight(), "the straight rod at rest, released under the loads"
    s_over_L = jnp.arange(rod.n_bodies, dtype=state.r.dtype) / rod.n
    e1 = jnp.asarray([[1.0, 0.0, 0.0]], dtype=state.v.dtype)
    v = state.v + s.rod_perturbation * s_over_L[:, None] * e1
    state = RodState(state.theta, state.r, state.Omega, v)
    return state, f"{what}; velocities + {s.rod_perturbation:g} (s/L) e1"


def _dataset(traj, **attrs):
    """The samples as an xarray Dataset: ``theta``, ``centreline`` (t, body, component),
    ``Omega``, ``v``, ``tip`` (t, component), ``energy`` (t)."""
    import numpy as np
    import xarray as xr

    vec = ("t", "body", "component")
    st = traj.states
    r = np.asarray(st.r)
    data = {
        "centreline": (vec, r, {"long_name": "position r_i of the bodies' centres"}),
        "theta": (vec, np.asarray(st.theta), {"long_name": "turn-vector theta_i (4.1)"}),
        "Omega": (vec, np.asarray(st.Omega), {"long_name": "right angular velocity Omega_i"}),
        "v": (vec, np.asarray(st.v), {"long_name": "velocity v_i of the centres"}),
        "tip": (("t", "component"), r[:, -1], {"long_name": "position of the tip body"}),
        "energy": ("t", np.asarray(traj.energy), {"long_name": "total mechanical energy"}),
    }
    ds = xr.Dataset(
        data,
        coords={
            "t": ("t", np.asarray(traj.ts)),
            "body": np.arange(r.shape[1]),
            "component": ["x", "y", "z"],
        },
    )
    ds.attrs.update(
        status=traj.status_name, message=traj.message, num_steps=int(traj.num_steps), **attrs
    )
    return ds


def simulate_rod_command(args: argparse.Namespace) -> int:
    """``rbo-jax simulate --rod SPEC``: the motion of a rod, as a table and a dataset."""
    import jax.numpy as jnp
    import numpy as np

    from ...lattice import simulate

    s = _settings(args)
    spec = _rod_spec(args)
    bodies = spec.n + 1
    check_memory(
        bodies * (BYTES_PER_BODY + args.samples * BYTES_PER_BODY_SAMPLE),
        f"--rod n = {spec.n} with --samples {args.samples}",
        "give fewer bodies (n) or fewer samples (--samples)",
    )
    try:
        rod = spec.build()
    except ValueError as e:  # the library's checks of what the table's did not cover
        raise Failure(f"--rod: {e}") from None
    print(f"Rod (rbo_jax.lattice.rod): {spec.describe()}")
    state0, initial = _initial_state(rod, s)
    method = s.rod_method or "explicit"
    print(f"initial state: {initial}; method {method}")
    ts = jnp.linspace(0.0, args.t1, args.samples)
    start = time.perf_counter()
    traj = simulate(rod, state0, ts, method=method, throw=False, **solver_options(args))
    ds = _dataset(
        traj,
        rod=spec.describe(),
        initial=initial,
        method=method,
        command="rbo-jax " + " ".join(args.argv),
    )
    elapsed = time.perf_counter() - start
    t, tip = ds["t"].values, ds["tip"].values
    reached = np.all(np.isfinite(ds["centreline"].values), axis=(1, 2))

    def values(i):
        return [float(t[i]), *map(float, tip[i])]

    return finish(args, traj, ds, reached, ["t", "tip x", "tip y", "tip z"], values, elapsed)
