"""Tests of rbo_jax.inertia: inertia tensors (4.39), (4.40) and their validation.

References: NumPy outer products and eigen-decompositions, finite differences.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import finite_difference_jacobian
from scipy.spatial.transform import Rotation

import rbo_jax as rbo
from rbo_jax.inertia import inertia_checks

K = np.array([1.0, 2.0, -2.0]) / 3.0


def frame_with_third_axis(k):
    """Orthonormal rows d1, d2, d3 = k."""
    d1 = np.cross(k, [1.0, 0.0, 0.0])
    d1 /= np.linalg.norm(d1)
    return np.stack([d1, np.cross(k, d1), k])


def test_transversely_isotropic_inertia_4_40():
    A1, A3 = 2.0, 3.5
    A = np.asarray(rbo.transversely_isotropic_inertia(A1, A3, 3.0 * K))  # k is normalised
    np.testing.assert_allclose(
        A, A1 * (np.eye(3) - np.outer(K, K)) + A3 * np.outer(K, K), rtol=1e-15, atol=1e-15
    )
    # (4.40) is (4.39) with d3 = k and A1 = A2.
    principal = rbo.principal_inertia([A1, A1, A3], frame_with_third_axis(K))
    np.testing.assert_allclose(A, principal, rtol=1e-14, atol=1e-15)
    # Eigenvalues (A1, A1, A3), k the eigenvector of A3.
    w, v = np.linalg.eigh(A)
    np.testing.assert_allclose(w, [A1, A1, A3], rtol=1e-14)
    np.testing.assert_allclose(abs(v[:, 2] @ K), 1.0, rtol=1e-14)
    assert A.dtype == np.float64


def test_principal_inertia_4_39():
    moments = np.array([1.0, 2.5, 4.0])
    axes = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix().T  # rows: rotated basis vectors
    A = np.asarray(rbo.principal_inertia(moments, axes))
    expected = sum(m * np.outer(d, d) for m, d in zip(moments, axes))
    np.testing.assert_allclose(A, expected, rtol=1e-14, atol=1e-15)
    for m, d in zip(moments, axes):
        np.testing.assert_allclose(A @ d, m * d, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(rbo.check_inertia(A), A, rtol=0, atol=0)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: rbo.principal_inertia([1.0, -2.0, 3.0], np.eye(3)), "moments.*must all be > 0"),
        (lambda: rbo.principal_inertia([1.0, 2.0, 3.0], np.eye(3) * 1.01), "orthonormal"),
        (lambda: rbo.principal_inertia([1.0, 2.0], np.eye(3)), r"shape \(3,\)"),
        (lambda: rbo.principal_inertia([1.0, 2.0, 3.0], np.eye(2)), r"shape \(3, 3\)"),
        (lambda: rbo.transversely_isotropic_inertia(0.0, 1.0, K), "parameter A1 must be > 0"),
        (lambda: rbo.transversely_isotropic_inertia(1.0, -1.0, K), "parameter A3 must be > 0"),
        (lambda: rbo.transversely_isotropic_inertia(1.0, 1.0, np.zeros(3)), "axis k"),
    ],
)
def test_construction_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(
    "A, match",
    [
        (np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "must be symmetric"),
        (np.diag([1.0, -0.5, 2.0]), r"positive definite.*smallest eigenvalue is -0\.5"),
        (np.diag([1.0, 0.0, 2.0]), "positive definite"),
        (np.eye(2), r"shape \(3, 3\)"),
        (np.eye(3).ravel(), r"shape \(3, 3\)"),
        (np.diag([1.0, np.nan, 2.0]), "must be finite"),
    ],
)
def test_check_inertia_refuses(A, match):
    with pytest.raises(ValueError, match=match):
        rbo.check_inertia(A)


def test_check_inertia_accepts_and_converts():
    A = rbo.check_inertia(np.diag([1, 2, 3]))  # integers become floats
    assert A.dtype == jnp.float64
    np.testing.assert_array_equal(A, np.diag([1.0, 2.0, 3.0]))
    # A symmetric, positive definite tensor that is not diagonal, with rounding noise.
    R = Rotation.from_rotvec([0.4, 0.2, -0.9]).as_matrix()
    B = R @ np.diag([1.0, 2.0, 2.5]) @ R.T
    np.testing.assert_array_equal(rbo.check_inertia(B), B)


def test_check_inertia_traced():
    """Traced tensors pass through check_inertia unchanged; inertia_checks names what fails (the
    solvers use it through RigidBodyOscillator.parameter_status)."""
    good = np.diag([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(jax.jit(rbo.check_inertia)(good), good)

    def failed(A):
        return jnp.stack([~v for v, _ in inertia_checks(A)])

    messages = [m for _, m in inertia_checks(good)]
    bad = {
        "positive definite": np.diag([1.0, -1.0, 3.0]),
        "symmetric": good + np.triu(np.ones((3, 3)), 1),
        "finite": np.diag([1.0, np.nan, 1.0]),
    }
    flags = np.asarray(jax.jit(jax.vmap(failed))(jnp.asarray([good, *bad.values()])))
    assert not flags[0].any()
    for row, word in zip(flags[1:], bad):
        assert any(word in m for m, f in zip(messages, row) if f), word


def test_inertia_differentiable_in_A1_A3():
    @jax.jit
    def fn(p):
        return rbo.transversely_isotropic_inertia(p[0], p[1], K).ravel()

    p0 = jnp.array([1.5, 2.5])
    J = jax.jit(jax.jacrev(fn))(p0)
    np.testing.assert_allclose(J[:, 0], (np.eye(3) - np.outer(K, K)).ravel(), atol=1e-15)
    np.testing.assert_allclose(J[:, 1], np.outer(K, K).ravel(), atol=1e-15)
    np.testing.assert_allclose(J, finite_difference_jacobian(fn, p0), rtol=1e-9, atol=1e-11)
    # Built inside vmap; a traced bad value gives a tensor that inertia_checks refuses.
    batched = jax.jit(jax.vmap(lambda a: rbo.transversely_isotropic_inertia(a, 1.0, K)))
    As = batched(jnp.array([1.0, 2.0, -2.0]))
    np.testing.assert_allclose(np.linalg.eigvalsh(As[1]), [1.0, 2.0, 2.0], rtol=1e-14)
    assert not bool(inertia_checks(As[2])[2][0]) and bool(inertia_checks(As[1])[2][0])


def test_non_physical_inertia_warns_once_naming_the_inequality():
    """A_3 = 2.5 > A_1 + A_2 = 2 violates a triangle inequality of the principal moments: no
    rigid body has this tensor; a NonPhysicalInertiaWarning names it, once, and can be
    silenced. Physical tensors (A_3 = 2 = A_1 + A_2: a flat disc) do not warn."""
    import warnings

    from rbo_jax.inertia import NonPhysicalInertiaWarning

    k = jnp.array([0.0, 0.0, 1.0])
    with pytest.warns(NonPhysicalInertiaWarning, match=r"A_3 <= A_1 \+ A_2.*filterwarnings"):
        A = rbo.transversely_isotropic_inertia(1.0, 2.5, k)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rbo.check_inertia(A)  # the same moments: not again
        rbo.transversely_isotropic_inertia(1.0, 2.0, k)
        rbo.principal_inertia(jnp.array([1.0, 2.0, 3.0]), jnp.eye(3))
    with pytest.warns(NonPhysicalInertiaWarning, match="A_3 <= A_1 \\+ A_2"):
        rbo.principal_inertia(jnp.array([1.0, 1.5, 3.0]), jnp.eye(3))
