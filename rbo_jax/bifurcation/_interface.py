"""What the solvers of this package share at their edges: the checks of the arguments they take
alike (a model function, its parameters, an equilibrium and its guess) and the base of their
results, which carry a status."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import equinox as eqx
import numpy as np

from .. import _enumeration as enum
from ..kinematics import _as_vector

__all__ = ["Outcome", "check_model_fn", "check_params", "check_theta_eq_fn", "theta_guess_vector"]


class Outcome(eqx.Module):
    """A solver's result whose ``status`` is an item of an :class:`equinox.Enumeration` with an
    item ``successful``."""

    status: eqx.AbstractVar[Any]

    @property
    def ok(self):
        """Whether the solve succeeded (``status == successful``; batched like the status)."""
        return self.status == enum.enumeration_of(self.status).successful


def check_model_fn(model_fn) -> None:
    """Raise where ``model_fn`` is not callable."""
    if not callable(model_fn):
        raise TypeError("model_fn must be a callable model_fn(**params) -> RigidBodyOscillator.")


def check_theta_eq_fn(theta_eq_fn) -> None:
    """Raise where ``theta_eq_fn`` is given and not callable."""
    if theta_eq_fn is not None and not callable(theta_eq_fn):
        raise TypeError("theta_eq_fn must be a callable theta_eq_fn(**params) -> theta.")


def check_params(params) -> None:
    """Raise where ``params`` is not a mapping ``{name: value}``."""
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping {{name: value}}, got {type(params).__name__}.")


def theta_guess_vector(theta_guess, dtype):
    """The equilibrium guess as a (3,) vector (``None``: zero)."""
    return np.zeros(3, dtype) if theta_guess is None else _as_vector(theta_guess, "theta_guess")
