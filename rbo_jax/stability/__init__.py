r"""Equilibria, linearisation, spectra and their classification, for every model: sections
4.2.4, 4.4 and 4.7 of the paper (:mod:`._equilibrium`, :mod:`._linearize`, :mod:`._classify`),
and what a stability map computes at one point (:mod:`._point`)."""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "..mechanics": ("EquilibriumStatus",),  # the statuses of every model's equilibrium
        "._equilibrium": (
            "EquilibriumSolution",
            "equilibrium",
            "newton_equilibrium",
            "raising_equilibrium",
            "solve_equilibrium",
        ),
        "._linearize": (
            "SecondOrderForm",
            "checked_spectrum",
            "eigenvalues",
            "fast_spectrum",
            "linearize",
            "second_order_form",
            "spectrum",
        ),
        "._classify": (
            "StabilityKind",
            "classify",
            "is_unstable",
            "spectral_abscissa",
            "unstable_oscillatory",
            "unstable_roots",
        ),
        "._critical": (
            "critical_between",
            "critical_load_along",
            "critical_search",
            "stability_code",
        ),
        "._point": (
            "STABILITY_KIND_NAMES",
            "EquilibriumStability",
            "critical_value",
            "equilibrium_stability",
        ),
    },
)
