r"""Bifurcation analysis of the rigid body oscillator beyond linear stability: Hopf points with
exact derivatives and the first Lyapunov coefficient (:mod:`._hopf`), periodic orbits by
shooting and their Floquet multipliers (:mod:`._orbit`), and continuation: equilibria with
fold, branch-point and Hopf detection (:mod:`._equilibria`), the family of limit cycles born at
a Hopf point (:mod:`._cycles`) and the Hopf boundary in two parameters (:mod:`._curve`)."""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._hopf": ("HopfPoint", "HopfStatus", "first_lyapunov_coefficient", "hopf_point"),
        "._orbit": ("OrbitStatus", "PeriodicOrbit", "floquet_multipliers", "periodic_orbit"),
        "._equilibria": ("continue_equilibria",),
        "._cycles": ("continue_limit_cycles",),
        "._curve": ("continue_hopf",),
    },
)
