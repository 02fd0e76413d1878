r"""Generalized Hopf (Bautin) points: where the first Lyapunov coefficient of a Hopf curve in two
parameters changes sign, so that flutter turns from soft to hard.

Along the Hopf curve $\alpha_H(\beta)$ of two parameters $(\alpha, \beta)$ (the flutter system
of :mod:`._hopf_system`, solved for the equilibrium, $\alpha$ and the pair $\pm i\omega$ at each
$\beta$), the first Lyapunov coefficient $\ell_1(\beta)$ is a smooth function; a Bautin point is
a root $\ell_1(\beta_B) = 0$ with $\ell_1'(\beta_B) \ne 0$ and second Lyapunov coefficient
$\ell_2 \ne 0$ (:mod:`._normal_form`). With the normal form $\rho' = \rho(\mu + \ell_1\rho^2 +
\ell_2\rho^4)$ ($\mu$ the distance to the Hopf curve times the transversality over $\omega$):
for $\ell_2 < 0$ the cycles born on the hard side ($\ell_1 > 0$) at $\alpha_H$ turn back at a
fold of cycles at $\mu_F = \ell_1^2/(4|\ell_2|)$ on the stable side of the equilibrium,
$\alpha_F - \alpha_H \approx \omega\ell_1^2/(4\ell_2\,\mathrm{transversality})$, and between
$\alpha_F$ and $\alpha_H$ the equilibrium and a large stable cycle coexist (hysteresis).

**Solve.** The secant method on $\ell_1(\beta)$, each value from the flutter program warm-started
at the previous Hopf point; it stops when the step in $\beta$ is below ``atol + rtol·|β|``
(superlinear convergence). The same loop then solves the Hopf points at $q \pm he_i$,
$q \pm 2he_i$ around the solution $q = (p, \beta_B)$ ($p$ the other parameters,
$h = 10^{-3}\max(1, |q_i|)$): the gradient of $\ell_1$ along the Hopf curve by Richardson's
central differences, $O(h^4)$, ~1e-9 relative (the exact derivative would need fourth
derivatives of the vector field). All of it is one loop (:func:`rbo_jax.solvers.iterate`)
around one copy of the flutter program, one solve per iteration, the last one at the solution,
whose loop of $\ell_1$'s third-order jet then also takes the evaluations of the second Lyapunov
coefficient $\ell_2$ (:mod:`._normal_form`): one traced jet for both.

**Derivatives** of the Bautin point follow from the implicit function theorem for the pair of
equations (flutter system, $\ell_1 = 0$), $\ell_1$ linearised by its gradient along the curve:
$d\beta_B = -\nabla_p\ell_1\cdot dp/\partial_\beta\ell_1$ and $du = -J^{+}\partial_{(p,\beta)}r\,
d(p, \beta)$ (:func:`rbo_jax.solvers.implicit`): ``jax.grad`` and ``jax.jacfwd`` work through
:func:`bautin_point`. $J$ and $\partial_{(p,\beta)}r$ are exact, from the last solve's jet (the
rows $D\tilde F[e_j]$, $D^2\tilde F[e_j, v]$ of :func:`._hopf_program.lyapunov`): no program of
the model's second derivatives. The differentiated solve is a program of its own (a static
flag): its jet also runs through the parameters, which would lengthen the value's
compilation where nothing is differentiated (measured: benchmarks/README.md, History).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from .. import _enumeration as enum
from .._programs import jit, program
from .._validation import array_namespace
from ..mechanics import AbstractMechanics
from ..solvers import Implicit, LeastSquares, Outcome, implicit, iterate
from ._hopf import _config_tree, cold_start, prepare
from ._hopf_program import _select, _typed, flutter_program
from ._hopf_system import Layout, Spec, model_at, oriented, residual
from ._normal_form import STENCIL, WEIGHTS

__all__ = ["BautinPoint", "BautinStatus", "bautin_point"]


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
    of the two ``parameters``, the ``frequency`` $\omega$, the equilibrium ``state`` (``theta``
    its turn-vectors), the critical ``eigenvector``, ``first_lyapunov`` (≈ 0: the residual of
    $\ell_1 = 0$), its derivative ``lyapunov_slope`` $d\ell_1/d\beta$ along the Hopf curve, the
    ``second_lyapunov`` coefficient $\ell_2$ (:mod:`._normal_form`; $\ell_2 < 0$: the cycles of
    the hard side fold back into a large stable cycle), the ``transversality`` of the Hopf
    point, the secant's ``num_steps`` and the ``status`` (:class:`BautinStatus`)."""

    value: Float[Array, "2"]
    frequency: Float[Array, ""]
    state: Any
    eigenvector: Complex[Array, " n"]
    first_lyapunov: Float[Array, ""]
    lyapunov_slope: Float[Array, ""]
    second_lyapunov: Float[Array, ""]
    transversality: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: BautinStatus

    @property
    def theta(self):
        """The turn-vector(s) of the equilibrium."""
        return getattr(self.state, "theta", self.state)


class Secant(NamedTuple):
    """The secant's settings (static)."""

    rtol: float
    atol: float
    max_steps: int


SECANT, GRADIENT, FINAL = 0, 1, 2
_OK, _HOPF_FAILED, _NOT_CONVERGED, _DEGENERATE = range(4)


class Raw(NamedTuple):
    config: Any
    u: Array
    C: Array
    beta: Array
    grad: Array  # of l1 along the Hopf curve, in q = (p, beta)
    transversality: Array
    l1: Array
    l2: Array
    num_steps: Array
    status: Array
    operator: Array | None  # the flutter system's exact Jacobian there (None unless asked)
    dq: Array | None  # its derivatives in q = (p, beta)
    dt: Array | None  # and in t


def _program(spec: Spec, secant: Secant, p, alpha0, beta0, guess, t, step, columns) -> Raw:
    r"""The secant iteration and the stencil of the gradient in one loop around one flutter
    program (module docstring); the last solve, at the solution, gives $\\ell_2$ and, with
    ``columns`` (static: the solve that is differentiated), the flutter system's exact
    derivatives there (:func:`._hopf_program.flutter_program`)."""
    model = model_at(spec, alpha0, jnp.concatenate([p, beta0[None]]))
    guess = model.configuration(guess, "theta_guess")  # None: at rest
    layout = Layout(model.free_size(), spec.kind)
    nq = p.shape[0] + 1
    u0, C0 = (jnp.asarray(x) for x in cold_start(spec, model, p.dtype))

    def point(c):
        slope = (c["l"] - c["l_prev"]) / (c["b"] - c["b_prev"])
        b = jnp.where(c["k"] == 1, beta0 + step * jnp.maximum(jnp.abs(beta0), 1.0), beta0)
        b = jnp.where(c["k"] >= 2, c["b"] - c["l"] / slope, b)
        qs = jnp.concatenate([p, c["b"][None]])
        i, j = c["j"] % nq, c["j"] // nq
        h = 1e-3 * jnp.maximum(jnp.abs(qs[i]), 1.0)
        fd = qs.at[i].add(jnp.asarray(STENCIL, p.dtype)[jnp.minimum(j, 3)] * h)
        fd = jnp.where(c["phase"] == FINAL, qs, fd)  # l2's solve: at the solution
        return jnp.where(c["phase"] == SECANT, jnp.concatenate([p, b[None]]), fd), slope

    def one(_, c):
        q, slope = point(c)
        final = c["phase"] == FINAL
        out = flutter_program(spec, q, alpha0, c["config"], t, c["k"] > 0, c["u"], c["C"],
                              final if columns else None, final)  # fmt: skip
        raw, l2, exact = out[0], out[-1], {}
        if columns:
            exact = dict(zip(("operator", "dq", "dt"), (out[1], *out[2])))
        ok, l1, b = raw.status == 0, raw.first_lyapunov, q[-1]
        k = c["k"] + 1
        small = (k >= 3) & (jnp.abs(b - c["b"]) <= secant.atol + secant.rtol * jnp.abs(b))
        flat = (k <= 2) | (jnp.isfinite(slope) & (slope != 0))
        code = jnp.where(ok, _OK, _HOPF_FAILED)
        code = jnp.where(flat, code, _DEGENERATE)
        code = jnp.where(~small & (k >= secant.max_steps), _NOT_CONVERGED, code)
        found = {**c, "config": raw.config, "u": raw.u, "C": raw.C, "b_prev": c["b"],
                 "l_prev": c["l"], "b": b, "l": l1, "k": k, "adjoint": raw.adjoint,
                 "transversality": raw.transversality}  # fmt: skip
        found["phase"] = jnp.where(small & (code == _OK), GRADIENT, SECANT)
        stop_secant = (code != _OK) | small
        s_code = jnp.where(stop_secant & (code != _OK), code, -1)
        last = c["j"] + 1 >= 4 * nq
        fd = {**c, "values": c["values"].at[c["j"]].set(l1), "j": c["j"] + 1}
        fd["phase"] = jnp.where(last, FINAL, GRADIENT)
        g_code = jnp.where(ok, -1, _HOPF_FAILED)
        last_solve = {**c, "l2": l2, **exact}
        new = _select(c["phase"] == SECANT, found, _select(final, last_solve, fd))
        code = jnp.where(c["phase"] == SECANT, s_code, jnp.where(final, _OK, g_code))
        return None, _typed(new, c), code

    n, cdtype = layout.n, C0.dtype
    zero = jnp.zeros((), p.dtype)
    c0 = dict(phase=jnp.asarray(SECANT, jnp.int32), k=jnp.asarray(0, jnp.int32),
              j=jnp.asarray(0, jnp.int32), config=guess, u=u0, C=C0, b_prev=beta0, l_prev=zero,
              b=beta0, l=zero, values=jnp.zeros(4 * nq, p.dtype), adjoint=jnp.zeros(n, cdtype),
              transversality=zero, l2=zero)  # fmt: skip
    if columns:
        rows = layout.rows(C0.shape[1])
        c0.update(operator=jnp.zeros((rows, layout.size), p.dtype),
                  dq=jnp.zeros((rows, nq), p.dtype), dt=jnp.zeros((rows, 1), p.dtype))  # fmt: skip
    c0 = jax.tree_util.tree_map(jnp.asarray, c0)
    budget = secant.max_steps + 4 * nq + 1
    _, c, code, _ = iterate(one, None, c0, max_steps=budget, exhausted=_NOT_CONVERGED)
    q = jnp.concatenate([p, c["b"][None]])
    h = 1e-3 * jnp.maximum(jnp.abs(q), 1.0)
    grad = jnp.tensordot(jnp.asarray(WEIGHTS, p.dtype), c["values"].reshape(4, nq), 1) / h
    return Raw(c["config"], c["u"], c["C"], c["b"], grad, c["transversality"], c["l"],
               c["l2"], c["k"], code, c.get("operator"), c.get("dq"), c.get("dt"))  # fmt: skip


def _flat_program(spec: Spec, secant: Secant, tree, p, alpha0, beta0, leaves, t, step, columns):
    """:func:`_program` on flat containers (the program store exports plain arrays: the
    configurations in and out as their leaves, their structure ``tree`` static)."""
    guess = None if tree is None else jax.tree_util.tree_unflatten(tree, leaves)
    raw = _program(spec, secant, p, alpha0, beta0, guess, t, step, columns)
    return (tuple(jax.tree_util.tree_leaves(raw.config)),) + tuple(raw[1:])


_bautin_program = program(_flat_program, fast_compile=True)


# --------------------------------------------------------------------------------------------
# The implicit derivative: the flutter system and l1 = 0, l1 linearised by its gradient
# --------------------------------------------------------------------------------------------


class _Residual(NamedTuple):
    spec: Spec

    def __call__(self, y, x, params):
        config, u, C, beta, qstar, grad = y
        p, t, _ = params
        q = jnp.concatenate([p, (beta + x[-1])[None]])
        layout = Layout(model_at(self.spec, q[-1], q).free_size(), self.spec.kind)  # structure
        r = residual(self.spec, layout, u + x[:-1], config, C, q, t)
        return jnp.concatenate([r, (grad @ (q - qstar))[None]])


class _Retract(NamedTuple):
    spec: Spec

    def __call__(self, y, x, params):
        config, u, C, beta, qstar, grad = y
        p = params[0]
        q = jnp.concatenate([p, beta[None]])
        model = model_at(self.spec, u[0], q)  # only its structure is used
        m = model.free_size()
        config = model.retract(config, model.free_increments(x[:m]))
        return config, u + x[:-1].at[:m].set(0.0), C, beta + x[-1], qstar, grad


def _increment(y, params):
    return jnp.zeros(y[1].shape[0] + 1, y[1].dtype)


def _solve(params, spec: Spec, secant: Secant, columns=False):
    """The program's solution; with ``columns`` (differentiated) also the exact Jacobian of
    :class:`_Residual` and its derivatives in ``p`` and ``t``: the flutter system's from the
    program, the row $\\nabla\\ell_1\\cdot(q - q^*)$'s from the stencil's gradient."""
    p, t, (alpha0, beta0, guess, step) = params
    leaves, tree = jax.tree_util.tree_flatten(guess)
    out = _bautin_program(spec, secant, None if guess is None else tree, p, alpha0, beta0,
                          tuple(leaves), t, step, bool(columns))  # fmt: skip
    xp = array_namespace(p, beta0)  # NumPy where concrete: no eager programs
    q = xp.concatenate([p, xp.asarray(beta0)[None]])
    raw = Raw(jax.tree_util.tree_unflatten(_config_tree(spec, q, alpha0), out[0]), *out[1:])
    xp = array_namespace(p, raw.beta)
    q = jax.lax.stop_gradient(xp.concatenate([p, xp.asarray(raw.beta)[None]]))
    y = (raw.config, raw.u, raw.C, raw.beta, q, jax.lax.stop_gradient(raw.grad))
    good = array_namespace(raw.status).asarray(raw.status) == _OK
    if not columns:
        return Implicit(y, None, good, raw)
    g, size = raw.grad, raw.operator.shape[1]
    operator = jnp.concatenate(
        [
            jnp.concatenate([raw.operator, raw.dq[:, -1:]], axis=1),
            jnp.concatenate([jnp.zeros(size, g.dtype), g[-1:]])[None],
        ]
    )
    dp = jnp.concatenate([raw.dq[:, :-1], g[None, :-1]])
    dt = jnp.concatenate([raw.dt, jnp.zeros((1, 1), g.dtype)])
    others = jax.tree_util.tree_map(lambda _: None, params[2])
    return Implicit(y, operator, good, raw, (dp, dt, others))


def _finish(spec: Spec, model: AbstractMechanics, y, raw: Raw) -> BautinPoint:
    config, u, _, beta, _, _ = y
    layout = Layout(model.free_size(), spec.kind)
    omega, q = oriented(layout, u)
    good = raw.status == _OK
    nan = lambda x: jnp.where(good, x, jnp.full_like(x, jnp.nan))  # noqa: E731
    return BautinPoint(
        value=nan(jnp.stack([u[layout.m], beta])),
        frequency=nan(omega),
        state=jax.tree_util.tree_map(nan, model.state_at_rest(config)),
        eigenvector=nan(q),
        first_lyapunov=nan(raw.l1),
        lyapunov_slope=nan(raw.grad[-1]),
        second_lyapunov=nan(raw.l2),
        transversality=nan(raw.transversality),
        num_steps=raw.num_steps,
        status=enum.from_code(BautinStatus, raw.status),
    )


# one small program, not two dozen eager ones (each compiled on first use), compiled fast
_finished = jit(_finish, fast_compile=True)


def bautin_point(
    model_fn: Callable[..., AbstractMechanics],
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
    curve $\alpha_H(\beta)$ where the first Lyapunov coefficient changes sign, i.e. where
    flutter turns from soft ($\ell_1 < 0$) to hard ($\ell_1 > 0$) (module docstring); any
    model.

    **Arguments:** ``model_fn`` and ``params`` as for :func:`rbo_jax.hopf_point` (the entries
    ``parameters`` may be absent; the others are fixed and differentiable); ``guess`` the pair
    $(\alpha_0, \beta_0)$: the Hopf point is first solved at $\beta_0$ from $\alpha_0$ (and
    ``theta_eq_fn``/``theta_guess``, as for :func:`rbo_jax.hopf_point`) and at
    $\beta_0 + \text{step}\cdot\max(1, |\beta_0|)$, then $\beta$ moves by the secant method
    on $\ell_1(\beta)$ until its step is below ``atol + rtol·|β|``, at most ``max_steps``
    steps.

    **Returns** a :class:`BautinPoint`; never raises for a failed solve (``status`` says why,
    values are NaN). ``jax.grad``/``jax.jacfwd`` of ``value`` (and ``frequency``, ``state``)
    with respect to the other entries of ``params`` by the implicit function theorem; ``vmap``
    over them works. One compiled program per model structure (module docstring), kept by the
    program store when it is on (:func:`rbo_jax.enable_compilation_cache`).

    Example: the damped Nikolai problem (4.57), (4.84), whose critical moment
    $M_c = 2b\sqrt{K(M_c)/A_1}$ does not depend on $A_3$ while $\ell_1$ does:
    ``bautin_point(lambda M, b, A3: nikolai_model(M, 1.0, 2.0, A3=A3, friction=b), {"b": 0.1},
    ("M", "A3"), (0.2, 1.2))``.
    """
    if (
        not isinstance(parameters, (tuple, list))
        or len(parameters) != 2
        or not all(isinstance(n, str) for n in parameters)
        or parameters[0] == parameters[1]
    ):
        raise ValueError(f"parameters must be two different names of params, got {parameters!r}.")
    alpha, beta = (str(n) for n in parameters)
    dtype = jnp.result_type(float)
    traced = isinstance(guess, jax.core.Tracer)
    guess = guess if traced else np.asarray(guess, dtype)
    if jnp.shape(guess) != (2,):
        raise ValueError(f"guess must be a pair ({alpha}, {beta}), got shape {jnp.shape(guess)}.")
    others = {str(k): v for k, v in params.items() if k not in (alpha, beta)}
    options = dict(kind="hopf", theta_eq_fn=theta_eq_fn, theta_guess=theta_guess, t=t,
                   rtol=1e-11, atol=1e-11, max_steps=64, steps=1, cluster=1e-5, frequency=None,
                   multiplicity=1, lyapunov=True)  # fmt: skip
    spec, model, p, alpha0, config, t = prepare(model_fn, others, alpha, guess[0], options,
                                                along=(beta, guess[1]))  # fmt: skip
    secant = Secant(float(rtol), float(atol), int(max_steps))
    step = step if isinstance(step, jax.core.Tracer) else np.asarray(step, dtype)
    params_ = (p[:-1], t, (alpha0, p[-1], config, step))
    out = implicit(
        lambda params: _solve(params, spec, secant),
        _Residual(spec),
        params_,
        linear=LeastSquares(),
        retract=_Retract(spec),
        increment=_increment,
        exact=lambda params: _solve(params, spec, secant, True),
    )
    return _finished(spec, model, out.y, out.extra)
