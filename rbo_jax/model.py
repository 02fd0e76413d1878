"""The rigid body oscillator's module before the models had a folder of their own: its names,
from :mod:`rbo_jax.models.rigid_body` (kept for code that imports them from here)."""

from .models.rigid_body import LeftForm, RightForm, RigidBodyOscillator, inverse3

__all__ = ["LeftForm", "RightForm", "RigidBodyOscillator", "inverse3"]
