"""Validation of user parameters, shared by foundations, loads, inertia and model descriptions.

Concrete (Python/NumPy) values are checked eagerly and raise ``ValueError`` naming the parameter.
Traced values (objects built inside ``jax.vmap``/``jax.jit``/``jax.grad``) cannot be checked at
construction; they are checked by the computations that use the model, with the same
requirements: every parametrised class lists them (``_requirements``) and answers
``parameter_checks()`` with ``(valid, message)`` pairs, and
:meth:`rbo_jax.RigidBodyOscillator.parameter_status` gathers them. A solver called with
``throw=True`` then raises the message (:func:`equinox.branched_error_if`); with ``throw=False``
the point gets the status ``invalid_parameters`` and NaN results, and the rest of a batch
completes.

The requirements themselves (:data:`POSITIVE`, :data:`NONNEGATIVE`, ...) are named objects, so
that the constructors and the application's model descriptions (:mod:`rbo_jax.app.spec`) check
and describe them the same way.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import sys
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._callables import canonical
from ._custom_types import Scalar, ScalarLike, Vector, VectorLike


@dataclasses.dataclass(frozen=True)
class Requirement:
    """A condition on a parameter value: ``text`` completes "must be ...", ``holds`` maps an
    array (NumPy or JAX) to a boolean array."""

    text: str
    holds: Callable


FINITE = Requirement("finite", lambda x: (x > -np.inf) & (x < np.inf))
POSITIVE = Requirement("> 0", lambda x: (x > 0) & (x < np.inf))
POSITIVE_OR_INF = Requirement("> 0 or inf", lambda x: x > 0)
NONNEGATIVE = Requirement(">= 0", lambda x: (x >= 0) & (x < np.inf))


def float_dtype():
    """float64 when x64 is enabled (the rbo_jax default), float32 otherwise (no warning)."""
    return jnp.result_type(float)


def common_float_dtype(*xs):
    """The widest floating dtype of ``xs`` (arrays or dtypes), by NumPy's rules — also under
    ``jax_numpy_dtype_promotion = "strict"``, which refuses to mix float32 with float64
    implicitly — canonicalised for the current x64 setting."""
    dtypes = [np.dtype(getattr(x, "dtype", x)) for x in xs]
    dtype = np.result_type(*dtypes, np.float16)
    if not np.issubdtype(dtype, np.floating):
        dtype = np.dtype(float_dtype())
    return jax.dtypes.canonicalize_dtype(dtype)


def is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def array_namespace(*xs):
    """The array namespace for ``xs``: NumPy when no leaf is traced (checks of concrete values
    run on the host, compiling nothing), else ``jax.numpy``."""
    return jnp if any(is_traced(x) for x in jax.tree_util.tree_leaves(xs)) else np


def on_host(tree):
    """``tree`` with its JAX arrays as NumPy arrays (pytrees such as models are rebuilt without
    running their constructors): checks then run in NumPy."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x) if isinstance(x, jax.Array) else x, tree)


def device_of(x):
    """A value checked on the host (NumPy) as a JAX array (a transfer, no XLA program); traced
    values as they are."""
    return x if is_traced(x) else jax.device_put(np.asarray(x))


# While tracing a solver's vector field with throw=False: runtime checks give NaN, not a host
# callback (JAX's persistent compilation cache keeps no program with one).
_FAILURES_AS_NAN: contextvars.ContextVar = contextvars.ContextVar(
    "rbo_jax_failures_as_nan", default=False
)


def error_if(x, pred, message: str):
    """:func:`equinox.error_if` for a check inside the equations of motion (a configuration
    where they are undefined); while tracing inside :func:`failures_as_nan`, ``x`` becomes NaN
    where ``pred`` holds instead, which a solver with ``throw=False`` reports as a non-finite
    state. Inside :func:`checked_inputs_trusted` it keeps equinox's setting from before."""
    if _FAILURES_AS_NAN.get():
        return jnp.where(pred, jnp.nan, x)
    on_error = _ON_ERROR.get()
    if on_error == "default":
        return eqx.error_if(x, pred, message)
    return eqx.error_if(x, pred, message, on_error=on_error)


# equinox's setting for error_if outside checked_inputs_trusted ("default": equinox decides)
_ON_ERROR: contextvars.ContextVar = contextvars.ContextVar("rbo_jax_on_error", default="default")


@contextlib.contextmanager
def checked_inputs_trusted(on: bool = True):
    """While tracing a diffrax solve whose inputs rbo_jax has checked on the host, turn off the
    runtime checks that diffrax makes of them again (``SaveAt.ts`` increasing and within
    ``[t0, t1]``, the sign of ``dt0``): they are host callbacks (:func:`equinox.error_if`), and
    JAX's persistent compilation cache and ``jax.export`` keep no program that holds one, so
    :func:`rbo_jax.simulate` would trace and compile in every process.

    equinox reads the default of ``error_if`` from a module variable of ``equinox._errors``
    (set from ``$EQX_ON_ERROR``) when the check is traced; this context sets it to ``"off"``
    and gives :func:`error_if` (rbo_jax's checks inside the equations of motion) the value from
    before. Only for callers that have checked those inputs and trace no user code that may
    call ``equinox.error_if`` (:func:`library_code_only`). With another equinox (no such
    variable) it does nothing: the program then holds the callbacks, and is compiled in every
    process, as before."""
    errors = sys.modules.get("equinox._errors")
    if not on or errors is None or not isinstance(getattr(errors, "EQX_ON_ERROR", None), str):
        yield
        return
    before = errors.EQX_ON_ERROR
    token = _ON_ERROR.set(before)
    errors.EQX_ON_ERROR = "off"
    try:
        yield
    finally:
        errors.EQX_ON_ERROR = before
        _ON_ERROR.reset(token)


def library_code_only(tree) -> bool:
    """Whether ``tree`` (a model) is made of rbo_jax's own classes, arrays and plain values only:
    no user function (a callable foundation or load), no user subclass, whose code could call
    :func:`equinox.error_if` (:func:`checked_inputs_trusted` would turn that off)."""
    if tree is None or isinstance(
        tree, (bool, int, float, complex, str, np.ndarray, np.generic, jax.Array, np.dtype)
    ):
        return True
    if isinstance(tree, (tuple, list)):
        return all(library_code_only(x) for x in tree)
    if isinstance(tree, eqx.Module) and type(tree).__module__.split(".")[0] == "rbo_jax":
        return all(library_code_only(getattr(tree, f.name, None)) for f in dataclasses.fields(tree))
    return False


@contextlib.contextmanager
def failures_as_nan(on: bool = True):
    """Inside this context (at trace time), :func:`error_if` gives NaN instead of raising."""
    token = _FAILURES_AS_NAN.set(bool(on))
    try:
        yield
    finally:
        _FAILURES_AS_NAN.reset(token)


def check_value(x, valid, message: str):
    """Validate ``x`` (an array) given ``valid`` (a boolean array computed from it).

    Concrete values raise ``ValueError(message)`` now; traced values are returned unchanged, to
    be checked by the computations that use them (module docstring).
    """
    if is_traced(valid):
        return x
    if not bool(np.all(np.asarray(valid))):
        raise ValueError(f"{message}, got {np.asarray(x).tolist()!r}")
    return x


def _as_float(x, shape: tuple[int, ...], what: str, owner: str):
    """``x`` as a real float array of the given shape, or an error naming ``what``. Concrete
    values become NumPy arrays: the constructors check and combine them on the host, where each
    JAX operation on a concrete value would compile a small XLA program of its own (~30 to
    build a model)."""
    x = x if is_traced(x) else np.asarray(x)
    if x.shape != shape and shape == ():
        raise ValueError(
            f"{owner}: {what} must be a scalar, got shape {x.shape}. rbo_jax objects hold a "
            "single parameter set: use jax.vmap to build batches."
        )
    if x.shape != shape:
        raise ValueError(
            f"{owner}: {what} must have shape {shape}, got {x.shape}. rbo_jax objects hold a "
            "single parameter set: use jax.vmap to build batches."
        )
    if np.issubdtype(x.dtype, np.complexfloating):
        raise TypeError(f"{owner}: {what} must be real, got dtype {x.dtype}.")
    return x.astype(float_dtype())


def scalar_parameter(
    x: ScalarLike,
    name: str,
    owner: str,
    meaning: str = "",
    requirement: Requirement = FINITE,
) -> Scalar:
    """``x`` as a float scalar array, checked against ``requirement`` (NaN is always refused;
    ``meaning`` says what the parameter is, in the message): a NumPy array for a concrete
    ``x`` (:func:`device_of` makes it a JAX array), ``x`` itself if traced."""
    x = _as_float(x, (), f"the parameter {name}", owner)
    detail = f" ({meaning})" if meaning else ""
    return check_value(
        x, requirement.holds(x), f"{owner}: the parameter {name} must be {requirement.text}{detail}"
    )


def set_parameters(module, **values) -> None:
    """Set the scalar fields of ``module`` listed in its ``_requirements`` from ``values``,
    coerced to float scalars and checked (concrete values now, traced ones later)."""
    owner = type(module).__name__
    table = {name: (requirement, meaning) for name, requirement, meaning in module._requirements}
    for name, value in values.items():
        requirement, meaning = table[name]
        setattr(module, name, device_of(scalar_parameter(value, name, owner, meaning, requirement)))


def requirement_checks(module) -> list:
    """``(valid, message)`` for every ``(field, requirement, meaning)`` of the class attribute
    ``_requirements`` of ``module``, and for its unit axis ``k`` if it has one."""
    owner = type(module).__name__
    out = []
    for name, requirement, meaning in getattr(module, "_requirements", ()):
        detail = f" ({meaning})" if meaning else ""
        value = getattr(module, name)
        out.append(
            (
                array_namespace(value).all(requirement.holds(value)),
                f"{owner}: the parameter {name} must be {requirement.text}{detail}",
            )
        )
    k = getattr(module, "k", None)
    if isinstance(k, (jax.Array, np.ndarray)) and k.shape == (3,):
        xp = array_namespace(k)
        out.append((xp.all(xp.isfinite(k)), f"{owner}: the axis k must be a nonzero finite vector"))
    return out


def checks_status(checks: list):
    """``(ok, which, messages)`` of traced ``(valid, message)`` pairs: whether every check
    holds, the index of the first that fails, and the messages (static): what the solvers
    raise (:func:`equinox.branched_error_if`) or report as ``invalid_parameters``."""
    valid = jnp.stack([jnp.asarray(v, dtype=bool) for v, _ in checks])
    return jnp.all(valid), jnp.argmin(valid), tuple(m for _, m in checks)


def callable_leaf(fn: Callable, owner: str, name: str) -> Callable:
    """A user callable stored as a module field.

    Equinox Modules (and other pytrees such as ``jax.tree_util.Partial``) are kept as they are,
    so their float leaves stay differentiable parameters. A plain function is wrapped in
    ``jax.tree_util.Partial``, which makes it part of the tree *structure* rather than a leaf:
    the object then passes through plain ``jax.jit``/``jax.vmap`` as well as the ``eqx.filter_*``
    transformations (calling it is unchanged). A new but identical function (the same code,
    closure and globals, :func:`rbo_jax._callables.canonical`: a notebook cell that builds its
    model again) is replaced by the first one seen, so that the model has the same structure
    and its compiled programs are reused.
    """
    if not callable(fn):
        raise TypeError(f"{owner}: {name} must be callable, got {type(fn).__name__}.")
    if isinstance(fn, (eqx.Module, jax.tree_util.Partial)):
        return fn
    return jax.tree_util.Partial(canonical(fn))


def unit_axis(k: VectorLike, owner: str, name: str = "k") -> Vector:
    """The axis ``k`` normalised to unit length (a JAX array); a zero or non-finite axis is
    refused. Concrete axes are checked and normalised in NumPy."""
    k = _as_float(k, (3,), f"the axis {name}", owner)
    xp = jnp if is_traced(k) else np
    k2 = xp.dot(k, k)
    k = check_value(
        k, (k2 > 0) & xp.isfinite(k2), f"{owner}: the axis {name} must be a nonzero finite vector"
    )
    return device_of(k / xp.sqrt(k2))


def tree_finite(tree):
    """Whether every float of ``tree`` is finite (a traced boolean)."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)
