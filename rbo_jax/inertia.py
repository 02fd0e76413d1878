r"""The inertia tensor $A$ of the body about its fixed point, eqs. (4.39)–(4.40).

$A$ is stored as a ``(3, 3)`` matrix in the reference (body) basis. The model accepts any
symmetric positive definite $A$; these helpers build one from principal moments and axes and
validate a given one. All are differentiable in their float inputs and accept traced values
(validation is then done by the solvers that use the model); concrete bad input raises
``ValueError`` at once.
"""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np

from ._custom_types import Matrix, MatrixLike, ScalarLike, VectorLike
from ._validation import (
    POSITIVE,
    check_value,
    device_of,
    float_dtype,
    is_traced,
    scalar_parameter,
    unit_axis,
)

__all__ = [
    "transversely_isotropic_inertia",
    "principal_inertia",
    "check_inertia",
    "inertia_checks",
    "NonPhysicalInertiaWarning",
]


class NonPhysicalInertiaWarning(UserWarning):
    r"""The principal moments violate a triangle inequality $A_i \le A_j + A_k$: no rigid body
    of positive mass density has this inertia tensor. Some studies use such tensors on purpose;
    silence with ``warnings.filterwarnings("ignore", category=NonPhysicalInertiaWarning)``."""


_WARNED: set = set()


def _warn_if_not_physical(A):
    """Warn (once per set of principal moments) when $A_i > A_j + A_k$ for some i."""
    moments = np.linalg.eigvalsh(0.5 * (np.asarray(A) + np.asarray(A).T))
    total = moments.sum()
    for i, Ai in enumerate(moments):
        if Ai > (total - Ai) * (1.0 + 1e-12):
            j, k = (n for n in range(3) if n != i)
            key = tuple(np.round(moments, 12))
            if key in _WARNED:
                return
            _WARNED.add(key)
            warnings.warn(
                "the inertia tensor's principal moments (ascending) "
                f"{', '.join(f'{m:.6g}' for m in moments)}"
                f" violate the triangle inequality A_{i + 1} <= A_{j + 1} + A_{k + 1} "
                f"({Ai:.6g} > {moments[j]:.6g} + {moments[k]:.6g}): no rigid body has this "
                "inertia. "
                "If this is intended, silence it with warnings.filterwarnings('ignore', "
                "category=rbo_jax.inertia.NonPhysicalInertiaWarning).",
                NonPhysicalInertiaWarning,
                stacklevel=3,
            )
            return


# Relative tolerances of the checks (rounding of matrices built from rotated axes is ~1e-16).
_SYMMETRY_RTOL = 1e-10
_ORTHONORMAL_ATOL = 1e-10


def _float_matrix(x, name: str, owner: str) -> Matrix:
    """A (3, 3) float matrix: NumPy for a concrete ``x`` (checked on the host), else traced."""
    x = x if is_traced(x) else np.asarray(x)
    if x.shape != (3, 3):
        raise ValueError(f"{owner}: {name} must have shape (3, 3), got {x.shape}.")
    if np.issubdtype(x.dtype, np.complexfloating):
        raise TypeError(f"{owner}: {name} must be real, got dtype {x.dtype}.")
    return x.astype(float_dtype())


def transversely_isotropic_inertia(A1: ScalarLike, A3: ScalarLike, k: VectorLike) -> Matrix:
    r"""The transversely isotropic inertia tensor $A = A_1(E - k\otimes k) + A_3\,k\otimes k$,
    eq. (4.40): symmetry axis $d_3 = k$ (normalised here), $A_1 = A_2 > 0$, $A_3 > 0$."""
    owner = "transversely_isotropic_inertia"
    A1 = scalar_parameter(A1, "A1", owner, "principal moment of inertia", POSITIVE)
    A3 = scalar_parameter(A3, "A3", owner, "principal moment of inertia", POSITIVE)
    k = unit_axis(k, owner)
    if any(is_traced(v) for v in (A1, A3, k)):
        kk = jnp.outer(k, k)
        return A1 * (jnp.eye(3, dtype=kk.dtype) - kk) + A3 * kk
    kk = np.outer(np.asarray(k), np.asarray(k))  # concrete: on the host, no XLA programs
    A = A1 * (np.eye(3, dtype=kk.dtype) - kk) + A3 * kk
    _warn_if_not_physical(A)
    return device_of(A)


def principal_inertia(moments: VectorLike, axes: MatrixLike) -> Matrix:
    r"""$A = \sum_i A_i\,d_i\otimes d_i$, eq. (4.39), from the principal moments
    ``moments`` $= (A_1, A_2, A_3)$, all $> 0$, and the principal axes, the **rows** of
    ``axes`` ($d_i$ = ``axes[i]``), which must be orthonormal (to 1e-10)."""
    owner = "principal_inertia"
    moments = moments if is_traced(moments) else np.asarray(moments)
    if moments.shape != (3,):
        raise ValueError(f"{owner}: moments must have shape (3,), got {moments.shape}.")
    moments = moments.astype(float_dtype())
    moments = check_value(
        moments,
        POSITIVE.holds(moments),
        f"{owner}: the principal moments of inertia (moments) must all be > 0 and finite",
    )
    axes = _float_matrix(axes, "axes", owner)
    xp = jnp if is_traced(moments) or is_traced(axes) else np
    error = xp.max(xp.abs(axes @ axes.T - xp.eye(3, dtype=axes.dtype)))
    axes = check_value(
        axes,
        error <= _ORTHONORMAL_ATOL,
        f"{owner}: the principal axes (rows of axes) must be orthonormal (|D D^T - E| <= "
        f"{_ORTHONORMAL_ATOL})",
    )
    A = axes.T @ (moments[:, None] * axes)
    if not is_traced(A):
        _warn_if_not_physical(A)
    return device_of(A)


def _inertia_properties(A):
    """finite, symmetric, positive definite (traced-friendly: Sylvester's criterion on the
    symmetric part, no eigenvalue call), and the asymmetry; in NumPy for a concrete ``A``."""
    xp = jnp if is_traced(A) else np
    A = A if xp is jnp else np.asarray(A)
    finite = xp.all(xp.isfinite(A))
    scale = xp.max(xp.abs(A))
    asymmetry = xp.max(xp.abs(A - A.T))
    symmetric = asymmetry <= _SYMMETRY_RTOL * scale
    S = 0.5 * (A + A.T)
    minor2 = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    det = (
        S[0, 0] * (S[1, 1] * S[2, 2] - S[1, 2] * S[2, 1])
        - S[0, 1] * (S[1, 0] * S[2, 2] - S[1, 2] * S[2, 0])
        + S[0, 2] * (S[1, 0] * S[2, 1] - S[1, 1] * S[2, 0])
    )
    positive = (S[0, 0] > 0) & (minor2 > 0) & (det > 0)
    return finite, symmetric, positive, asymmetry


def inertia_checks(A) -> list:
    """``(valid, message)`` pairs of an inertia tensor: finite, symmetric (to a relative 1e-10),
    positive definite (4.39). Traced values are checked by the solvers through
    :meth:`rbo_jax.RigidBodyOscillator.parameter_status`."""
    finite, symmetric, positive, _ = _inertia_properties(A)
    owner = "check_inertia"
    return [
        (finite, f"{owner}: the inertia tensor A must be finite."),
        (
            symmetric,
            f"{owner}: the inertia tensor A must be symmetric (|A - A^T| <= "
            f"{_SYMMETRY_RTOL} max|A|).",
        ),
        (positive, f"{owner}: the inertia tensor A must be positive definite."),
    ]


def check_inertia(A: MatrixLike) -> Matrix:
    r"""``A`` as a float ``(3, 3)`` array, after checking that it is an inertia tensor: finite,
    symmetric (to a relative 1e-10) and positive definite (eq. (4.39): $A_i > 0$).

    Concrete input raises ``ValueError`` saying which property fails (for positive
    definiteness, with the smallest eigenvalue); traced input is returned as it is and checked by
    the solvers that use the model (:func:`inertia_checks`). Physical realisability (the
    triangle inequalities $A_i \le A_j + A_k$) is not required: a concrete tensor that violates
    one gives a :class:`NonPhysicalInertiaWarning` (once per set of moments) naming it.
    """
    owner = "check_inertia"
    A = _float_matrix(A, "the inertia tensor A", owner)
    if is_traced(A):  # checked where it is used (inertia_checks), not traced again here
        return A
    finite, symmetric, positive, asymmetry = _inertia_properties(A)
    if not bool(finite):
        raise ValueError(f"{owner}: the inertia tensor A must be finite, got {np.asarray(A)!r}.")
    if not bool(symmetric):
        raise ValueError(
            f"{owner}: the inertia tensor A must be symmetric, but max|A - A^T| = "
            f"{float(asymmetry):.3g} (relative tolerance {_SYMMETRY_RTOL}); got {np.asarray(A)!r}."
        )
    if not bool(positive):
        smallest = float(np.linalg.eigvalsh(0.5 * (np.asarray(A) + np.asarray(A).T))[0])
        raise ValueError(
            f"{owner}: the inertia tensor A must be positive definite, but its smallest "
            f"eigenvalue is {smallest:.6g}; got {np.asarray(A)!r}."
        )
    _warn_if_not_physical(A)
    return device_of(A)
