"""The status of an equilibrium solve, for every model."""

from __future__ import annotations

import equinox as eqx

__all__ = ["EquilibriumStatus"]


class EquilibriumStatus(eqx.Enumeration):
    """Outcome of :func:`rbo_jax.solve_equilibrium` (any model)."""

    successful = ""
    not_converged = (
        "Newton's method did not converge to an equilibrium (zero total moment and force, eq. "
        "4.61): start from another guess, take more load steps (steps=...) or raise max_steps."
    )
    singular_point = (
        "The equilibrium search reached a singular point |theta| = 2*pi*k of the integrating "
        "tensor Z (eq. 4.11)."
    )
    domain_error = "The equilibrium search left the domain of the foundation energy (eq. 4.49)."
    nonfinite = (
        "The equilibrium search produced a non-finite configuration, step or residual (a "
        "singular stiffness: the system may be at a buckling load, or a parameter is not "
        "finite)."
    )
    invalid_parameters = (
        "A model parameter is invalid (built from traced values its constructors could not "
        "check); the model's parameter_status() names it."
    )
