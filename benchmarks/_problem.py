"""The benchmark problem of ``bench_simulate.py`` and ``bench_sweep.py``: the Nikolai problem
(4.57)–(4.62), a transversely isotropic body (4.40) on the quadratic foundation (4.50) under a
follower moment (4.57); each point (c, d, M) starts at rest 1e-3 rad off its equilibrium
θ = (M/d) k (4.62); t ∈ [0, 20], rtol = 1e-8, atol = 1e-10, final state only. Its final states
by rbo_jax, by SciPy's DOP853 on the plain-NumPy field of ``_numpy_reference.py`` and by the
numba DOP853 of ``_numba_reference.py``. Nothing here imports JAX at import.
"""

from __future__ import annotations

import numpy as np

A1, A3 = 1.0, 0.5
K = np.array([0.0, 0.0, 1.0])
T1, RTOL, ATOL = 20.0, 1e-8, 1e-10
PERTURBATION = np.array([1e-3, -5e-4, 2e-4])
DESCRIPTION = f"Nikolai problem, t in [0, {T1}], rtol = {RTOL:g}, atol = {ATOL:g}"


def inertia():
    """A = A1 (E − k⊗k) + A3 k⊗k (4.40) of the benchmark problem, and its inverse."""
    A = A1 * (np.eye(3) - np.outer(K, K)) + A3 * np.outer(K, K)
    return A, np.linalg.inv(A)


def final_state(c, d, M, solver, rtol=RTOL, atol=ATOL):
    """The benchmark problem at (c, d, M) by ``solver`` (rbo_jax's ``simulate`` or
    ``fast_simulate``, ``throw=False``): (the final state (θ, Ω) (6,), accepted steps, status).
    Traceable: vmapped over the points."""
    import jax.numpy as jnp

    from rbo_jax import (
        FollowerMoment,
        QuadraticFoundation,
        RigidBodyOscillator,
        transversely_isotropic_inertia,
    )

    k = jnp.asarray(K)
    model = RigidBodyOscillator(
        transversely_isotropic_inertia(A1, A3, k),
        QuadraticFoundation(c, d, k),
        FollowerMoment(M, k),
    )
    theta0 = (M / d) * k + jnp.asarray(PERTURBATION)
    traj = solver(
        model, theta0, jnp.zeros(3), jnp.array([0.0, T1]), rtol=rtol, atol=atol, throw=False
    )
    return jnp.concatenate([traj.theta[-1], traj.Omega[-1]]), traj.num_steps, traj.status


def scipy_final_state(c, d, M, A, A_inv):
    """The benchmark problem at (c, d, M) by SciPy's ``solve_ivp(method="DOP853")`` on
    ``_numpy_reference.numpy_rhs`` (inertia ``A``, its inverse ``A_inv``): the solution, checked
    successful."""
    from _numpy_reference import numpy_rhs
    from scipy.integrate import solve_ivp

    y0 = np.concatenate([(M / d) * K + PERTURBATION, np.zeros(3)])
    sol = solve_ivp(
        numpy_rhs,
        (0.0, T1),
        y0,
        method="DOP853",
        rtol=RTOL,
        atol=ATOL,
        args=(c, d, M, A, A_inv, K),
    )
    assert sol.success, sol.message
    return sol


def numba_final_states(points: np.ndarray, parallel: bool) -> dict:
    """The final states at the (c, d, M) rows of ``points`` by the numba DOP853 (serial, or
    ``prange`` with ``parallel``): ``_numba_reference.timed_solve``'s dict (needs numba)."""
    import _numba_reference

    A, A_inv = inertia()
    return _numba_reference.timed_solve(points, parallel, T1, RTOL, ATOL, PERTURBATION, A, A_inv, K)
