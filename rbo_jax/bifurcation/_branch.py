r"""Branches of equilibria with their special points located: the continuation of
:mod:`rbo_jax.continuation` (Keller's pseudo-arclength method, any model), its Hopf points
solved exactly by :func:`rbo_jax.hopf_point`."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from ..continuation import follow_equilibria
from ..mechanics import AbstractMechanics
from ._hopf import hopf_point

__all__ = ["continue_equilibria"]


def continue_equilibria(
    model_fn: Callable[..., AbstractMechanics],
    params: Mapping[str, object],
    parameter: str,
    start: float,
    stop: float,
    *,
    locate_hopf: bool = True,
    **options,
):
    r"""Follow the equilibria of ``model_fn(**params, parameter=λ)`` (any model) from
    λ = ``start`` towards ``stop`` by pseudo-arclength continuation, detecting folds, branch
    points and Hopf points, each Hopf point then solved by :func:`rbo_jax.hopf_point` from the
    last point before it (``locate_hopf``). The keywords and the returned
    :class:`xarray.Dataset` are :func:`rbo_jax.continuation.follow_equilibria`'s (its module
    docstring: the method, the special points): ``theta_guess``, ``steps``, ``ds``, ``ds_min``,
    ``ds_max``, ``max_points``, ``tol``, ``parameter_scale``, ``spectra``, ``t``,
    ``progress``."""
    locate = hopf_point if locate_hopf else None
    return follow_equilibria(model_fn, params, parameter, start, stop, locate_hopf=locate,
                             **options)  # fmt: skip
