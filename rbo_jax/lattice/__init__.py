r"""Lattices of rigid body oscillators: chains and grids of coupled bodies (media whose every
point is a rigid body: Cosserat continua, liquid crystals, Kelvin's medium).

Bodies on the sites, each a :class:`rbo_jax.RigidBodyOscillator`, neighbours coupled by an
energy of their relative turn (:mod:`rbo_jax.models.lattice`); every body obeys the right form
(4.55)–(4.56) with the gradient of the total energy. Simulation on the lattice DOP853
(:mod:`._integrate`), diffrax, or a symplectic Lie-group splitting (:mod:`._splitting`,
:mod:`._simulate`); linear waves by the Bloch matrix (:mod:`._dispersion`); nonlinear waves
(:mod:`._waves`); fits of stiffnesses to fields and dispersion curves (:mod:`._fit`).

Bodies that also translate: rods and chains of links (:mod:`rbo_jax.models.rod`: Cosserat rods,
Beck's, Ziegler's and Pflüger's columns, their strains and forces); :func:`simulate` takes a rod
and its state too; fits to measured eigenvalues and trajectories (:func:`fit_spectrum`,
:func:`fit_trajectory`). A lattice and a rod have the analyses of every model
(:func:`rbo_jax.solve_equilibrium`, :func:`rbo_jax.spectrum`, :func:`rbo_jax.hopf_point`,
:func:`rbo_jax.continue_equilibria`, ...); the rods' names of them stay here (:mod:`._aliases`,
:mod:`._rod_continuation`).
"""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "..models.lattice": (
            "Lattice",
            "chain",
            "grid",
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
        "._fit": (
            "LatticeFit",
            "RodFit",
            "RodSpectrumData",
            "RodTrajectoryData",
            "fit_dispersion",
            "fit_field",
            "fit_spectrum",
            "fit_trajectory",
        ),
        "..models.rod": (
            "DistributedForce",
            "FrictionalPlane",
            "Gravity",
            "MuscleTorques",
            "RestCurvature",
            "Rod",
            "RodState",
            "TipForce",
            "TipMoment",
            "circular_rod",
            "pendulum",
            "rod",
        ),
        "..stability": ("linearize", "solve_equilibrium"),
        "._aliases": (
            "RodEquilibrium",
            "RodEquilibriumStatus",
            "RodHopfPoint",
            "critical_load",
            "equilibrium",
            "rod_continue_hopf",
            "rod_hopf_point",
            "spectrum",
        ),
        "._rod_dynamics": ("RodTrajectory",),
        "._rod_continuation": ("RodBranch", "continue_equilibrium"),
    },
)
