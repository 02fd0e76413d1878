"""rbo_jax: differentiable JAX physics of the rigid body oscillator (turn-vector formulation).

Importing the package enables float64 in JAX (see :mod:`rbo_jax._precision` and the README) and,
before JAX's backend starts, asks for one CPU device per core the process may use, so that batch
work uses the whole machine (:mod:`rbo_jax._devices`; ``RBO_JAX_CPU_DEVICES=off`` to opt out).
The names below load on first use (:mod:`rbo_jax._lazy`): ``import rbo_jax`` imports JAX, not
equinox, diffrax, optimistix, optax, xarray or zarr, which the layers that need them import when
one of their names is first used.
"""

from . import _lazy
from ._cache import enable_from_environment as _enable_cache_from_environment
from ._devices import use_every_core as _use_every_core
from ._precision import enable_float64_by_default as _enable_float64_by_default
from ._version import __version__ as __version__  # the one place it is written

_enable_float64_by_default()
_use_every_core()  # one CPU device per core, unless the user chose or JAX has started
_enable_cache_from_environment()  # $RBO_JAX_COMPILATION_CACHE (rbo_jax.enable_compilation_cache)

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {
        "._precision": ("float64_enabled",),
        "._cache": ("enable_compilation_cache",),
        ".kinematics": (
            "Turn",
            "compose",
            "composition_invariants",
            "distance_to_singularity",
            "integrating_tensor",
            "integrating_tensor_det",
            "integrating_tensor_inv",
            "skew",
            "turn_tensor",
            "turn_vector",
            "vector_invariant",
        ),
        ".inertia": ("check_inertia", "principal_inertia", "transversely_isotropic_inertia"),
        ".analytic": (
            "nikolai_bending_roots",
            "nikolai_bending_roots_small_load",
            "nikolai_bending_stiffness",
            "nikolai_equilibrium",
            "nikolai_spectrum",
            "precession_rate",
            "torsion_roots",
        ),
        ".foundations": (
            "AbstractFoundation",
            "AbstractTransverselyIsotropicFoundation",
            "BarrierFoundation",
            "CosineFoundation",
            "IsotropicFoundation",
            "QuadraticFoundation",
            "SumFoundation",
            "TransverselyIsotropicFoundation",
            "ZeroFoundation",
            "body_potential_moment",
            "potential_moment",
            "transverse_coefficients",
        ),
        ".loads": (
            "AbstractLoad",
            "CallableLoad",
            "DeadMoment",
            "FollowerMoment",
            "Friction",
            "PotentialLoad",
            "SemiTangentialMoment",
            "as_load",
        ),
        ".mechanics": ("AbstractMechanics",),
        ".models.rigid_body": ("RightForm", "RigidBodyOscillator"),
        ".problems": ("nikolai_model",),
        ".trajectory": ("SolveStatus", "Trajectory"),
        ".simulate": ("DarbouxSolution", "solve_darboux"),
        ".motion": ("simulate",),
        ".ensemble": ("fast_simulate",),
        ".stability": (
            "EquilibriumSolution",
            "EquilibriumStatus",
            "SecondOrderForm",
            "StabilityKind",
            "classify",
            "equilibrium",
            "fast_spectrum",
            "linearize",
            "second_order_form",
            "solve_equilibrium",
            "spectral_abscissa",
            "spectrum",
            "EquilibriumStability",
            "equilibrium_stability",
        ),
        ".precession": (
            "RegularPrecession",
            "precession_residual",
            "precession_spectrum",
            "precession_variational_matrix",
            "regular_precession",
        ),
        ".fitting": (
            "FitResult",
            "TrajectoryData",
            "fit",
            "posterior",
            "profile_likelihood",
            "synthetic_sensor_data",
        ),
        ".bifurcation": (
            "BautinPoint",
            "BautinStatus",
            "FoldOfCycles",
            "HopfPoint",
            "HopfStatus",
            "OrbitStatus",
            "PeriodicOrbit",
            "continue_equilibria",
            "continue_hopf",
            "continue_limit_cycles",
            "first_lyapunov_coefficient",
            "bautin_point",
            "floquet_multipliers",
            "flutter_map",
            "fold_of_cycles",
            "hopf_point",
            "hysteresis_loop",
            "is_conservative",
            "periodic_orbit",
            "second_lyapunov_coefficient",
        ),
        ".batch": (
            "SweepError",
            "critical_load",
            "open_sweep",
            "stability_map",
            "status_counts",
            "sweep",
        ),
        ".plotting": (
            "plot_bifurcation_diagram",
            "plot_dispersion",
            "plot_flutter_map",
            "plot_hopf_boundary",
            "plot_hysteresis",
            "plot_space_time",
            "plot_sweep",
        ),
    },
)
