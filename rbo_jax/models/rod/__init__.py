r"""Rods and chains of links: bodies that turn **and translate** (:class:`Rod`), their state
(:class:`RodState`), loads (:mod:`._loads`), strains, energies and forces (:mod:`._field`), and
their builders (:mod:`._builders`). The public names are :mod:`rbo_jax.lattice`'s."""

from ... import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use; in the order they import each other
        "._state": ("RodState",),
        "._loads": ("DistributedForce", "Gravity", "Motion", "TipForce", "TipMoment"),
        "._actuation": ("FrictionalPlane", "MuscleTorques", "RestCurvature"),
        "._field": (
            "attached",
            "body_forces",
            "composed",
            "coupling_energy",
            "energy",
            "first_order",
            "forces_at",
            "forces_tangent",
            "free_increments",
            "free_index",
            "kinetic_energy",
            "kinetic_moment",
            "log_unit",
            "matrix_of",
            "potential_energy",
            "rates",
            "rest_turns",
            "static_residual",
            "strains",
            "tensors",
        ),
        "._rod": ("BASES", "Rod"),
        "._builders": ("circular_rod", "pendulum", "rod"),
    },
)
