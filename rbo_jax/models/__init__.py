r"""The models: final classes implementing :class:`rbo_jax.mechanics.AbstractMechanics`.

- :mod:`.rigid_body`: :class:`rbo_jax.RigidBodyOscillator`, one body on a foundation (4.55)–(4.56);
- :mod:`.lattice`: :class:`rbo_jax.lattice.Lattice`, bodies coupled through their relative turns;
- :mod:`.rod`: :class:`rbo_jax.lattice.Rod`, bodies that turn and translate (Cosserat rods,
  Beck's, Ziegler's and Pflüger's columns).
"""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        ".rigid_body": ("LeftForm", "RightForm", "RigidBodyOscillator"),
        ".lattice": ("Lattice", "chain", "grid"),
        ".rod": ("Rod", "RodState", "circular_rod", "pendulum", "rod"),
    },
)
