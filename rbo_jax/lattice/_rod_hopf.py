r"""Flutter points of rods: where the equilibrium of ``model_fn(**params)`` (a :class:`Rod`) loses
stability by an oscillation as the load ``parameter`` $P$ grows.

With $A(P)$ the first-order matrix of :func:`rbo_jax.lattice.linearize` at the equilibrium of
:func:`rbo_jax.lattice.solve_equilibrium` ($m$ rows: turn increments, displacements, angular
velocities and velocities of the bodies that move), two kinds of flutter are solved for:

**Hopf** (``kind="hopf"``, a damped rod): a simple pair $\pm i\omega$ crosses the imaginary
axis. Unknowns $(v, \omega, P)$, $v \in \mathbb{C}^m$:

$$(A(P) - i\omega)\,v = 0, \qquad C^H v = e_1 .$$

**Collision** (``kind="collision"``, an undamped rod under a follower load: Beck's, Pflüger's and
Ziegler's columns). Below the flutter load every eigenvalue is imaginary, so the Hopf system is
degenerate at every stable $P$; flutter is the merging of two pairs $i\omega_1, i\omega_2$ into
a double eigenvalue $i\omega$ with a Jordan chain (a Krein collision), past which they leave
the axis as $\pm a + i\omega$. Unknowns $(v, u, \omega, P)$:

$$(A(P) - i\omega)\,v = 0, \qquad (A(P) - i\omega)\,u = v, \qquad C^H v = e_1, \qquad C^H u = 0 .$$

$C$ ($m \times k$, orthonormal) spans the eigenvectors of the followed eigenvalue at the guess:
$k$ is its multiplicity there, 2 for a rod whose section and loads are symmetric about its
axis (bending in two planes at one frequency). The $k$ normalisations pick one $v$ (and one
$u$) out of the $k$-dimensional eigenspace, so that the solution is isolated. The real and
imaginary parts make an over-determined, consistent system of $2m + 2k$ (Hopf) or
$4m + 4k$ (collision) real equations in $2m + 2$ or $4m + 2$ real unknowns, with a Jacobian of
full column rank at a generic flutter point; Newton's method takes the least-squares step
(QR). Its Jacobian's load column needs $\partial_P A$: the central difference of the
linearisation along the equilibrium's tangent (:func:`._rod_hopf_system._matrices`; the
equilibrium's derivative by forward mode, the implicit function theorem of
:mod:`._rod_statics`). It only steers the iteration: the residual, hence the solution, is
exact. The rows are equilibrated
first (each divided by its norm): the stiff shear, stretch and hinge modes make rows of $A$
up to $10^{12}$ times the others, and their rounding, unscaled, leaves the system
inconsistent at $10^{-3}$ of the soft rows (the derivative of Ziegler's flutter load was off
by $10^{-4}$; equilibrated, the least-squares residual is $10^{-16}$). ``residual`` is the
max norm of the equilibrated residual. Newton stops at a step below the tolerances or at a
residual at the rounding level ($64\epsilon$): from there the steps are rounding amplified by
the stiff rows, $10^{-10}$ of the load and more for Ziegler's damped pendulum.

**One program.** The start and the iteration run in one ``lax.while_loop`` (the start in its
first iteration, from the matrix that iteration computes), so the solve runs inside
``jax.jit`` and ``jax.vmap``; compiled with :func:`rbo_jax._programs.fast_compile_options`
eagerly and under ``jax.vmap`` alone. Measured (issue 32, 2026-11-28, one pinned core, fresh
processes alternating with the tree before, first call): before, the solve ran as compiled
pieces in a Python loop with $\partial_P A$ by forward mode through the linearisation (a
second derivative of the forces: that piece compiled in 11 s); Ziegler's pendulum
19.9-22.2 -> 9.6-10.4 s, Pflüger's column of 8 bodies 17.9-23.0 -> 8.3-10.8 s, its first
``jax.grad`` in the tip mass 59.3-60.6 -> 26.0-27.8 s; the same values to $10^{-10}$.
``jax.vmap`` over three tip masses: 17 s (38 s compiled with XLA's default options).

**Start.** The eigenvalues of $A$ at ``guess``: for ``"hopf"`` the pair with the largest real
part among those with $\mathrm{Im}\,p > 0$; for ``"collision"`` the two lowest distinct
eigenvalues of the upper half plane, $\lambda_1, \lambda_2$ (sorted by imaginary part: the two
lowest frequencies below the collision, or $\pm a + i\omega$ past it), with eigenvectors $v_1$,
$v_2$ scaled to $C^Hv_j = e_1$; then $i\omega = (\lambda_1 + \lambda_2)/2$,
$v = (v_1 + v_2)/2$, $u = (v_1 - v_2)/(\lambda_1 - \lambda_2)$, which solves the chain up to
$O((\lambda_1 - \lambda_2)^2)$. Eigenvalues within ``cluster`` × $|\lambda|$ of each other are
one eigenvalue of multiplicity $k$.

**Derivatives.** The solution $y(p)$ of $F(y, p) = 0$ is differentiated with respect to the
other parameters $p$ by the implicit function theorem, $dy = -J^+\,\partial_pF\,dp$ ($J^+$ the
least-squares inverse of the Jacobian at the solution, exact for the consistent system), with
$J$ and $\partial_pF$ from the derivatives of $A$ in the load and in every parameter by
forward mode (exact: a central difference there loses the soft modes to the rounding of the
stiff rows, $10^{-6}$ of Pflüger's $dP/d\mu$), in a second program compiled when the solve is
first differentiated (:func:`_sensitivities`). The tangent is then one product with them:
``jax.grad``, ``jax.jacfwd`` and ``jax.jvp`` of ``value`` and ``frequency`` work (e.g. of
Pflüger's flutter load with respect to the tip mass), under ``jax.vmap`` too.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Complex, Float, Int

from .. import _enumeration as enum
from .. import _programs
from ..bifurcation._hopf import canonical
from ..bifurcation._interface import Outcome
from ..bifurcation._system import HopfStatus, _code
from ._rod import Rod, RodState
from ._rod_hopf_system import (
    Options,
    Static,
    _equilibrated,
    _jacobian_of,
    _matrices,
    _newton_step,
    _residual_of,
    _sizes,
    _start,
)

__all__ = ["KINDS", "RodHopfPoint", "rod_hopf_point"]

KINDS = ("auto", "hopf", "collision")


class RodHopfPoint(Outcome):
    r"""A flutter point of a rod (module docstring): the critical ``value`` of the load, the
    ``frequency`` $\omega > 0$, the critical ``eigenvector`` $v$ of $A$ ($|v| = 1$, over the
    first-order state of :func:`rbo_jax.lattice.linearize`), the equilibrium ``state`` at the
    critical load, the ``kind`` solved for (``"hopf"`` or ``"collision"``), the Newton
    ``residual`` (max norm, rows equilibrated) and ``num_steps``, and the ``status`` (a
    :class:`rbo_jax.bifurcation.HopfStatus`). ``value``, ``frequency`` and ``eigenvector`` are
    NaN where the status is not successful. Of :class:`rbo_jax.HopfPoint`'s fields, ``value``,
    ``frequency``, ``eigenvector``, ``residual``, ``num_steps``, ``status``, ``ok`` and
    ``period`` are here; ``theta`` is ``state``, and ``adjoint``, ``transversality`` and
    ``first_lyapunov`` are not computed for rods."""

    value: Float[Array, ""]
    frequency: Float[Array, ""]
    eigenvector: Complex[Array, " m"]
    state: RodState
    residual: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: HopfStatus
    kind: str = eqx.field(static=True)

    @property
    def period(self):
        return 2 * jnp.pi / self.frequency


_SUCCESSFUL = _code(HopfStatus.successful)
_RUNNING = -1  # the loop's own code: not a status
_ROUNDING = 64  # machine epsilons: a residual at the rounding level


# --------------------------------------------------------------------------------------------
# Newton's iteration, in one program.
# --------------------------------------------------------------------------------------------


class Raw(NamedTuple):
    """The solve's outputs (arrays), in this order."""

    value: Array
    frequency: Array
    eigenvector: Array
    theta: Array
    r: Array
    residual: Array
    num_steps: Array
    status: Array
    y: Array
    C: Array


class _Carry(NamedTuple):
    it: Array
    code: Array
    y: Array
    C: Array
    residual: Array
    theta: Array
    r: Array


def _unknowns_size(kind: str, m: int) -> int:
    return 2 * m + 2 if kind == "hopf" else 4 * m + 2


def _solve_traced(static: Static, options: Options, guess, others) -> Raw:
    r"""The start and Newton's iteration (module docstring) in a ``lax.while_loop``. The start
    is made in the first iteration from the matrix that iteration computes anyway (one traced
    copy of the equilibrium and the linearisation in the program; under ``jax.vmap`` the
    eigenvalues are computed in every iteration and used in the first)."""
    m, nb = _sizes(static, guess, others)
    dtype = guess.dtype
    k = options.multiplicity
    scale = jnp.where(guess != 0, jnp.abs(guess), jnp.ones_like(guess))
    S = HopfStatus
    codes = {name: _code(getattr(S, name)) for name in enum.names(S)}

    def body(c: _Carry) -> _Carry:
        A, dA, ok, state = _matrices(static, c.y[-1], others, 1, scale)
        A_P = dA[0]
        fresh = c.it == 0
        y, C, found, fits = jax.lax.cond(
            fresh,
            lambda: _start(static, options, jnp.where(ok, A, 0), c.y[-1]),
            lambda: (c.y, c.C, jnp.ones((), bool), jnp.ones((), bool)),
        )
        dy, residual = _newton_step(static.kind, A, A_P, y, C)
        # a step below the tolerances, or a residual at the rounding level (the steps that
        # would follow are rounding, amplified by the stiff rows: 1e-10 of the load and more)
        converged = jnp.all(jnp.abs(dy) <= options.atol + options.rtol * jnp.abs(y))
        converged = converged | (residual <= _ROUNDING * jnp.finfo(dtype).eps)
        it = c.it + 1
        running = jnp.full((), _RUNNING, jnp.int32)
        code = jnp.where(converged, codes["successful"], running)
        code = jnp.where(
            it >= options.max_steps, jnp.where(converged, code, codes["not_converged"]), code
        )
        code = jnp.where(jnp.all(jnp.isfinite(dy)), code, codes["not_converged"])
        code = jnp.where(ok, code, codes["equilibrium_failed"])
        # the start: no equilibrium, no pair to follow, or one of more than `multiplicity`
        start_failed = fresh & (~ok | ~found | ~fits)
        start_code = jnp.where(found, codes["not_converged"], codes["no_oscillatory_pair"])
        start_code = jnp.where(ok, start_code, codes["equilibrium_failed"])
        code = jnp.where(start_failed, start_code, code)
        it = jnp.where(start_failed, 0, it)
        residual = jnp.where(start_failed, jnp.inf, residual)
        y = jnp.where(code == _RUNNING, y + dy, y)
        return _Carry(it, code.astype(jnp.int32), y, C, residual, state.theta, state.r)

    y0 = jnp.zeros(_unknowns_size(static.kind, m), dtype).at[-1].set(guess)
    cdtype = jnp.complex128 if dtype == jnp.float64 else jnp.complex64
    init = _Carry(
        jnp.zeros((), jnp.int32),
        jnp.full((), _RUNNING, jnp.int32),
        y0,
        jnp.zeros((m, k), cdtype),
        jnp.full((), jnp.inf, dtype),
        jnp.zeros((nb, 3), dtype),
        jnp.zeros((nb, 3), dtype),
    )
    c = jax.lax.while_loop(lambda c: c.code == _RUNNING, body, init)
    omega, P = c.y[-2], c.y[-1]
    zero = (c.code == codes["successful"]) & ~(omega > 1e-9 * jnp.maximum(1.0, jnp.abs(P)))
    code = jnp.where(zero, codes["zero_frequency"], c.code)
    good = code == codes["successful"]
    v = jax.lax.complex(c.y[:m], c.y[m : 2 * m])
    nan = jnp.asarray(jnp.nan, dtype)
    return Raw(
        jnp.where(good, P, nan), jnp.where(good, omega, nan),
        jnp.where(good, v / jnp.linalg.norm(v).astype(v.dtype), jnp.nan),
        jnp.where(good, c.theta, nan),
        jnp.where(good, c.r, nan), c.residual, c.it, code.astype(jnp.int32), c.y, c.C,
    )  # fmt: skip


_solve_program = _programs.jit(_solve_traced, fast_compile=True)


# --------------------------------------------------------------------------------------------
# Derivatives: the implicit function theorem.
# --------------------------------------------------------------------------------------------


def _sensitivities(static: Static, y, C, others):
    r"""$-J^+\partial_pF$ of the frequency and the load (2 × the flattened ``others``) at the
    solution ``y``: the derivatives of $A$ in the load and the constants
    (:func:`._rod_hopf_system._matrices`), the Jacobian $J$ and $\partial_pF$ from them, and
    the last two rows of the least-squares inverse of the equilibrated $J$."""
    flat, _ = ravel_pytree(others)
    P = y[-1]
    A, dA, _, _ = _matrices(static, P, others, 1 + flat.size, None, exact=True)
    J = _jacobian_of(static.kind, A, dA[0], y, C)

    def along(D):  # the residual is affine in A
        return jax.jvp(lambda A: _residual_of(static.kind, A, y, C), (A,), (D,))[1]

    F_p = jax.vmap(along, out_axes=1)(dA[1:])
    scale = _equilibrated(J)
    Q, R = jnp.linalg.qr(J / scale[:, None])
    last = jnp.zeros((R.shape[0], 2), R.dtype).at[-2:].set(jnp.eye(2, dtype=R.dtype))
    rows = (Q @ jax.scipy.linalg.solve_triangular(R.T, last, lower=True)).T / scale[None, :]
    return -(rows @ F_p)


_sensitivity_program = _programs.jit(_sensitivities, fast_compile=True)


def _zero_tangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, dtype=jax.dtypes.float0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _solve(static: Static, options: Options, guess, others) -> Raw:
    return _solve_program(static, options, guess, others)


@_solve.defjvp
def _solve_jvp(static, options, primals, tangents):
    r"""The implicit function theorem (module docstring): $dy = -J^+\partial_pF\,dp$, the load
    and the frequency being the last two unknowns; the sensitivities are computed from the
    primal solution only (the tangent is one product with them, nothing to transpose for
    ``jax.grad``). The guess has no influence."""
    guess, others = primals
    raw = _solve(static, options, guess, others)
    zeros = Raw(*(_zero_tangent(x) for x in raw))
    flat, _ = ravel_pytree(tangents[1])
    if flat.size == 0:
        return raw, zeros
    good = raw.status == _SUCCESSFUL
    # zero where the solve failed, before the product (no NaN in the transposed product)
    sensitivities = jnp.where(good, _sensitivity_program(static, raw.y, raw.C, others), 0.0)
    d_omega, d_value = sensitivities @ flat
    return raw, zeros._replace(
        value=jnp.where(good, d_value, 0.0), frequency=jnp.where(good, d_omega, 0.0)
    )


# --------------------------------------------------------------------------------------------
# The public solver.
# --------------------------------------------------------------------------------------------


def _is_damped(rod: Rod) -> bool:
    """Whether the rod has Kelvin–Voigt damping (a traced damping counts as damped)."""
    leaves = (rod.turn_damping, rod.gap_damping)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return True
    return bool(any(np.any(np.asarray(x) != 0) for x in leaves))


def choose_kind(model_fn, params: Mapping, parameter: str, guess, kind: str) -> str:
    """``kind``, with ``"auto"`` resolved: ``"hopf"`` for a damped rod at the guess, else
    ``"collision"``."""
    if kind not in KINDS:
        raise ValueError(f"hopf_point of a rod: kind must be one of {KINDS}, got {kind!r}.")
    if kind != "auto":
        return kind
    rod = model_fn(**{**params, parameter: guess})
    if not isinstance(rod, Rod):
        raise TypeError(f"model_fn must return a Rod, got {type(rod).__name__}.")
    return "hopf" if _is_damped(rod) else "collision"


def _check_unused(theta_eq_fn, theta_guess, t):
    given = {"theta_eq_fn": theta_eq_fn is not None, "theta_guess": theta_guess is not None}
    given["t"] = not (isinstance(t, (int, float)) and t == 0.0)
    for name, is_given in given.items():
        if is_given:
            raise ValueError(
                f"hopf_point of a rod: {name} does not apply (the rod's equilibrium is "
                "solved by lattice.solve_equilibrium from the straight rod)."
            )


def _prepare(model_fn, params, parameter, guess, kind, steps, options, along=None):
    """The checked arguments: ``(static, options, others, guess)``, ``kind`` resolved at the
    guess (and the first value of ``along``)."""
    if not callable(model_fn):
        raise TypeError("model_fn must be a callable model_fn(**params) -> Rod.")
    if not isinstance(parameter, str):
        raise TypeError(f"parameter must be the name of an entry of params, got {parameter!r}.")
    rtol, atol, max_steps, cluster, frequency, multiplicity = options
    if int(steps) < 1 or int(max_steps) < 1 or not cluster > 0 or int(multiplicity) < 1:
        raise ValueError(
            "hopf_point of a rod: steps, max_steps and multiplicity must be >= 1, cluster > 0."
        )
    dtype = jnp.result_type(float)
    others = {str(k): jnp.asarray(v, dtype) for k, v in params.items() if k != parameter}
    guess = jnp.asarray(guess, dtype)
    first = others if along is None else {**others, along[0]: along[1]}
    kind = choose_kind(model_fn, first, parameter, guess, kind)
    static = Static(canonical(model_fn), parameter, kind, int(steps))
    frequency = None if frequency is None else float(frequency)
    options = Options(float(rtol), float(atol), int(max_steps), float(cluster), frequency,
                      int(multiplicity))  # fmt: skip
    return static, options, others, guess


def rod_hopf_point(
    model_fn: Callable[..., Rod],
    params: Mapping[str, object],
    parameter: str,
    guess,
    *,
    kind: str = "auto",
    steps: int = 1,
    cluster: float = 1e-5,
    frequency=None,
    multiplicity: int = 2,
    theta_eq_fn=None,
    theta_guess=None,
    t=0.0,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 32,
) -> RodHopfPoint:
    r"""The flutter point nearest ``guess`` of the equilibrium of ``model_fn(**params)`` (a
    :class:`Rod`) in the load ``parameter`` (module docstring); what
    :func:`rbo_jax.hopf_point` does for a rod.

    **Arguments:** `model_fn` (every entry of ``params`` and the load are passed as floats,
    traced: build the load vector with ``jnp.stack``), `params` (``{name: value}``, floats; the
    entry ``parameter`` may be absent), `guess` (a load near the flutter load), `kind`
    (``"hopf"``: a simple pair crosses the axis, for damped rods; ``"collision"``: two
    imaginary pairs merge, for undamped rods under follower loads; ``"auto"``, the default:
    ``"hopf"`` when the rod built at the guess has a nonzero or traced Kelvin–Voigt damping,
    else ``"collision"``), `frequency` (``"hopf"``: follow the pair nearest this frequency
    at the guess), `steps` (load steps of every equilibrium solve), `cluster` (relative
    distance under which eigenvalues count as one), `multiplicity` (the most eigenvalues that
    may make one followed eigenvalue: 2, a rod bending alike in two planes; a start with more
    fails with ``not_converged``), `rtol`, `atol` (Newton stops when every step component is
    below ``atol + rtol`` × the unknown), `max_steps`. ``theta_eq_fn``, ``theta_guess`` and
    ``t`` of the rigid body's solver do not apply.

    **Returns** a :class:`RodHopfPoint`; a failed solve says why in ``status`` (the values
    NaN), never raises. One compiled program (start and Newton's iteration in a
    ``lax.while_loop``): it runs inside ``jax.jit`` and ``jax.vmap`` (e.g. over a tip mass),
    and ``jax.grad``, ``jax.jacfwd`` and ``jax.jvp`` of ``value`` and ``frequency`` with
    respect to the other entries of ``params`` work by the implicit function theorem (exact:
    forward-mode autodiff at the solution, in a second program compiled when first
    differentiated).
    """
    _check_unused(theta_eq_fn, theta_guess, t)
    options = (rtol, atol, max_steps, cluster, frequency, multiplicity)
    static, options, others, guess = _prepare(model_fn, params, parameter, guess, kind, steps,
                                              options)  # fmt: skip
    return _point(static.kind, _solve(static, options, guess, others))


def _point(kind: str, raw: Raw) -> RodHopfPoint:
    return RodHopfPoint(
        value=raw.value,
        frequency=raw.frequency,
        eigenvector=raw.eigenvector,
        state=RodState.at_rest(raw.theta, raw.r),
        residual=raw.residual,
        num_steps=raw.num_steps,
        status=enum.from_code(HopfStatus, raw.status),
        kind=kind,
    )
