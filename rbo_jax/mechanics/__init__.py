r"""The interface every analysis talks to: :class:`AbstractMechanics`.

A rigid body oscillator, a lattice of them and a rod are three final classes implementing it
(:mod:`rbo_jax.models`); equilibria, spectra, critical loads, Hopf points, continuation, maps,
simulation and fits are each written once against it (STYLE.md, point 20: what
``diffrax.AbstractTerm`` is to ``diffeqsolve``).
"""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._interface": (
            "STRUCTURES",
            "AbstractMechanics",
            "checked_parameters",
            "first_order_field",
            "zero_increments",
        ),
        "._status": ("EquilibriumStatus",),
    },
)
