r"""Lattices of rigid body oscillators: the model (:class:`Lattice`, :func:`chain`,
:func:`grid`) and its energies, moments and equations of motion (:mod:`._field`). The public
names are :mod:`rbo_jax.lattice`'s."""

from ... import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._lattice": ("Lattice", "chain", "grid"),
        "._field": (
            "body_moments",
            "chain_moments",
            "coupling_energy",
            "coupling_moments",
            "energy_gradient",
            "kinetic_moment",
            "rates",
            "relative_turns",
            "right_forms",
            "site_energy",
            "total_energy",
        ),
    },
)
