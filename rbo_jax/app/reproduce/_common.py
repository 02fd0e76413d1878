"""What the reproduction checks share: :class:`Check`, the axis, tolerances and figure saving."""

from __future__ import annotations

import dataclasses
import os

import jax.numpy as jnp
import numpy as np

from .._outputs import save_figure

K = jnp.array([0.0, 0.0, 1.0])
TIGHT = dict(rtol=1e-12, atol=1e-12)


@dataclasses.dataclass
class Check:
    """One comparison of a computed quantity with the paper's value or closed form; passes when
    ``error <= tolerance`` (and the error is finite)."""

    section: str
    quantity: str
    paper: str
    ours: str
    error: float
    tolerance: float

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.error) and self.error <= self.tolerance)


def fmt(x) -> str:
    return f"{x:.6g}" if isinstance(x, (float, np.floating)) else str(x)


def save(plt, fig, out: str, name: str):
    """Write a figure into the report's folder, whole or not at all."""
    save_figure(fig, os.path.join(out, name), dpi=110, bbox_inches="tight")
    plt.close(fig)
