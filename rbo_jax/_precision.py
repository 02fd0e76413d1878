"""Float64 by default.

JAX computes in float32 unless ``jax_enable_x64`` is set. The rigid body oscillator is integrated
with tolerances (rtol 1e-8 to 1e-12) far below float32's eps (1.2e-7), so a user who forgot the flag
would silently get meaningless digits. Importing :mod:`rbo_jax` therefore turns float64 on, unless
the user has explicitly chosen otherwise with the environment variable ``JAX_ENABLE_X64`` (any of
``0``, ``false``, ``False``), in which case their choice is respected and the simulator warns when a
float32 computation is asked for tolerances below float32's resolution.
"""

from __future__ import annotations

import os

import jax

_OPT_OUT = {"0", "false", "False", "FALSE", "no"}


def enable_float64_by_default() -> bool:
    """Enable ``jax_enable_x64`` unless ``JAX_ENABLE_X64`` is explicitly false.

    Returns whether float64 is enabled afterwards.
    """
    if os.environ.get("JAX_ENABLE_X64", "") not in _OPT_OUT:
        jax.config.update("jax_enable_x64", True)
    return bool(jax.config.jax_enable_x64)


def float64_enabled() -> bool:
    """Whether JAX currently produces float64 arrays by default."""
    return bool(jax.config.jax_enable_x64)
