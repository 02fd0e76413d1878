"""rbo_jax: differentiable JAX physics of the rigid body oscillator (turn-vector formulation).

Importing the package enables float64 in JAX (see :mod:`rbo_jax._precision` and the README).
"""

import importlib.metadata

from ._precision import enable_float64_by_default as _enable_float64_by_default

_enable_float64_by_default()

from ._precision import float64_enabled as float64_enabled  # noqa: E402
from .analytic import nikolai_bending_roots as nikolai_bending_roots  # noqa: E402
from .analytic import nikolai_bending_roots_small_load as nikolai_bending_roots_small_load  # noqa: E402
from .analytic import nikolai_bending_stiffness as nikolai_bending_stiffness  # noqa: E402
from .analytic import nikolai_equilibrium as nikolai_equilibrium  # noqa: E402
from .analytic import nikolai_spectrum as nikolai_spectrum  # noqa: E402
from .analytic import precession_rate as precession_rate  # noqa: E402
from .analytic import torsion_roots as torsion_roots  # noqa: E402
from .batch import SweepError as SweepError  # noqa: E402
from .batch import critical_load as critical_load  # noqa: E402
from .batch import open_sweep as open_sweep  # noqa: E402
from .batch import stability_map as stability_map  # noqa: E402
from .batch import status_counts as status_counts  # noqa: E402
from .batch import sweep as sweep  # noqa: E402
from .bifurcation import HopfPoint as HopfPoint  # noqa: E402
from .bifurcation import HopfStatus as HopfStatus  # noqa: E402
from .bifurcation import OrbitStatus as OrbitStatus  # noqa: E402
from .bifurcation import PeriodicOrbit as PeriodicOrbit  # noqa: E402
from .bifurcation import continue_equilibria as continue_equilibria  # noqa: E402
from .bifurcation import continue_hopf as continue_hopf  # noqa: E402
from .bifurcation import continue_limit_cycles as continue_limit_cycles  # noqa: E402
from .bifurcation import first_lyapunov_coefficient as first_lyapunov_coefficient  # noqa: E402
from .bifurcation import floquet_multipliers as floquet_multipliers  # noqa: E402
from .bifurcation import hopf_point as hopf_point  # noqa: E402
from .bifurcation import periodic_orbit as periodic_orbit  # noqa: E402
from .ensemble import fast_simulate as fast_simulate  # noqa: E402
from .fitting import FitResult as FitResult  # noqa: E402
from .fitting import TrajectoryData as TrajectoryData  # noqa: E402
from .fitting import fit as fit  # noqa: E402
from .foundations import AbstractFoundation as AbstractFoundation  # noqa: E402
from .foundations import (  # noqa: E402
    AbstractTransverselyIsotropicFoundation as AbstractTransverselyIsotropicFoundation,
)
from .foundations import BarrierFoundation as BarrierFoundation  # noqa: E402
from .foundations import IsotropicFoundation as IsotropicFoundation  # noqa: E402
from .foundations import QuadraticFoundation as QuadraticFoundation  # noqa: E402
from .foundations import SumFoundation as SumFoundation  # noqa: E402
from .foundations import TransverselyIsotropicFoundation as TransverselyIsotropicFoundation  # noqa: E402
from .foundations import body_potential_moment as body_potential_moment  # noqa: E402
from .foundations import potential_moment as potential_moment  # noqa: E402
from .foundations import transverse_coefficients as transverse_coefficients  # noqa: E402
from .inertia import check_inertia as check_inertia  # noqa: E402
from .inertia import principal_inertia as principal_inertia  # noqa: E402
from .inertia import transversely_isotropic_inertia as transversely_isotropic_inertia  # noqa: E402
from .kinematics import Turn as Turn  # noqa: E402
from .kinematics import compose as compose  # noqa: E402
from .kinematics import composition_invariants as composition_invariants  # noqa: E402
from .kinematics import distance_to_singularity as distance_to_singularity  # noqa: E402
from .kinematics import integrating_tensor as integrating_tensor  # noqa: E402
from .kinematics import integrating_tensor_det as integrating_tensor_det  # noqa: E402
from .kinematics import integrating_tensor_inv as integrating_tensor_inv  # noqa: E402
from .kinematics import skew as skew  # noqa: E402
from .kinematics import turn_tensor as turn_tensor  # noqa: E402
from .kinematics import turn_vector as turn_vector  # noqa: E402
from .kinematics import vector_invariant as vector_invariant  # noqa: E402
from .loads import AbstractLoad as AbstractLoad  # noqa: E402
from .loads import CallableLoad as CallableLoad  # noqa: E402
from .loads import DeadMoment as DeadMoment  # noqa: E402
from .loads import FollowerMoment as FollowerMoment  # noqa: E402
from .loads import Friction as Friction  # noqa: E402
from .loads import PotentialLoad as PotentialLoad  # noqa: E402
from .loads import SemiTangentialMoment as SemiTangentialMoment  # noqa: E402
from .loads import as_load as as_load  # noqa: E402
from .maps import EquilibriumStability as EquilibriumStability  # noqa: E402
from .maps import equilibrium_stability as equilibrium_stability  # noqa: E402
from .model import RightForm as RightForm  # noqa: E402
from .model import RigidBodyOscillator as RigidBodyOscillator  # noqa: E402
from .plotting import plot_bifurcation_diagram as plot_bifurcation_diagram  # noqa: E402
from .plotting import plot_hopf_boundary as plot_hopf_boundary  # noqa: E402
from .plotting import plot_sweep as plot_sweep  # noqa: E402
from .precession import RegularPrecession as RegularPrecession  # noqa: E402
from .precession import precession_residual as precession_residual  # noqa: E402
from .precession import precession_spectrum as precession_spectrum  # noqa: E402
from .precession import precession_variational_matrix as precession_variational_matrix  # noqa: E402
from .precession import regular_precession as regular_precession  # noqa: E402
from .problems import nikolai_model as nikolai_model  # noqa: E402
from .simulate import DarbouxSolution as DarbouxSolution  # noqa: E402
from .simulate import SolveStatus as SolveStatus  # noqa: E402
from .simulate import Trajectory as Trajectory  # noqa: E402
from .simulate import simulate as simulate  # noqa: E402
from .simulate import solve_darboux as solve_darboux  # noqa: E402
from .stability import EquilibriumSolution as EquilibriumSolution  # noqa: E402
from .stability import EquilibriumStatus as EquilibriumStatus  # noqa: E402
from .stability import SecondOrderForm as SecondOrderForm  # noqa: E402
from .stability import StabilityKind as StabilityKind  # noqa: E402
from .stability import classify as classify  # noqa: E402
from .stability import equilibrium as equilibrium  # noqa: E402
from .stability import fast_spectrum as fast_spectrum  # noqa: E402
from .stability import linearize as linearize  # noqa: E402
from .stability import second_order_form as second_order_form  # noqa: E402
from .stability import solve_equilibrium as solve_equilibrium  # noqa: E402
from .stability import spectral_abscissa as spectral_abscissa  # noqa: E402
from .stability import spectrum as spectrum  # noqa: E402

__version__ = importlib.metadata.version("rbo_jax")
