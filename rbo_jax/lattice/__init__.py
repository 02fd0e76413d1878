r"""Lattices of rigid body oscillators: chains and grids of coupled bodies (media whose every
point is a rigid body: Cosserat continua, liquid crystals, Kelvin's medium).

Bodies on the sites, each a :class:`rbo_jax.RigidBodyOscillator`, neighbours coupled by an
energy of their relative turn (:mod:`._lattice`); every body obeys the right form
(4.55)–(4.56) with the gradient of the total energy (:mod:`._field`). Simulation on the lattice
DOP853 (:mod:`._integrate`), diffrax, or a symplectic Lie-group splitting (:mod:`._splitting`,
:mod:`._simulate`); linear waves by the Bloch matrix (:mod:`._dispersion`); nonlinear waves
(:mod:`._waves`); fits of stiffnesses to fields and dispersion curves (:mod:`._fit`).

Bodies that also translate: rods and chains of links (:mod:`._rod`: Cosserat rods, Beck's,
Ziegler's and Pflüger's columns), their strains and forces (:mod:`._rod_field`), equilibria by
Newton with block-tridiagonal solves (:mod:`._rod_statics`, :mod:`._banded`), spectra, critical
loads and motion (:mod:`._rod_dynamics`), continuation through limit points
(:mod:`._rod_continuation`), flutter points and boundaries (:mod:`._rod_hopf`,
:mod:`._rod_hopf_system`, :mod:`._rod_hopf_curve`), fits to measured eigenvalues
and trajectories (:mod:`._rod_fit`); :func:`simulate` takes a rod and its state too.
"""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._lattice": ("Lattice", "chain", "grid"),
        "._field": (
            "body_moments",
            "coupling_energy",
            "coupling_moments",
            "energy_gradient",
            "kinetic_moment",
            "relative_turns",
            "total_energy",
        ),
        "._simulate": ("simulate",),
        "._trajectory": ("LatticeTrajectory",),
        "._dispersion": (
            "bloch_blocks",
            "bloch_matrix",
            "dispersion",
            "group_velocity",
            "uniform_equilibrium",
        ),
        "._waves": ("breather", "kink", "twist"),
        "._fit": ("LatticeFit", "fit_dispersion", "fit_field"),
        "._rod": ("Rod", "RodState", "circular_rod", "pendulum", "rod"),
        "._rod_loads": ("DistributedForce", "Gravity", "TipForce", "TipMoment"),
        "._rod_statics": (
            "RodEquilibrium",
            "RodEquilibriumStatus",
            "equilibrium",
            "solve_equilibrium",
        ),
        "._rod_dynamics": ("RodTrajectory", "critical_load", "linearize", "spectrum"),
        "._rod_continuation": ("RodBranch", "continue_equilibrium"),
        "._rod_fit": ("RodFit", "fit_spectrum", "fit_trajectory"),
        "._rod_hopf": ("RodHopfPoint", "rod_hopf_point"),
        "._rod_hopf_curve": ("rod_continue_hopf",),
    },
)
