"""Plain-NumPy reference of the Nikolai problem (4.55)-(4.56) with the quadratic foundation
(4.50) and a follower moment (4.57): the "what a user would write by hand" baseline of the
benchmarks, independent of rbo_jax (no JAX, no autodiff)."""

import numpy as np


def _skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def numpy_rhs(t, y, c, d, M, A, A_inv, K):
    theta, Omega = y[:3], y[3:]
    th2 = theta @ theta
    th = np.sqrt(th2)
    if th < 1e-4:
        gcoef = 1.0 / 12.0 + th2 / 720.0
    else:
        g = th * np.sin(th) / (2.0 * (1.0 - np.cos(th)))
        gcoef = (1.0 - g) / th2
    R = _skew(theta)
    Z = np.eye(3) - 0.5 * R + gcoef * (np.outer(theta, theta) - th2 * np.eye(3))
    kt = K @ theta
    dU = c * theta + (d - c) * kt * K  # gradient of (4.50)
    # (4.55) with the follower moment: P^T (M P k) = M k.
    rhs = M * K - Z @ dU - np.cross(Omega, A @ Omega)
    return np.concatenate([Z.T @ Omega, A_inv @ rhs])


def numpy_jacobian(c, d, M, A, A_inv, K, theta_eq, h=1e-6):
    """6x6 Jacobian of numpy_rhs at (theta_eq, 0) by central finite differences."""
    y0 = np.concatenate([theta_eq, np.zeros(3)])
    J = np.empty((6, 6))
    for i in range(6):
        e = np.zeros(6)
        e[i] = h
        J[:, i] = (
            numpy_rhs(0.0, y0 + e, c, d, M, A, A_inv, K)
            - numpy_rhs(0.0, y0 - e, c, d, M, A, A_inv, K)
        ) / (2 * h)
    return J
