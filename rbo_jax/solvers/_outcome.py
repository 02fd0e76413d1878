"""The base of every solve's result: a ``status`` and whether it is successful."""

from __future__ import annotations

from typing import Any

import equinox as eqx

from .. import _enumeration as enum

__all__ = ["Outcome"]


class Outcome(eqx.Module):
    """A solver's result whose ``status`` is an item of an :class:`equinox.Enumeration` with an
    item ``successful``."""

    status: eqx.AbstractVar[Any]

    @property
    def ok(self):
        """Whether the solve succeeded (``status == successful``; batched like the status)."""
        return self.status == enum.enumeration_of(self.status).successful
