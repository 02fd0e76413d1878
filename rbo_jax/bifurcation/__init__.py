r"""Bifurcation analysis of the rigid body oscillator beyond linear stability: Hopf points with
exact derivatives and the first Lyapunov coefficient (:mod:`._hopf`), periodic orbits by
shooting and their Floquet multipliers (:mod:`._orbit`), and continuation: equilibria with
fold, branch-point and Hopf detection (:mod:`._equilibria`), the family of limit cycles born at
a Hopf point with its folds, period doublings and Neimark-Sacker points (:mod:`._cycles`,
:mod:`._cycle_fold`, :mod:`._cycle_special`), the Hopf boundary in two parameters
(:mod:`._curve`, :mod:`._hopf_curve`), and generalized Hopf (Bautin) points with the second
Lyapunov coefficient (:mod:`._bautin`, :mod:`._normal_form`); soft/hard flutter maps and
hysteresis loops (:mod:`._flutter`)."""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._hopf": ("HopfPoint", "HopfStatus", "first_lyapunov_coefficient", "hopf_point"),
        "._orbit": (
            "OrbitStatus",
            "PeriodicOrbit",
            "floquet_multipliers",
            "is_conservative",
            "periodic_orbit",
        ),
        "._equilibria": ("continue_equilibria",),
        "._cycles": ("continue_limit_cycles",),
        "._cycle_fold": ("FoldOfCycles", "fold_of_cycles"),
        "._curve": ("continue_hopf",),
        "._bautin": ("BautinPoint", "BautinStatus", "bautin_point"),
        "._normal_form": ("second_lyapunov_coefficient",),
        "._flutter": ("flutter_map", "hysteresis_loop"),
    },
)
