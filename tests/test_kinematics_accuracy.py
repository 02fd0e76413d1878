"""Accuracy of :mod:`rbo_jax.kinematics` against mpmath references (50 significant digits or more).

The grids are log-spaced in |θ| ∈ [1e-12, 3] and dense around every place where a Taylor branch
hands over to a closed form:

- |θ| = 1 (t = θ² = 1): the coefficient functions of Q (4.3), Z (4.11) and Z⁻¹ (4.20);
- tan(|θ|/2) = 0.1, i.e. |θ| = 2 atan(0.1) ≈ 0.1993: the arctan(x)/x series of turn_vector/compose;
- |φ| = 2: the half-angle coefficients (t/4 = 1) of the quaternion inside compose (4.5).

An accuracy dip at a hand-over would show up as a local spike of the error there.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

import rbo_jax as rbo
from rbo_jax import kinematics as kin

REF_DPS = 200  # working digits of the coefficient references (≥ 50 survive every cancellation)
MAT_DPS = 50

THETA_SWITCH_TAYLOR = 1.0
THETA_SWITCH_ATAN = 2 * np.arctan(0.1)
THETA_SWITCH_QUAT = 2.0


def _around(x, lo=1e-12, hi=1e-1, n=16):
    d = np.geomspace(lo, hi, n)
    return np.concatenate([x * (1 - d), [x], x * (1 + d)])


MODULI = np.unique(
    np.concatenate(
        [
            np.geomspace(1e-12, 3.0, 100),
            _around(THETA_SWITCH_TAYLOR),
            _around(THETA_SWITCH_ATAN),
        ]
    )
)
T = MODULI**2
AXES = np.random.default_rng(7).normal(size=(len(MODULI), 3))
AXES /= np.linalg.norm(AXES, axis=1, keepdims=True)
THETAS = AXES * MODULI[:, None]

# --------------------------------------------------------------------------------------------
# mpmath references.
# --------------------------------------------------------------------------------------------


def _sqrt(t):
    return mp.sqrt(t)


MP_COEFFS = {
    "sinc": lambda t: mp.sin(_sqrt(t)) / _sqrt(t),  # sin θ/θ (4.3)
    "cosc": lambda t: (1 - mp.cos(_sqrt(t))) / t,  # (1 − cos θ)/θ² (4.3), (4.20)
    "_sinc3": lambda t: (_sqrt(t) - mp.sin(_sqrt(t))) / _sqrt(t) ** 3,  # (θ − sin θ)/θ³ (4.20)
    "gcoef": lambda t: (1 - _sqrt(t) / 2 * mp.cot(_sqrt(t) / 2)) / t,  # (1 − g)/θ² (4.11)
    "_cos": lambda t: mp.cos(_sqrt(t)),
}


@functools.cache
def mp_coefficient(name: str, t: float, order: int):
    """d^order/dt^order of a coefficient function at t (exact float input), REF_DPS digits."""
    with mp.workdps(REF_DPS):
        tm = mp.mpf(t)
        f = MP_COEFFS[name]
        if order == 0:
            return f(tm)
        # central differences with a step far below the digits kept (f is analytic in t > 0)
        return mp.diff(f, tm, order, h=tm * mp.mpf(10) ** -50)


def mp_matrices(theta):
    """Q (4.3), Z (4.11), Z⁻¹ (4.20) of the float vector θ (taken exactly), MAT_DPS digits."""
    with mp.workdps(REF_DPS):
        th = [mp.mpf(float(x)) for x in theta]
        tm = th[0] ** 2 + th[1] ** 2 + th[2] ** 2
        coeff = {name: MP_COEFFS[name](tm) for name in ("sinc", "cosc", "_sinc3", "gcoef")}
        R = mp.matrix([[0, -th[2], th[1]], [th[2], 0, -th[0]], [-th[1], th[0], 0]])
        R2 = mp.matrix(3, 3)
        for i in range(3):
            for j in range(3):
                R2[i, j] = th[i] * th[j] - (tm if i == j else 0)
        E = mp.eye(3)
        out = {
            "turn_tensor": E + coeff["sinc"] * R + coeff["cosc"] * R2,
            "integrating_tensor": E - R / 2 + coeff["gcoef"] * R2,
            "integrating_tensor_inv": E + coeff["cosc"] * R + coeff["_sinc3"] * R2,
        }
        with mp.workdps(MAT_DPS):
            return {k: [[+v[i, j] for j in range(3)] for i in range(3)] for k, v in out.items()}


@functools.cache
def reference_matrices():
    refs = [mp_matrices(theta) for theta in THETAS]
    return {
        name: (
            np.array([[[float(x) for x in row] for row in r[name]] for r in refs]),
            [r[name] for r in refs],
        )
        for name in ("turn_tensor", "integrating_tensor", "integrating_tensor_inv")
    }


def _rel_matrix_error(got, ref_mp):
    """max_ij |M_ij − M_ref,ij| / ‖M_ref‖_F computed in mpmath (the float reference itself has
    rounding errors of 1e-16)."""
    with mp.workdps(MAT_DPS):
        diff = max(abs(mp.mpf(float(got[i, j])) - ref_mp[i][j]) for i in range(3) for j in range(3))
        norm = mp.sqrt(sum(ref_mp[i][j] ** 2 for i in range(3) for j in range(3)))
        return float(diff / norm)


def _rel_skew_error(got, ref_mp):
    """Error of the skew part (M − Mᵀ)/2 relative to its own norm: the first-order part of Q, Z,
    Z⁻¹, which must stay accurate relative to |θ| even when |θ| ≪ 1."""
    with mp.workdps(MAT_DPS):
        pairs = [(0, 1), (0, 2), (1, 2)]
        ref = [(ref_mp[i][j] - ref_mp[j][i]) / 2 for i, j in pairs]
        ours = [(mp.mpf(float(got[i, j])) - mp.mpf(float(got[j, i]))) / 2 for i, j in pairs]
        return float(max(abs(a - b) for a, b in zip(ours, ref)) / mp.sqrt(sum(r**2 for r in ref)))


def mp_compose(phi, psi):
    """Principal log of exp(φ×E)·exp(ψ×E) via the quaternion product at MAT_DPS digits (4.5)."""
    with mp.workdps(MAT_DPS):

        def quat(v):
            v = [mp.mpf(float(x)) for x in v]
            th = mp.sqrt(sum(x * x for x in v))
            return mp.cos(th / 2), [mp.sin(th / 2) / th * x for x in v]

        w1, v1 = quat(phi)
        w2, v2 = quat(psi)
        w = w1 * w2 - sum(a * b for a, b in zip(v1, v2))
        cross = [
            v1[1] * v2[2] - v1[2] * v2[1],
            v1[2] * v2[0] - v1[0] * v2[2],
            v1[0] * v2[1] - v1[1] * v2[0],
        ]
        v = [w1 * b + w2 * a + c for a, b, c in zip(v1, v2, cross)]
        if w < 0:
            w, v = -w, [-x for x in v]
        s = mp.sqrt(sum(x * x for x in v))
        return [2 * mp.atan2(s, w) / s * x for x in v]


def _rel_vector_error(got, ref_mp):
    with mp.workdps(MAT_DPS):
        diff = mp.sqrt(sum((mp.mpf(float(g)) - r) ** 2 for g, r in zip(got, ref_mp)))
        return float(diff / mp.sqrt(sum(r**2 for r in ref_mp)))


def _report(errors, where, what):
    """Max error and where it occurs (shown on failure)."""
    i = int(np.argmax(errors))
    return f"{what}: max error {errors[i]:.3e} at |θ| = {where[i]!r}"


# --------------------------------------------------------------------------------------------
# Coefficient functions of t = θ².
# --------------------------------------------------------------------------------------------

# Tolerances (relative, elementwise). Measured maxima over this grid: values ≤ 1.2e-15, first
# derivatives ≤ 9e-14 (_gcoef just above t = 1, where the closed form's derivative cancels),
# second derivatives ≤ 6.5e-12 (_gcoef, same place).
COEFF_TOL = {0: 1e-13, 1: 1e-12, 2: 2e-11}


@functools.cache
def coefficient_on_grid(name):
    """(f, df/dt, d²f/dt²) of kin.<name> on the grid T: one compiled program per function."""
    f = getattr(kin, name)
    d1 = jax.grad(f)
    d2 = jax.grad(d1)
    out = jax.jit(jax.vmap(lambda t: (f(t), d1(t), d2(t))))(jnp.asarray(T))
    return [np.asarray(x) for x in out]


@pytest.mark.parametrize("order", [0, 1, 2])
@pytest.mark.parametrize("name", ["sinc", "cosc", "_sinc3", "gcoef"])
def test_coefficient_accuracy(name, order):
    """sin θ/θ, (1 − cos θ)/θ² (4.3), (θ − sin θ)/θ³ (4.20), (1 − g)/θ² (4.11) and their first and
    second derivatives in t (jax.grad) against mpmath, elementwise relative error, no dip at the
    Taylor hand-over t = 1 (or anywhere else on [1e-24, 9])."""
    got = coefficient_on_grid(name)[order]
    ref = np.array([float(mp_coefficient(name, t, order)) for t in T])
    assert np.all(np.isfinite(got))
    err = np.abs(got - ref) / np.abs(ref)
    assert err.max() <= COEFF_TOL[order], _report(err, MODULI, f"{name}^({order})")


@pytest.mark.parametrize("order", [0, 1, 2])
def test_cos_accuracy(order):
    """cos θ as a function of t (used by (4.6) and the quaternion of compose): absolute error, as
    cos θ has a zero on the grid's range."""
    got = coefficient_on_grid("_cos")[order]
    ref = np.array([float(mp_coefficient("_cos", t, order)) for t in T])
    err = np.abs(got - ref)
    assert err.max() <= 1e-15 * 10**order, _report(err, MODULI, f"_cos^({order})")


H = np.linspace(0.05, 3.1, 62)  # h = θ/2 of the coefficients' closed forms, within (0, π)
ANGLES = np.linspace(0.0, np.pi / 2, 31)  # the direction of (s, w) = r (sin a, cos a)


def _nested(f, order):
    for _ in range(order):
        f = jax.grad(f)
    return f


@functools.cache
def elementary_on_grid():
    """The derivatives of orders 0 to 3 of sin, cos and cot at ``H``, and of
    ``atan2_nonnegative`` along the path ``(s, w) = (sin a, cos a) + u (0.3, -0.7)`` in ``u`` at 0
    (rules of their own: the polynomial kernels are evaluated once at every order)."""
    from rbo_jax import _elementary as el

    def along(a):
        return lambda u: el.atan2_nonnegative(jnp.sin(a) + 0.3 * u, jnp.cos(a) - 0.7 * u)

    fns = {
        "sin": lambda h: el.sin_cos(h)[0],
        "cos": lambda h: el.sin_cos(h)[1],
        "cot": el.cot,
    }
    out = {}
    for k in range(4):
        for name, f in fns.items():
            out[name, k] = np.asarray(jax.jit(jax.vmap(_nested(f, k)))(jnp.asarray(H)))
        at = jax.vmap(lambda a, k=k: _nested(along(a), k)(jnp.zeros_like(a)))
        out["atan2", k] = np.asarray(jax.jit(at)(jnp.asarray(ANGLES)))
    return out


@pytest.mark.parametrize("order", [0, 1, 2, 3])
@pytest.mark.parametrize("name", ["sin", "cos", "cot", "atan2"])
def test_elementary_derivatives_accuracy(name, order):
    """sin, cos and cot (the closed forms of Z (4.11) and of the lattices' quaternions) and
    atan2 (the turn-vector of a rotation, inverse of (4.3)), and their derivatives to the third
    order (Lyapunov coefficients take third derivatives of the equations of motion), against
    mpmath: within 4e-15 of the largest value (relative for cot, which grows as 1/h). Measured:
    at most 7.5e-16; differentiating the polynomial kernels instead gave up to 2.3e-12 (the third
    derivative of cos), an approximation's derivative not being one of the derivative."""
    got = elementary_on_grid()[name, order]
    with mp.workdps(50):
        if name == "atan2":
            ref = [
                mp.diff(lambda u: mp.atan2(mp.sin(a) + 0.3 * u, mp.cos(a) - 0.7 * u), 0, order)
                for a in map(mp.mpf, ANGLES)
            ]
        else:
            f = {"sin": mp.sin, "cos": mp.cos, "cot": mp.cot}[name]
            ref = [mp.diff(f, mp.mpf(h), order) for h in H]
    ref = np.array([float(r) for r in ref])
    assert np.all(np.isfinite(got))
    if name == "cot":
        err = np.abs(got - ref) / np.abs(ref)
        assert err.max() <= 4e-15, _report(err, H, f"cot^({order})")
    else:
        err = np.abs(got - ref) / np.abs(ref).max()
        assert err.max() <= 4e-15, _report(err, H if name != "atan2" else ANGLES, name)


# --------------------------------------------------------------------------------------------
# Q, Z, Z⁻¹.
# --------------------------------------------------------------------------------------------

MATRIX_FUNCS = ["turn_tensor", "integrating_tensor", "integrating_tensor_inv"]


@pytest.mark.parametrize("name", MATRIX_FUNCS)
def test_matrix_accuracy(name):
    """Q (4.3), Z (4.11) and Z⁻¹ (4.20): entries within 1e-13 of mpmath relative to the matrix
    norm, and the skew (first-order) part within 1e-13 relative to its own norm, for |θ| from 1e-12
    to 3 including the hand-over at |θ| = 1."""
    got = np.asarray(jax.jit(jax.vmap(getattr(rbo, name)))(jnp.asarray(THETAS)))
    _, ref_mp = reference_matrices()[name]
    err = np.array([_rel_matrix_error(g, r) for g, r in zip(got, ref_mp)])
    assert err.max() <= 1e-13, _report(err, MODULI, name)
    err_skew = np.array([_rel_skew_error(g, r) for g, r in zip(got, ref_mp)])
    assert err_skew.max() <= 1e-13, _report(err_skew, MODULI, f"skew part of {name}")


def test_turn_vector_accuracy():
    """turn_vector (inverse of (4.3)) of the correctly rounded Q(θ) (mpmath) returns θ with
    relative error ≤ 1e-13 for |θ| from 1e-12 to 3, including the arctan-series switch at
    |θ| = 2 atan(0.1)."""
    Q_ref, _ = reference_matrices()["turn_tensor"]
    got = np.asarray(jax.jit(jax.vmap(rbo.turn_vector))(jnp.asarray(Q_ref)))
    err = np.linalg.norm(got - THETAS, axis=1) / MODULI
    assert err.max() <= 1e-13, _report(err, MODULI, "turn_vector")


def _compose_cases():
    rng = np.random.default_rng(11)
    n1 = np.array([1.0, 0.2, -0.3])
    n1 /= np.linalg.norm(n1)
    n2 = n1 + 0.6 * np.array([-0.1, 1.0, 0.4])
    n2 /= np.linalg.norm(n2)  # n1·n2 ≈ 0.86: no cancellation in the composed angle
    # composed angle swept through [1e-12, 3], dense at the arctan switch
    scales = np.unique(np.concatenate([np.geomspace(1e-12, 2.7, 40), _around(0.18, n=10)]))
    phis = [0.55 * s * n1 for s in scales]
    psis = [0.55 * s * n2 for s in scales]
    # |φ| around the quaternion hand-over |φ| = 2 (t/4 = 1)
    for a in _around(THETA_SWITCH_QUAT, n=10):
        axis = rng.normal(size=3)
        phis.append(a * axis / np.linalg.norm(axis))
        psis.append(0.5 * n2)
    return np.array(phis), np.array(psis)


def test_compose_accuracy():
    """compose(φ, ψ) (4.5) against the mpmath quaternion product: relative error ≤ 1e-13 for
    composed angles from 1e-12 to 3 and for |φ| around the half-angle hand-over |φ| = 2."""
    phis, psis = _compose_cases()
    got = np.asarray(jax.jit(jax.vmap(rbo.compose))(jnp.asarray(phis), jnp.asarray(psis)))
    refs = [mp_compose(p, q) for p, q in zip(phis, psis)]
    err = np.array([_rel_vector_error(g, r) for g, r in zip(got, refs)])
    moduli = np.array([float(mp.sqrt(sum(x * x for x in r))) for r in refs])
    assert err.max() <= 1e-13, _report(err, moduli, "compose")
