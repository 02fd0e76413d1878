"""Figures: stability maps, root loci, sweeps, bifurcation diagrams, Hopf boundaries, soft/hard
flutter maps and hysteresis loops, and the
space-time images and dispersion branches of lattices (optional dependency: matplotlib,
``pip install rbo_jax[plot]``). One module per kind of figure; this package re-exports them."""

from ._bifurcation import plot_bifurcation_diagram, plot_hopf_boundary
from ._common import pyplot
from ._flutter import plot_flutter_map, plot_hysteresis
from ._lattice import plot_dispersion, plot_space_time
from ._maps import plot_root_locus, plot_stability_map, plot_sweep

__all__ = [
    "plot_stability_map",
    "plot_root_locus",
    "plot_sweep",
    "plot_bifurcation_diagram",
    "plot_hopf_boundary",
    "plot_flutter_map",
    "plot_hysteresis",
    "plot_space_time",
    "plot_dispersion",
    "pyplot",
]
