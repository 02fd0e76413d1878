"""``rbo-jax simulate --lattice SPEC``: a chain or grid of copies of the body the model options
describe (:mod:`rbo_jax.lattice`), as a table and a dataset.

The options of the ``lattice`` group (``options.toml``) default to None here, so that one given
without ``--lattice`` is refused; :data:`DEFAULTS` fills them in. Everything is checked before
anything is compiled: the lattice (:class:`~rbo_jax.app.spec.LatticeSpec`), the initial wave
against the foundation and the topology, the method against the loads.
"""

from __future__ import annotations

import argparse
import math
import time

from .._io import DATASET_SUFFIXES
from .._reader import SpecError
from ..spec import LatticeSpec, ModelSpec
from ._common import Failure, check_suffix, flag, refuse_group, settings
from ._memory import BYTES_PER_BODY, BYTES_PER_BODY_SAMPLE, check_memory
from ._samples import finish, initial_state, solver_options

DEFAULTS = {
    "coupling_kb": 1.0,
    "coupling_kt": 1.0,
    "wave": "perturbed",
    "perturbation": 1e-3,
    "seed": 0,
    "wave_speed": 0.0,
    "winding": 1,
    "method": "dop853",
    "dt": None,
}
_WAVE_OPTIONS = {
    "perturbation": "perturbed",
    "seed": "perturbed",
    "wave_speed": "kink",
    "winding": "twist",
}
_KAPPA = {"[lattice] kappa_b": "--coupling-kb", "[lattice] kappa_t": "--coupling-kt"}


def refuse_lattice_options(args: argparse.Namespace) -> None:
    """One body (no ``--lattice``): none of the lattice options may be given."""
    refuse_group(args, DEFAULTS, "--lattice", "a chain or grid of bodies", "--lattice chain:32")


def _settings(args: argparse.Namespace) -> argparse.Namespace:
    """The lattice options with their defaults, checked on their own."""
    s = settings(args, DEFAULTS)
    for dest, wave in _WAVE_OPTIONS.items():
        if getattr(args, dest) is not None and s.wave != wave:
            raise Failure(f"{flag(dest)} belongs to --wave {wave}, not --wave {s.wave}.")
    if s.method == "splitting" and s.dt is None:
        raise Failure("--method splitting needs --dt, its fixed step (e.g. --dt 0.01).")
    if s.method != "splitting" and s.dt is not None:
        raise Failure(
            f"--dt is the step of --method splitting; --method {s.method} chooses its "
            f"steps by --rtol and --atol."
        )
    if s.dt is not None and not (s.dt > 0 and math.isfinite(s.dt)):
        raise Failure(f"--dt must be > 0 and finite, got {s.dt:g}.")
    if not (s.perturbation >= 0 and math.isfinite(s.perturbation)):
        raise Failure(f"--perturbation must be >= 0 and finite, got {s.perturbation:g}.")
    if not math.isfinite(s.wave_speed):
        raise Failure(f"--wave-speed must be finite, got {s.wave_speed:g}.")
    if s.seed < 0:
        raise Failure(f"--seed must be >= 0, got {s.seed}.")
    if args.progress:
        raise Failure(
            "--progress is for one body (--integrator simulate); a lattice has no progress bar."
        )
    if args.integrator != "fast_simulate":
        raise Failure(
            "--integrator is for one body; choose the lattice's integrator with "
            "--method dop853|diffrax|splitting."
        )
    if args.out is not None:
        check_suffix(args.out, DATASET_SUFFIXES, "--out")  # no CSV of a lattice
    return s


def _lattice_spec(args, s) -> LatticeSpec:
    try:
        tbl = LatticeSpec.table_from_text(args.lattice)
    except ValueError as e:
        raise Failure(f"--lattice {args.lattice}: {e}.") from None
    tbl |= {"kappa_b": s.coupling_kb, "kappa_t": s.coupling_kt}
    try:
        return LatticeSpec.from_mapping(tbl)
    except SpecError as e:
        if e.where in _KAPPA:
            raise Failure(f"{_KAPPA[e.where]}: {e.message}") from None
        need = (
            "a chain needs N >= 2 bodies"
            if tbl["kind"] == "chain"
            else "a grid needs at least 2 sites along each axis"
        )
        raise Failure(f"--lattice {args.lattice}: {need}.") from None


def _axial_inertia(spec: ModelSpec, k) -> float:
    """k.A.k, the moment of inertia about the axis (plain numbers)."""
    if spec.inertia.type == "principal":
        return float(sum(m * x * x for m, x in zip(spec.inertia.value("moments"), k)))
    return float(spec.inertia.value("A3"))


def _check_wave(args, s, spec: ModelSpec, lattice: LatticeSpec, k) -> None:
    """The initial wave against the options, the foundation and the topology."""
    if s.method == "splitting" and spec.loads:
        raise Failure(
            "--method splitting integrates lattices without loads (its kicks are the "
            "gradient of the foundations and couplings); drop --follower, --dead and "
            "--friction, or use --method dop853 or diffrax."
        )
    if s.wave == "perturbed":
        return
    if args.about_equilibrium:
        raise Failure(
            f"--about-equilibrium belongs to --wave perturbed; --wave {s.wave} sets "
            f"the initial state itself."
        )
    if any(args.theta0):
        raise Failure(
            f"--theta0 belongs to --wave perturbed; --wave {s.wave} sets the turn-vectors itself."
        )
    if lattice.kind != "chain" or (s.wave == "twist" and not lattice.periodic):
        raise Failure(
            f"--wave {s.wave} needs a {'periodic ' if s.wave == 'twist' else ''}chain "
            f"(--lattice chain:N{'' if s.wave == 'twist' else '[:free]'}), got "
            f"--lattice {args.lattice}."
        )
    if s.wave == "twist":
        spin = sum(a * b for a, b in zip(args.Omega0, k))
        if max(abs(a - spin * b) for a, b in zip(args.Omega0, k)) > 1e-12 * (1 + abs(spin)):
            raise Failure(
                "--wave twist spins every body about the axis k: --Omega0 must be "
                "parallel to --axis (or zero)."
            )
        return
    if args.foundation != "cosine" or not args.c > 0:
        raise Failure(
            "--wave kink needs --foundation cosine with --c > 0: the sine-Gordon "
            "kink of U = c (1 - cos|theta|) (rbo_jax.lattice.kink)."
        )
    if any(args.Omega0):
        raise Failure(
            "--Omega0 belongs to --wave perturbed and twist; the kink's velocities "
            "follow from --wave-speed."
        )
    sound = math.sqrt(s.coupling_kt / _axial_inertia(spec, k))
    if not abs(s.wave_speed) < sound:
        raise Failure(
            f"--wave-speed must be below the speed of sound sqrt(kappa_t/A3) = "
            f"{sound:g} sites per unit time, got {s.wave_speed:g}."
        )


def _initial_states(args, s, spec: ModelSpec, lattice: LatticeSpec, model, k):
    """``(theta0, Omega0)`` of every body, ``(N, 3)``, and a line describing them."""
    import numpy as np

    from ...lattice import kink, twist

    n = math.prod(lattice.shape)
    if s.wave == "kink":
        return kink(
            n, args.c, s.coupling_kt, _axial_inertia(spec, k), x0=(n - 1) / 2, v=s.wave_speed, k=k
        ), f"kink at site {(n - 1) / 2:g}, v = {s.wave_speed:g}"
    if s.wave == "twist":
        spin = float(np.dot(args.Omega0, k))
        return twist(n, s.winding, spin, k=k), f"twist, winding {s.winding}, spin {spin:g}"
    theta0, Omega0 = initial_state(args, model)
    rng = np.random.default_rng(s.seed)
    noise = s.perturbation * rng.standard_normal((2, n, 3))
    states = (np.asarray(theta0) + noise[0], np.asarray(Omega0) + noise[1])
    return states, (
        f"perturbed: theta0 = {np.asarray(theta0).tolist()}, Omega0 = "
        f"{np.asarray(Omega0).tolist()}, perturbation {s.perturbation:g} "
        f"(seed {s.seed})"
    )


def simulate_lattice(args: argparse.Namespace, spec: ModelSpec) -> int:
    """``rbo-jax simulate --lattice SPEC``: the motion of a lattice of the model's bodies."""
    import jax.numpy as jnp
    import numpy as np

    from ...lattice import simulate

    s = _settings(args)
    lattice = _lattice_spec(args, s)
    bodies = math.prod(lattice.shape)
    check_memory(
        bodies * (BYTES_PER_BODY + args.samples * BYTES_PER_BODY_SAMPLE),
        f"--lattice {args.lattice} ({bodies:,} bodies) with --samples {args.samples}",
        "give fewer bodies (--lattice) or fewer samples (--samples)",
    )
    k = np.asarray(spec.axis, dtype=float)
    k = k / np.linalg.norm(k)
    _check_wave(args, s, spec, lattice, k)
    lat = lattice.build(spec)
    print(
        f"Lattice of rigid body oscillators (rbo_jax.lattice): {lattice.describe()}; every "
        f"body: {spec.describe()}"
    )
    (theta0, Omega0), initial = _initial_states(args, s, spec, lattice, lat.body, k)
    print(f"initial state: {initial}; method {s.method}")
    ts = jnp.linspace(0.0, args.t1, args.samples)
    start = time.perf_counter()
    try:
        traj = simulate(
            lat, theta0, Omega0, ts, method=s.method, dt=s.dt, throw=False, **solver_options(args)
        )
    except ValueError as e:  # the library's checks of what the options above did not cover
        raise Failure(f"--lattice {args.lattice}: {e}") from None
    ds = traj.to_xarray(
        model=spec.describe(),
        lattice=lattice.describe(),
        wave=initial,
        method=s.method,
        command="rbo-jax " + " ".join(args.argv),
    )
    elapsed = time.perf_counter() - start
    t, theta = ds["t"].values, ds["theta"].values
    reached = np.all(np.isfinite(theta), axis=(1, 2))
    largest = np.max(np.linalg.norm(theta, axis=2), axis=1)

    def values(i):
        return [float(t[i]), float(largest[i])]

    recentred = f"{int(traj.num_recentred)} turn-vectors re-centred, "
    return finish(args, traj, ds, reached, ["t", "max |theta_i|"], values, elapsed, recentred)
