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
from ..model import RigidBodyOscillator

__all__ = [
    "Outcome",
    "abstract_model",
    "check_model_fn",
    "check_params",
    "check_theta_eq_fn",
    "model_solver",
    "theta_guess_vector",
]


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


def model_solver(model_fn, point: Mapping, name: str):
    """The model's own solver ``name``, or ``None`` for a rigid body oscillator.

    The protocol by which models of higher layers (a :class:`rbo_jax.lattice.Rod`) go through
    :func:`rbo_jax.hopf_point` and :func:`rbo_jax.continue_hopf` without this package importing
    them: ``model_fn(**point)`` is traced once abstractly (:func:`equinox.filter_eval_shape`,
    every value a float array of its shape), and where the model's class defines the static
    method ``name`` (``rbo_hopf_point``, ``rbo_continue_hopf``) the call is handed to it with
    the same arguments. A model function that cannot be traced so is left to the rigid body's
    solver, which reports its own error.
    """
    model = abstract_model(model_fn, {str(k): np.shape(v) for k, v in point.items()})
    if model is None or isinstance(model, RigidBodyOscillator):
        return None
    return getattr(type(model), name, None)


def abstract_model(model_fn, shapes: Mapping):
    """``model_fn(**point)`` traced abstractly (:func:`equinox.filter_eval_shape`), every value
    a float array of the shape in ``shapes``; ``None`` where it cannot be traced so (the rigid
    body's solvers then call it concretely and report its own error)."""
    try:
        zeros = {k: np.zeros(shape) for k, shape in shapes.items()}
        return eqx.filter_eval_shape(lambda p: model_fn(**p), zeros)
    except Exception:  # noqa: BLE001 - any error of the user's function: reported by that path
        return None
