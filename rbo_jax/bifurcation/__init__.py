r"""Bifurcation analysis of the rigid body oscillator beyond linear stability: Hopf points with
exact derivatives and the first Lyapunov coefficient (:mod:`._hopf`), periodic orbits by
shooting and their Floquet multipliers (:mod:`._orbit`), and continuation: equilibria with
fold, branch-point and Hopf detection (:mod:`._equilibria`), the family of limit cycles born at
a Hopf point (:mod:`._cycles`) and the Hopf boundary in two parameters (:mod:`._curve`)."""

from ._curve import continue_hopf
from ._cycles import continue_limit_cycles
from ._equilibria import continue_equilibria
from ._hopf import HopfPoint, HopfStatus, first_lyapunov_coefficient, hopf_point
from ._orbit import OrbitStatus, PeriodicOrbit, floquet_multipliers, periodic_orbit

__all__ = ["HopfPoint", "HopfStatus", "first_lyapunov_coefficient", "hopf_point", "OrbitStatus",
           "PeriodicOrbit", "floquet_multipliers", "periodic_orbit", "continue_equilibria",
           "continue_limit_cycles", "continue_hopf"]
