"""Validation of user parameters, shared by foundations, loads and inertia.

Concrete (Python/NumPy) values are checked eagerly and raise ``ValueError`` naming the parameter;
traced values (objects built inside ``jax.vmap``/``jax.jit``/``jax.grad``) are checked with
:func:`equinox.error_if`, which raises when the computation runs.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Scalar, ScalarLike, Vector, VectorLike


def _float_dtype():
    """float64 when x64 is enabled (the rbo_jax default), float32 otherwise (no warning)."""
    return jnp.result_type(float)


def _is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _check(x, valid, message: str):
    """Validate ``x`` (an array) given ``valid`` (a boolean array computed from it).

    Concrete values raise ``ValueError(message)`` now; traced values are wrapped in
    :func:`equinox.error_if`, which raises when the computation runs.
    """
    if _is_traced(valid):
        return eqx.error_if(x, jnp.logical_not(jnp.all(valid)), message)
    if not bool(np.all(np.asarray(valid))):
        raise ValueError(f"{message}, got {np.asarray(x).tolist()!r}")
    return x


def _scalar_parameter(
    x: ScalarLike,
    name: str,
    owner: str,
    requirement: str = "",
    valid: Callable | None = None,
) -> Scalar:
    """``x`` as a float scalar array, checked with ``valid`` (described by ``requirement``).

    Non-finite values are always refused unless ``valid`` says otherwise.
    """
    x = jnp.asarray(x)
    if x.shape != ():
        raise ValueError(
            f"{owner}: the parameter {name} must be a scalar, got shape {x.shape}. rbo_jax "
            "objects hold a single parameter set: use jax.vmap to build batches."
        )
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise TypeError(f"{owner}: the parameter {name} must be real, got dtype {x.dtype}.")
    x = x.astype(_float_dtype())
    if valid is None:
        return _check(x, jnp.isfinite(x), f"{owner}: the parameter {name} must be finite")
    return _check(x, valid(x), f"{owner}: the parameter {name} must be {requirement}")


def _positive(x):
    return (x > 0) & jnp.isfinite(x)


def _positive_or_inf(x):
    return x > 0


def _nonnegative(x):
    return (x >= 0) & jnp.isfinite(x)


def _callable_leaf(fn: Callable, owner: str, name: str) -> Callable:
    """A user callable stored as a module field.

    Equinox Modules (and other pytrees such as ``jax.tree_util.Partial``) are kept as they are,
    so their float leaves stay differentiable parameters. A plain function is wrapped in
    ``jax.tree_util.Partial``, which makes it part of the tree *structure* rather than a leaf:
    the object then passes through plain ``jax.jit``/``jax.vmap`` as well as the ``eqx.filter_*``
    transformations (calling it is unchanged).
    """
    if not callable(fn):
        raise TypeError(f"{owner}: {name} must be callable, got {type(fn).__name__}.")
    if isinstance(fn, (eqx.Module, jax.tree_util.Partial)):
        return fn
    return jax.tree_util.Partial(fn)


def _unit_axis(k: VectorLike, owner: str, name: str = "k") -> Vector:
    """The axis ``k`` normalised to unit length; a zero or non-finite axis is refused."""
    k = jnp.asarray(k)
    if k.shape != (3,):
        raise ValueError(
            f"{owner}: the axis {name} must have shape (3,), got {k.shape}. rbo_jax objects "
            "hold a single parameter set: use jax.vmap to build batches."
        )
    if jnp.issubdtype(k.dtype, jnp.complexfloating):
        raise TypeError(f"{owner}: the axis {name} must be real, got dtype {k.dtype}.")
    k = k.astype(_float_dtype())
    k2 = jnp.dot(k, k)
    k = _check(
        k, (k2 > 0) & jnp.isfinite(k2), f"{owner}: the axis {name} must be a nonzero finite vector"
    )
    return k / jnp.sqrt(k2)
