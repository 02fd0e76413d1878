r"""Bifurcation analysis beyond linear stability, for every model: flutter points (Hopf
crossings and Krein collisions) with exact derivatives and the first Lyapunov coefficient
(:mod:`._hopf`, :mod:`._hopf_system`), the flutter boundary in two parameters, natural and by
pseudo-arclength (:mod:`._curve`, :mod:`._hopf_curve`), generalized Hopf (Bautin) points with
the second Lyapunov coefficient (:mod:`._bautin`, :mod:`._normal_form`), branches of equilibria
with their special points (:mod:`._branch`); for one body, periodic orbits by shooting and
their Floquet multipliers (:mod:`._orbit`), the family of limit cycles born at a Hopf point
with its folds, period doublings and Neimark-Sacker points (:mod:`._cycles`,
:mod:`._cycle_fold`, :mod:`._cycle_special`), soft/hard flutter maps and hysteresis loops
(:mod:`._flutter`)."""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._hopf_system": ("HopfStatus",),
        "._hopf": ("HopfPoint", "first_lyapunov_coefficient", "hopf_point"),
        "._orbit": (
            "OrbitStatus",
            "PeriodicOrbit",
            "floquet_multipliers",
            "is_conservative",
            "periodic_orbit",
        ),
        "._branch": ("continue_equilibria",),
        "._cycles": ("continue_limit_cycles",),
        "._cycle_fold": ("FoldOfCycles", "fold_of_cycles"),
        "._curve": ("continue_hopf",),
        "._bautin": ("BautinPoint", "BautinStatus", "bautin_point"),
        "._normal_form": ("second_lyapunov_coefficient",),
        "._flutter": ("flutter_map", "hysteresis_loop"),
    },
)
