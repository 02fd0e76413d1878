"""What the rigid body's periodic-orbit tools share: the model of a point of parameters."""

from __future__ import annotations

from ..models.rigid_body import RigidBodyOscillator

__all__ = ["rigid_model", "with_value"]


def with_value(others: dict, parameter: str, value) -> dict:
    """The parameters ``others`` with ``parameter`` set to ``value``."""
    return {**others, parameter: value}


def rigid_model(model_fn, point) -> RigidBodyOscillator:
    """``model_fn(**point)``, which must be a rigid body oscillator (the periodic orbits,
    limit cycles and their folds integrate one body by :func:`rbo_jax.fast_simulate`)."""
    model = model_fn(**point)
    if not isinstance(model, RigidBodyOscillator):
        raise TypeError(
            "model_fn must return a RigidBodyOscillator here (periodic orbits and limit cycles "
            f"are integrated for one body), got {type(model).__name__}."
        )
    return model
