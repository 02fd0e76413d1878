"""``pyplot()``: matplotlib, loaded on first use (an optional dependency)."""

from __future__ import annotations

__all__ = ["pyplot"]


def pyplot():
    """``matplotlib.pyplot``, or an ImportError that says how to install it."""
    try:
        import matplotlib.pyplot as plt  # headless machines fall back to the Agg backend
    except ImportError as e:  # pragma: no cover - exercised only without matplotlib
        raise ImportError("rbo_jax.plotting needs matplotlib: pip install 'rbo_jax[plot]'.") from e
    return plt
