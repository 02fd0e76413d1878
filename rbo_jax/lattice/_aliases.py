"""The rods' names of the analyses that every model now shares (kept: code outside this
repository uses them): a rod's equilibrium is :func:`rbo_jax.solve_equilibrium`'s, its flutter
point :func:`rbo_jax.hopf_point`'s, with the same results and statuses."""

from __future__ import annotations

from ..bifurcation import HopfPoint, continue_hopf, hopf_point
from ..stability import (
    EquilibriumSolution,
    EquilibriumStatus,
    checked_spectrum,
    critical_load_along,
    raising_equilibrium,
)

RodEquilibrium = EquilibriumSolution
RodEquilibriumStatus = EquilibriumStatus
RodHopfPoint = HopfPoint
critical_load = critical_load_along
rod_hopf_point = hopf_point
rod_continue_hopf = continue_hopf


def equilibrium(model, guess=None, **kwargs):
    """:func:`rbo_jax.equilibrium` (its errors say ``lattice.equilibrium``)."""
    return raising_equilibrium(model, guess, "lattice.equilibrium", **kwargs)


def spectrum(model, state=None, **kwargs):
    """:func:`rbo_jax.spectrum` (its errors say ``lattice.spectrum``)."""
    return checked_spectrum(model, state, "lattice.spectrum", **kwargs)
