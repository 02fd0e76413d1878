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
central differences, $O(h^4)$, ~1e-9 relative (the exact derivative would need fourth
derivatives of the vector field, whose traced program took minutes to compile), and finally the
second Lyapunov coefficient $\ell_2$ at the solution (:mod:`._normal_form`). All of it is ONE
compiled loop around ONE traced third-order jet of the vector field (:func:`._field.jet`), one
evaluation per iteration: the Hopf system's rows, then those of $\ell_2$ (:func:`_program`).

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
from .._programs import jit, program
from ..model import RigidBodyOscillator
from ._field import jet
from ._hopf import (
    HopfStatus,
    Static,
    _is_traced,
    _nan_unless,
    _zero_tangent,
    canonical,
    flat_parameters,
)
from ._interface import Outcome, check_model_fn, check_params, check_theta_eq_fn, theta_guess_vector
from ._normal_form import STENCIL, WEIGHTS, Schedule
from ._system import DONE, _code, _oriented, _Problem, _typed, normalisation_vector

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


class BautinPoint(Outcome):
    r"""A generalized Hopf (Bautin) point (module docstring): ``value`` $= (\alpha_B, \beta_B)$
    of the two ``parameters``, the ``frequency`` $\omega$, the equilibrium ``theta``, the critical
    ``eigenvector``, ``first_lyapunov`` (≈ 0: the residual of $\ell_1 = 0$), its derivative
    ``lyapunov_slope`` $d\ell_1/d\beta$ along the Hopf curve, the ``second_lyapunov``
    coefficient $\ell_2$ (:mod:`._normal_form`; $\ell_2 < 0$: the cycles of the hard side fold
    back into a large stable cycle), the ``transversality`` of the Hopf point, the secant's
    ``num_steps`` and the ``status`` (:class:`BautinStatus`)."""

    # this result's own fields, declared here (its pytree and its docs); `ok` is Outcome's
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


class BStatic(NamedTuple):
    """What the Bautin program is compiled for: the Hopf program's static data (its flat
    parameters end with $\\beta$) and the secant's tolerances and budget."""

    hopf: Static
    rtol: float
    atol: float
    max_steps: int


SECANT, GRADIENT, SECOND, FINISHED = range(4)  # the phases of the program's loop


class _Bautin:
    r"""The Bautin point in ONE loop around ONE traced third-order jet of the vector field
    (:func:`._field.jet`), one evaluation per iteration (:meth:`body`): the Hopf solves of the
    secant iteration on $\ell_1(\beta)$ (module docstring; the Hopf system's loop of
    :class:`._system._Problem`, restarted warm at each new $\beta$), then those at
    $q \pm he_i$, $q \pm 2he_i$ around the solution $q = (p, \beta)$ ($h = 10^{-3}\max(1,
    |q_i|)$: the gradient of $\ell_1$ along the Hopf curve by Richardson's central differences,
    ~1e-9 relative), then the evaluations of $\ell_2$ at the solution
    (:class:`._normal_form.Schedule`)."""

    def __init__(self, static: BStatic, p, guess, theta0, t, step):
        self.static, self.p, self.guess, self.theta0, self.t, self.step = (
            static, p, guess, theta0, t, step,
        )  # fmt: skip
        self.dtype, self.n = p.dtype, p.shape[0] + 1
        self.schedule = Schedule(6, p.dtype)

    def problem(self, q) -> _Problem:
        """The Hopf system at the flat parameters $q = (p, \beta)$."""
        h = self.static.hopf
        return _Problem(
            h.model_fn, h.parameter, h.names, h.shapes, h.rtol, h.atol, h.max_steps, q, self.t
        )

    def point(self, c):
        r"""The flat parameters $q = (p, \beta)$ of the next Hopf solve: the secant's next
        $\beta$ (phase ``SECANT``), or the ``j``-th point of the stencil around the solution
        (``GRADIENT``); and the secant's slope."""
        p, b0, n = self.p, self.guess[1], self.n
        slope = (c["l"] - c["l_prev"]) / (c["b"] - c["b_prev"])
        b = jnp.where(c["k"] == 0, b0, b0 + self.step * jnp.maximum(jnp.abs(b0), 1.0))
        b = jnp.where(c["k"] >= 2, c["b"] - c["l"] / slope, b)
        i, j = c["j"] % n, c["j"] // n
        q = jnp.concatenate([p, c["b"][None]])
        h_i = 1e-3 * jnp.maximum(jnp.abs(q[i]), 1.0)
        fd = q.at[i].add(jnp.asarray(STENCIL, self.dtype)[jnp.minimum(j, 3)] * h_i)
        return jnp.where(c["phase"] == SECANT, jnp.concatenate([p, b[None]]), fd), slope

    def initial(self) -> dict:
        """The first carry: the cold Hopf solve at the guess, nothing else done."""
        dtype, i32, guess, cdtype = self.dtype, jnp.int32, self.guess, self.schedule.cdtype
        q0 = jnp.concatenate([self.p, guess[1:]])
        cold = jnp.zeros(17, dtype), jnp.zeros(12, dtype), jnp.asarray(False)
        h = self.static.hopf
        start = self.problem(q0).first_state(h.theta_eq_fn, guess[0], self.theta0, *cold)
        zero = jnp.zeros((), dtype)
        c = dict(hopf=start, q=q0, b_prev=guess[1], l_prev=zero, b=guess[1], l=zero)
        c.update(k=jnp.asarray(0, i32), j=jnp.asarray(0, i32), values=jnp.zeros(4 * self.n, dtype))
        c.update(code=jnp.asarray(_code(BautinStatus.successful), i32))
        c.update(phase=jnp.asarray(SECANT, i32))
        # the last secant solve (its Jacobians: the implicit function theorem) and l2's loop
        c.update(u=cold[0], Ju=jnp.zeros((17, 17), dtype), Jp=jnp.zeros((17, self.n), dtype))
        z6 = jnp.zeros(6, cdtype)
        second = self.schedule.initial_state(jnp.zeros((6, 6), dtype), 0.0, z6, z6)
        return jax.tree.map(jnp.asarray, {**c, "transversality": zero, "second": second})

    def solved(self, c):
        r"""After a Hopf solve: the secant's step or the stencil's value, then the next solve
        (warm, from the secant's last point) or the evaluations of $\ell_2$."""
        static, s, i32 = self.static, c["hopf"], jnp.int32
        ok_code, failed = _code(BautinStatus.successful), _code(BautinStatus.hopf_failed)
        u, Ju, Jp, _, _, status, adjoint, l1, trans = self.problem(c["q"]).outputs(
            s, self.guess[0], c["k"] > 0
        )
        hopf_ok = status == _HOPF_OK
        _, slope = self.point(c)
        b, k = c["q"][-1], c["k"] + 1
        small = (k >= 3) & (jnp.abs(b - c["b"]) <= static.atol + static.rtol * jnp.abs(b))
        flat = (k <= 2) | (jnp.isfinite(slope) & (slope != 0))
        code = jnp.where(hopf_ok, ok_code, failed)
        code = jnp.where(flat, code, _code(BautinStatus.degenerate))
        code = jnp.where(~small & (k >= static.max_steps), _code(BautinStatus.not_converged), code)
        stop = (code != ok_code) | small
        omega, a, b_, _, _ = _oriented(u)
        second = self.schedule.initial_state(s["J"], omega, jax.lax.complex(a, b_), adjoint)
        secant = dict(c, b_prev=c["b"], l_prev=c["l"], b=b, l=l1, u=u, Ju=Ju, Jp=Jp, k=k)
        secant.update(transversality=trans, code=code.astype(i32), second=second)
        secant["phase"] = jnp.where(stop, jnp.where(code == ok_code, GRADIENT, FINISHED), SECANT)
        last = c["j"] + 1 >= 4 * self.n
        fd = dict(c, values=c["values"].at[c["j"]].set(l1), j=c["j"] + 1)
        fd["code"] = jnp.where(hopf_ok, c["code"], failed).astype(i32)
        fd["phase"] = jnp.where(~hopf_ok, FINISHED, jnp.where(last, SECOND, GRADIENT))
        new = jax.tree.map(lambda x, y: jnp.where(c["phase"] == SECANT, x, y), secant, fd)
        new = _typed(new, c)
        q, _ = self.point(new)
        w = normalisation_vector(new["u"])
        again = self.problem(q).initial_state(new["u"], w, True, s["theta_eq"])
        return _typed({**new, "q": q, "hopf": again}, c)

    def body(self, c):
        """One evaluation of the jet: a row of the Hopf system (:meth:`._system._Problem.
        evaluation`) or of $\\ell_2$ (:meth:`._normal_form.Schedule.evaluation`), then the
        step of the one that asked for it."""
        dtype, schedule = self.dtype, self.schedule
        hopf = self.problem(c["q"])
        y_h, t_h = hopf.evaluation(c["hopf"])
        shift, t_2, scale = schedule.evaluation(c["second"])
        m, u = y_h.shape[0], c["u"]
        y_2 = jnp.concatenate([u[:3] + shift[:3], shift[3:], u[3:4], self.p, c["b"][None]])
        t_2 = jnp.concatenate([t_2, jnp.zeros((3, m - 6), dtype)], axis=1)
        second = c["phase"] == SECOND
        y, d = jnp.where(second, y_2, y_h), jnp.where(second, t_2, t_h)
        derivatives = jet(hopf.field, y, d[0], d[1], d[2])

        def hopf_step(c):
            c = _typed({**c, "hopf": hopf.advance(c["hopf"], *derivatives)}, c)
            return jax.lax.cond(c["hopf"]["phase"] >= DONE, self.solved, lambda c: c, c)

        def second_step(c):
            st = schedule.advance(c["second"], scale, *derivatives[1:])
            phase = jnp.where(schedule.done(st), FINISHED, SECOND)
            return _typed({**c, "second": st, "phase": phase}, c)

        return jax.lax.cond(second, second_step, hopf_step, c)


def _program(static: BStatic, p, guess, theta0, t, step):
    """:class:`_Bautin`'s loop. Returns ``(beta, u, Ju, Jp, transversality, l1, grad, steps,
    code, l2)``."""
    bautin = _Bautin(static, p, guess, theta0, t, step)
    c = jax.lax.while_loop(lambda c: c["phase"] < FINISHED, bautin.body, bautin.initial())
    q = jnp.concatenate([p, c["b"][None]])
    h_q = 1e-3 * jnp.maximum(jnp.abs(q), 1.0)
    values = c["values"].reshape(4, bautin.n)
    grad = jnp.tensordot(jnp.asarray(WEIGHTS, p.dtype), values, 1) / h_q
    out = (c["b"], c["u"], c["Ju"], c["Jp"], c["transversality"], c["l"], grad, c["k"])
    return out + (c["code"], Schedule.result(c["second"]))


_bautin_program = program(_program, fast_compile=True)


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
    beta, u, Ju, Jp, trans, l1, grad, steps, code, l2 = _bautin_program(
        static, p, guess, theta0, t, step
    )
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


@functools.partial(jit, fast_compile=True)
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
    # keywords shared with hopf_point, continue_hopf (a public, documented signature)
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
    over them works. One compiled program per model structure (module docstring), kept by the
    program store when it is on (:func:`rbo_jax.enable_compilation_cache`).

    Example: the damped Nikolai problem (4.57), (4.84), whose critical moment
    $M_c = 2b\sqrt{K(M_c)/A_1}$ does not depend on $A_3$ while $\ell_1$ does:
    ``bautin_point(lambda M, b, A3: nikolai_model(M, 1.0, 2.0, A3=A3, friction=b), {"b": 0.1},
    ("M", "A3"), (0.2, 1.2))``.
    """
    check_model_fn(model_fn)
    check_params(params)
    if (
        not isinstance(parameters, (tuple, list))
        or len(parameters) != 2
        or not all(isinstance(n, str) for n in parameters)
        or parameters[0] == parameters[1]
    ):
        raise ValueError(f"parameters must be two different names of params, got {parameters!r}.")
    check_theta_eq_fn(theta_eq_fn)
    dtype = jnp.result_type(float)
    alpha, beta = (str(n) for n in parameters)
    guess = guess if _is_traced(guess) else np.asarray(guess, dtype)
    if jnp.shape(guess) != (2,):
        raise ValueError(f"guess must be a pair ({alpha}, {beta}), got shape {jnp.shape(guess)}.")
    others = {str(k): v for k, v in params.items() if k not in (alpha, beta)}
    theta_guess = theta_guess_vector(theta_guess, dtype)
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
