"""The names of a stability map's point, from :mod:`rbo_jax.stability` (kept for code that
imports them from here)."""

from .stability import (
    STABILITY_KIND_NAMES,
    EquilibriumStability,
    critical_value,
    equilibrium_stability,
    is_unstable,
)

__all__ = [
    "STABILITY_KIND_NAMES",
    "EquilibriumStability",
    "critical_value",
    "equilibrium_stability",
    "is_unstable",
]
