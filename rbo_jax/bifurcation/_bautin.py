r"""Generalized Hopf (Bautin) points: where the first Lyapunov coefficient of a Hopf curve in two
parameters changes sign, so that flutter turns from soft to hard.

Along the Hopf curve $\alpha_H(\beta)$ of two parameters $(\alpha, \beta)$ (the Hopf system of
:mod:`._hopf`, solved for the equilibrium, $\alpha$ and the pair $\pm i\omega$ at each $\beta$),
the first Lyapunov coefficient $\ell_1(\beta)$ is a smooth function; a Bautin point is a root
$\ell_1(\beta_B) = 0$ with $\ell_1'(\beta_B) \ne 0$ and second Lyapunov coefficient
$\ell_2 \ne 0$ (:mod:`._normal_form`). With the normal form $\rho' = \rho(\mu + \ell_1\rho^2 +
\ell_2\rho^4)$ ($\mu$ the distance to the Hopf curve times the transversality over $\omega$):
for $\ell_2 < 0$ the cycles born on the hard side ($\ell_1 > 0$) at $\alpha_H$ turn back at a
fold of cycles at $\mu_F = \ell_1^2/(4|\ell_2|)$ on the stable side of the equilibrium,
$\alpha_F - \alpha_H \approx \omega\ell_1^2/(4\ell_2\,\mathrm{transversality})$, and between
$\alpha_F$ and $\alpha_H$ the equilibrium and a large stable cycle coexist (hysteresis).

**Solve.** The secant method on $\ell_1(\beta)$, each value from the Hopf program of
:mod:`._system` warm-started at the previous Hopf point; it stops when the step in $\beta$ is
below ``atol + rtol·|β|`` (superlinear convergence). The same loop then solves the Hopf points
at $q \pm he_i$, $q \pm 2he_i$ around the solution $q = (p, \beta_B)$ ($p$ the other parameters,
$h = 10^{-3}\max(1, |q_i|)$): the gradient of $\ell_1$ along the Hopf curve by Richardson's
central differences, $O(h^4)$, ~1e-9 relative (one compiled loop around one copy of the Hopf
program; the exact derivative would need fourth derivatives of the vector field, whose traced
program took minutes to compile). A second program computes $\ell_2$ at the solution.

**Derivatives** of the Bautin point follow from the implicit function theorem for the pair of
equations (Hopf system, $\ell_1 = 0$): $d\beta_B = -\nabla_p\ell_1\cdot dp/\partial_\beta\ell_1$,
and $du = -(\partial_u r)^{-1}\partial_{(p,\beta)} r\,d(p, \beta)$ of the Hopf system
(:mod:`._hopf`) at $(dp, d\beta_B)$: ``jax.grad`` and ``jax.jacfwd`` work through
:func:`bautin_point`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from .. import _enumeration as enum
from .._programs import program
from ..kinematics import _as_vector
from ..model import RigidBodyOscillator
from ._hopf import (
    HopfStatus,
    Static,
    _is_traced,
    _nan_unless,
    _zero_tangent,
    canonical,
    flat_parameters,
    solution,
)
from ._normal_form import STENCIL, WEIGHTS, second_lyapunov_coefficient
from ._system import _adjoint_vector, _code, _oriented, _Problem, normalisation_vector

__all__ = ["BautinPoint", "BautinStatus", "bautin_point"]

_HOPF_OK = int(np.asarray(enum.code(HopfStatus.successful)))


class BautinStatus(eqx.Enumeration):
    """Outcome of :func:`rbo_jax.bautin_point`."""

    successful = ""
    hopf_failed = (
        "The Hopf point could not be computed at the guess or during the iteration "
        "(hopf_point at the same values says why): start closer to the Hopf curve."
    )
    not_converged = (
        "The secant iteration for l1 = 0 along the Hopf curve did not converge within max_steps: "
        "start closer to the sign change of the first Lyapunov coefficient."
    )
    degenerate = (
        "The first Lyapunov coefficient does not change sign transversally at the solution "
        "(its derivative along the Hopf curve vanishes): not a generic Bautin point."
    )


class BautinPoint(eqx.Module):
    r"""A generalized Hopf (Bautin) point (module docstring): ``value`` $= (\alpha_B, \beta_B)$
    of the two ``parameters``, the ``frequency`` $\omega$, the equilibrium ``theta``, the critical
    ``eigenvector``, ``first_lyapunov`` (≈ 0: the residual of $\ell_1 = 0$), its derivative
    ``lyapunov_slope`` $d\ell_1/d\beta$ along the Hopf curve, the ``second_lyapunov``
    coefficient $\ell_2$ (:mod:`._normal_form`; $\ell_2 < 0$: the cycles of the hard side fold
    back into a large stable cycle), the ``transversality`` of the Hopf point, the secant's
    ``num_steps`` and the ``status`` (:class:`BautinStatus`)."""

    value: Float[Array, "2"]
    frequency: Float[Array, ""]
    theta: Float[Array, "3"]
    eigenvector: Complex[Array, "6"]
    first_lyapunov: Float[Array, ""]
    lyapunov_slope: Float[Array, ""]
    second_lyapunov: Float[Array, ""]
    transversality: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: BautinStatus

    @property
    def ok(self):
        return self.status == BautinStatus.successful


class BStatic(NamedTuple):
    """What the Bautin programs are compiled for: the Hopf program's static data (its flat
    parameters end with $\\beta$) and the secant's tolerances and budget."""

    hopf: Static
    rtol: float
    atol: float
    max_steps: int


def _start(h: Static, p, guess, theta0, t, n):
    """The loop's first carry: nothing solved yet (zeros shaped as the Hopf program's output)."""
    dtype = p.dtype
    cold = (jnp.zeros(17, dtype), jnp.zeros(12, dtype), jnp.asarray(False))
    q = jnp.concatenate([p, guess[1:]])
    shapes = jax.eval_shape(lambda: solution(h, q, guess[0], theta0, t, *cold))
    return dict(
        b_prev=guess[1],
        l_prev=jnp.zeros((), dtype),
        b=guess[1],
        l=jnp.zeros((), dtype),
        raw=jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes),
        u=cold[0],
        w=cold[1],
        k=jnp.asarray(0, jnp.int32),
        j=jnp.asarray(0, jnp.int32),
        values=jnp.zeros(4 * n, dtype),
        code=jnp.asarray(_code(BautinStatus.successful), jnp.int32),
        phase=jnp.asarray(0, jnp.int32),
    )


def _secant(static: BStatic, p, guess, theta0, t, step):
    r"""The secant iteration on $\ell_1(\beta)$ (module docstring), then the gradient of $\ell_1$
    along the Hopf curve with respect to $q = (p, \beta)$ by central differences of Hopf points
    solved again at $q \pm h e_i$, $q \pm 2he_i$ ($h = 10^{-3}\max(1, |q_i|)$, Richardson's
    stencil: ~1e-9 relative): one loop around ONE copy of the Hopf program, whose phase picks
    the point to solve. Returns ``(beta, u, Ju, Jp, transversality, l1, grad, steps, code)``."""
    dtype, h = p.dtype, static.hopf
    n = p.shape[0] + 1
    ok_code, failed = _code(BautinStatus.successful), _code(BautinStatus.hopf_failed)

    def point(c):
        """The flat parameters of this iteration's Hopf solve."""
        b0 = guess[1]
        slope = (c["l"] - c["l_prev"]) / (c["b"] - c["b_prev"])
        b = jnp.where(c["k"] == 0, b0, b0 + step * jnp.maximum(jnp.abs(b0), 1.0))
        b = jnp.where(c["k"] >= 2, c["b"] - c["l"] / slope, b)
        i, j = c["j"] % n, c["j"] // n
        q = jnp.concatenate([p, c["b"][None]])
        h_i = 1e-3 * jnp.maximum(jnp.abs(q[i]), 1.0)
        fd = q.at[i].add(jnp.asarray(STENCIL, dtype)[jnp.minimum(j, 3)] * h_i)
        return jnp.where(c["phase"] == 0, jnp.concatenate([p, b[None]]), fd), slope

    def body(c):
        q, slope = point(c)
        raw = solution(h, q, guess[0], theta0, t, c["u"], c["w"], c["k"] > 0)
        hopf_ok = raw.status == _HOPF_OK
        b, k = q[-1], c["k"] + 1
        small = (k >= 3) & (jnp.abs(b - c["b"]) <= static.atol + static.rtol * jnp.abs(b))
        flat = (k <= 2) | (jnp.isfinite(slope) & (slope != 0))
        code = jnp.where(hopf_ok, ok_code, failed)
        code = jnp.where(flat, code, _code(BautinStatus.degenerate))
        code = jnp.where(~small & (k >= static.max_steps), _code(BautinStatus.not_converged), code)
        stop = (code != ok_code) | small
        secant = dict(
            c,
            b_prev=c["b"],
            l_prev=c["l"],
            b=b,
            l=raw.first_lyapunov,
            raw=raw,
            u=raw.u,
            w=normalisation_vector(raw.u),
            k=k,
            code=code.astype(jnp.int32),
            phase=jnp.where(stop, jnp.where(code == ok_code, 1, 2), 0).astype(jnp.int32),
        )
        fd = dict(
            c,
            values=c["values"].at[c["j"]].set(raw.first_lyapunov),
            j=c["j"] + 1,
            code=jnp.where(hopf_ok, c["code"], failed).astype(jnp.int32),
            phase=jnp.where((c["j"] + 1 >= 4 * n) | ~hopf_ok, 2, 1).astype(jnp.int32),
        )
        return jax.tree.map(lambda a, b: jnp.where(c["phase"] == 0, a, b), secant, fd)

    c = jax.lax.while_loop(lambda c: c["phase"] < 2, body, _start(h, p, guess, theta0, t, n))
    q = jnp.concatenate([p, c["b"][None]])
    h_q = 1e-3 * jnp.maximum(jnp.abs(q), 1.0)
    grad = jnp.tensordot(jnp.asarray(WEIGHTS, dtype), c["values"].reshape(4, n), 1) / h_q
    raw = c["raw"]
    return (
        c["b"],
        raw.u,
        raw.Ju,
        raw.Jp,
        raw.transversality,
        raw.first_lyapunov,
        grad,
        c["k"],
        c["code"],
    )


def _final(static: BStatic, q, u, t):
    r"""$\ell_2$ (:mod:`._normal_form`) at the Hopf solution ``u`` for the flat parameters
    $q = (p, \beta)$, with the adjoint vector of $J$ at the point."""
    h = static.hopf
    problem = _Problem(h.model_fn, h.parameter, h.names, h.shapes, 0.0, 0.0, 0, q, t)

    def F(x):
        return problem.field(jnp.concatenate([x, u[3:4], q]))

    x0 = jnp.concatenate([u[:3], jnp.zeros(3, u.dtype)])
    omega, a, b, _, _ = _oriented(u)
    qv = jax.lax.complex(a, b)
    adjoint = _adjoint_vector(jax.jacfwd(F)(x0), omega, qv)
    return second_lyapunov_coefficient(F, x0, omega, qv, adjoint)


_secant_program = program(_secant, fast_compile=True)
_final_program = program(_final, fast_compile=True)


class Raw(NamedTuple):
    beta: Array
    u: Array
    transversality: Array
    l1: Array
    grad: Array
    l2: Array
    steps: Array
    status: Array
    Ju: Array  # the Hopf system's Jacobians at the solution (implicit function theorem)
    Jp: Array


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def bautin_solution(static: BStatic, p, guess, theta0, t, step) -> Raw:
    """The raw Bautin point; differentiable in ``p`` (module docstring)."""
    beta, u, Ju, Jp, trans, l1, grad, steps, code = _secant_program(
        static, p, guess, theta0, t, step
    )
    l2 = _final_program(static, jnp.concatenate([p, beta[None]]), u, t)
    return Raw(beta, u, trans, l1, grad, l2, steps, code, Ju, Jp)


@bautin_solution.defjvp
def _bautin_jvp(static, primals, tangents):
    # the custom_jvp function itself, not its body: so jax.grad runs the programs the value
    # compiled (a traced body would compile them again, without the small-program options)
    raw = bautin_solution(static, *primals)
    dbeta, du = _implicit_tangent(raw.grad, raw.Ju, raw.Jp, tangents[0])
    zeros = jax.tree.map(_zero_tangent, raw)
    return raw, zeros._replace(beta=dbeta, u=du)


@jax.jit
def _implicit_tangent(grad, Ju, Jp, dp):
    """$(d\beta_B, du)$ for $dp$ (module docstring): one compiled program, also for the batch
    of tangents of ``jax.jacfwd``."""
    n_p = dp.shape[0]
    dbeta = -(grad[:n_p] @ dp) / grad[n_p]
    return dbeta, -jnp.linalg.solve(Ju, Jp @ jnp.concatenate([dp, dbeta[None]]))


@jax.jit
def _finish(raw: Raw) -> BautinPoint:
    omega, a, b, _, _ = _oriented(raw.u)
    good = raw.status == _code(BautinStatus.successful)
    return BautinPoint(
        value=_nan_unless(good, jnp.stack([raw.u[3], raw.beta])),
        frequency=_nan_unless(good, omega),
        theta=_nan_unless(good, raw.u[:3]),
        eigenvector=_nan_unless(good, jax.lax.complex(a, b)),
        first_lyapunov=_nan_unless(good, raw.l1),
        lyapunov_slope=_nan_unless(good, raw.grad[-1]),
        second_lyapunov=_nan_unless(good, raw.l2),
        transversality=_nan_unless(good, raw.transversality),
        num_steps=raw.steps,
        status=enum.from_code(BautinStatus, raw.status),
    )


def bautin_point(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameters: tuple[str, str],
    guess,
    *,
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    t=0.0,
    step: float = 1e-3,
    rtol: float = 1e-12,
    atol: float = 1e-12,
    max_steps: int = 40,
) -> BautinPoint:
    r"""The generalized Hopf (Bautin) point nearest ``guess`` of the equilibria of
    ``model_fn(**params)`` in the two ``parameters`` $(\alpha, \beta)$: the point of the Hopf
    curve $\alpha_H(\beta)$ where the first Lyapunov coefficient changes sign, i.e. where flutter
    turns from soft ($\ell_1 < 0$) to hard ($\ell_1 > 0$) (module docstring).

    **Arguments:** ``model_fn`` and ``params`` as for :func:`rbo_jax.hopf_point` (the entries
    ``parameters`` may be absent; the others are fixed and differentiable); ``guess`` the pair
    $(\alpha_0, \beta_0)$: the Hopf point is first solved at $\beta_0$ from $\alpha_0$ (and
    ``theta_eq_fn``/``theta_guess``, as for :func:`rbo_jax.hopf_point`) and at
    $\beta_0 + \text{step}\cdot\max(1, |\beta_0|)$, then $\beta$ moves by the secant method
    on $\ell_1(\beta)$ until its step is below ``atol + rtol·|β|``, at most
    ``max_steps`` steps.

    **Returns** a :class:`BautinPoint`; never raises for a failed solve (``status`` says why,
    values are NaN). ``jax.grad``/``jax.jacfwd`` of ``value`` (and ``frequency``, ``theta``)
    with respect to the other entries of ``params`` by the implicit function theorem; ``vmap``
    over them works. Two compiled programs per model structure (the secant loop around the
    Hopf program, with the gradient of $\ell_1$; $\ell_2$), kept by the program store when it is on
    (:func:`rbo_jax.enable_compilation_cache`).

    Example: the damped Nikolai problem (4.57), (4.84), whose critical moment
    $M_c = 2b\sqrt{K(M_c)/A_1}$ does not depend on $A_3$ while $\ell_1$ does:
    ``bautin_point(lambda M, b, A3: nikolai_model(M, 1.0, 2.0, A3=A3, friction=b), {"b": 0.1},
    ("M", "A3"), (0.2, 1.2))``.
    """
    if not callable(model_fn):
        raise TypeError("model_fn must be a callable model_fn(**params) -> RigidBodyOscillator.")
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping {{name: value}}, got {type(params).__name__}.")
    if (
        not isinstance(parameters, (tuple, list))
        or len(parameters) != 2
        or not all(isinstance(n, str) for n in parameters)
        or parameters[0] == parameters[1]
    ):
        raise ValueError(f"parameters must be two different names of params, got {parameters!r}.")
    if theta_eq_fn is not None and not callable(theta_eq_fn):
        raise TypeError("theta_eq_fn must be a callable theta_eq_fn(**params) -> theta.")
    dtype = jnp.result_type(float)
    alpha, beta = (str(n) for n in parameters)
    guess = guess if _is_traced(guess) else np.asarray(guess, dtype)
    if jnp.shape(guess) != (2,):
        raise ValueError(f"guess must be a pair ({alpha}, {beta}), got shape {jnp.shape(guess)}.")
    others = {str(k): v for k, v in params.items() if k not in (alpha, beta)}
    theta_guess = (
        np.zeros(3, dtype) if theta_guess is None else _as_vector(theta_guess, "theta_guess")
    )
    names, shapes, p = flat_parameters(others)
    hopf = Static(
        canonical(model_fn),
        canonical(theta_eq_fn),
        alpha,
        names + (beta,),
        shapes + ((),),
        1e-11,
        1e-11,
        64,
    )
    static = BStatic(hopf, float(rtol), float(atol), int(max_steps))
    t = t if _is_traced(t) else np.asarray(t, dtype)
    step = step if _is_traced(step) else np.asarray(step, dtype)
    return _finish(bautin_solution(static, p, guess, theta_guess, t, step))
