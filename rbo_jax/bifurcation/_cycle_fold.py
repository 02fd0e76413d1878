r"""Folds of limit cycles (saddle-node of cycles), located exactly by Newton's method on the
minimally augmented shooting system, and the derivative of the fold's parameter.

With $x = [\theta, \Omega]$, the flow $\varphi_T(x_0; \alpha, p)$ of the right form
(4.55)–(4.56) (e.g. the Nikolai problem: follower moment (4.57) $\alpha = M$, friction (4.84)
$p \ni b$), $z = (x_0, T)$ and $y = (z, \alpha)$, a limit cycle solves the 7 **shooting
equations**

$$G(y) = \begin{pmatrix}\varphi_T(x_0; \alpha) - x_0 \\ g\cdot(x_0 - x_{ref})\end{pmatrix} = 0,
  \qquad G_z = \begin{pmatrix} M - E & F(\varphi_T) \\ g^T & 0\end{pmatrix}$$

($M = \partial\varphi_T/\partial x_0$ the monodromy matrix, $g$ a fixed unit phase vector). Along
the branch of cycles the tangent $(\dot z, \dot\alpha)$ solves $G_z\dot z + G_\alpha\dot\alpha =
0$; at a **fold** $\dot\alpha = 0$, so $G_z$ is singular: a second Floquet multiplier equals 1
(a Jordan block with the trivial one). Govaerts' **minimally augmented system** adds one scalar
equation: with bordering vectors $b, c$ (the left and right singular vectors of $G_z$ at the
guess), the solution of

$$\begin{pmatrix} G_z & b \\ c^T & 0\end{pmatrix}\begin{pmatrix} v \\ h\end{pmatrix} =
  \begin{pmatrix} 0 \\ 1\end{pmatrix}$$

gives the test function $h(y)$, zero exactly where $G_z$ is singular, and Newton's method solves
$G(y) = 0$, $h(y) = 0$ for the 8 unknowns $y$. With $w$ from the transposed system
($G_z^T w + c\,h = 0$, $b^Tw = 1$), $h_y = -w^T (G_z)_y v$. The second derivatives are
directional: $(G_z)_y v = \frac{d}{d\varepsilon} G_y(y + \varepsilon (v, 0))$ (the symmetry of
second derivatives), i.e. the forward-mode derivative along $v_x$ of the forward-mode Jacobian
$\partial\varphi_T/\partial(x_0, \alpha)$ through :func:`rbo_jax.fast_simulate` (one pass, one
outer direction), plus, along $v_T$, the closed forms $\partial_T\partial_y\varphi_T =
DF(\varphi_T)\,\partial_y\varphi_T + \partial_y F|_{explicit}$ and $\partial_y[F(\varphi_T)] =
DF(\varphi_T)\,\partial_y\varphi_T$. Each iteration evaluates this once, along the previous
iteration's $v$ (a lagged direction: $h_y$ is exact at the solution, the residual always; the
convergence is superlinear). The first iteration only sets $b$, $c$ and $v$.

**Derivative of the fold** with respect to the other parameters $p$ (envelope theorem: the fold
is the extremum of $\alpha$ on $G(y; p) = 0$): with $w$ the left null vector of $G_z$,

$$\frac{d\alpha^*}{dp} = -\frac{w^T G_p}{w^T G_\alpha},$$

first derivatives only ($G_p = \partial_p\varphi_T$ from the same forward-mode pass).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from .. import _enumeration as enum
from .._callables import canonical
from .._programs import program
from ..models.rigid_body import RigidBodyOscillator
from ..solvers import Dense, Implicit, Outcome, implicit, iterate, newton_update
from ._field import flat_field
from ._hopf import flat_parameters
from ._hopf_system import unpack_parameters
from ._models import rigid_model as _build
from ._orbit import OrbitStatus, _sorted, flow

__all__ = ["FoldOfCycles", "fold_of_cycles"]


class FoldOfCycles(Outcome):
    r"""A fold of limit cycles (module docstring): the parameter ``value`` $\alpha^*$ at the
    fold, the cycle there (``period``, initial state ``theta0``, ``Omega0``), its six Floquet
    ``multipliers`` (sorted by decreasing modulus; two equal 1), the ``residual`` (max norm of
    the shooting equations and the test function), Newton's ``num_steps`` and the ``status``
    (:class:`rbo_jax.bifurcation.OrbitStatus`)."""

    # this result's own fields, declared here (its pytree and its docs); `ok` is Outcome's
    value: Float[Array, ""]
    period: Float[Array, ""]
    theta0: Float[Array, "3"]
    Omega0: Float[Array, "3"]
    multipliers: Complex[Array, "6"]
    residual: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: OrbitStatus


class Static(NamedTuple):
    """What the fold program is compiled for (hashable, stable reprs)."""

    # alike the Hopf program's Static, but the static data of another program (fold_program)
    model_fn: Callable
    parameter: str
    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    rtol: float
    atol: float
    max_steps: int
    tol: float
    max_newton: int


class Raw(NamedTuple):
    y: Array  # (x0, T, alpha)
    residual: Array
    num_steps: Array
    status: Array
    multipliers: Array
    null_vector: Array  # c: the right null vector of G_z at the fold


def _evaluate(model_fn, parameter, names, shapes, solver, p, y, v):
    r"""At $y = (x_0, T, \alpha)$: the flow $\varphi_T$, $G_y$'s blocks and $(G_z)_y v$ (module
    docstring), from one forward-mode pass along $v_x$ of the Jacobian of $\varphi_T$ over
    $(x_0, \alpha, p)$, and the Jacobian of $F$ at $\varphi_T$ over $(x, \alpha, p)$."""

    def model_at(w):  # w = (alpha, p)
        return _build(model_fn, {**unpack_parameters(names, shapes, w[1:]), parameter: w[0]})

    def phi(z):  # z = (x0, alpha, p)
        xT, ok = flow(model_at(z[6:]), z[:6], y[6], **solver)
        return xT, (xT, ok)

    def jacobian(z):
        return jax.jacfwd(phi, has_aux=True)(z)

    z = jnp.concatenate([y[:6], y[7:], p])
    dz = jnp.concatenate([v[:6], jnp.zeros(1 + p.shape[0], p.dtype)])
    (D, (xT, ok)), (dD, _) = jax.jvp(jacobian, (z,), (dz,))

    def field(w):  # w = (x, alpha, p)
        f = flat_field(model_at(w[6:]), throw=False)(w[:6])
        return f, f

    Fw, f = jax.jacfwd(field, has_aux=True)(jnp.concatenate([xT, z[6:]]))
    DF = Fw[:, :6]
    vx, vT = v[:6], v[6]
    Dxv = D[:, :6] @ vx + f * vT
    # (G_z)_y v, top rows: columns x0, T, alpha (the phase row is constant)
    H = jnp.concatenate(
        [
            dD[:, :6] + vT * (DF @ D[:, :6]),
            (DF @ Dxv)[:, None],
            dD[:, 6:7] + vT * (DF @ D[:, 6:7] + Fw[:, 6:7]),
        ],
        axis=1,
    )
    return xT, ok, D, f, H


def _bordered(Gz, b, c):
    """``(v, h, w)``: the bordered system's solution and that of its transpose (module
    docstring)."""
    top = jnp.concatenate([Gz, b[:, None]], axis=1)
    B = jnp.concatenate([top, jnp.concatenate([c, jnp.zeros(1, c.dtype)])[None]])
    e = jnp.zeros(8, Gz.dtype).at[7].set(1.0)
    vh = jnp.linalg.solve(B, e)
    w = jnp.linalg.solve(B.T, e)
    return vh[:7], vh[7], w[:7]


def fold_program(model_fn, parameter, names, shapes, rtol, atol, max_steps, tol, max_newton, p, y0):
    r"""Newton's method on the minimally augmented system (module docstring) from ``y0`` $=
    (x_0, T, \alpha)$, the phase vector $g = F(x_0)$ at the guess. Returns plain arrays:
    ``(y, residual, num_steps, status code, multipliers, dalpha/dp)``."""
    solver = dict(rtol=rtol, atol=atol, max_steps=max_steps)
    model = _build(model_fn, {**unpack_parameters(names, shapes, p), parameter: y0[7]})
    g = flat_field(model, throw=False)(y0[:6])
    g = g / jnp.linalg.norm(g)
    ev = functools.partial(_evaluate, model_fn, parameter, names, shapes, solver, p)

    def step(y, c):
        v, b, cc, k = c["v"], c["b"], c["c"], c["k"]
        xT, ok, D, f, H = ev(y, v)
        top = jnp.concatenate([D[:, :6] - jnp.eye(6, dtype=y.dtype), f[:, None]], axis=1)
        Gz = jnp.concatenate([top, jnp.concatenate([g, jnp.zeros(1, g.dtype)])[None]])
        U, _, Vt = jnp.linalg.svd(Gz)
        b = jnp.where(k == 0, U[:, -1], b)
        cc = jnp.where(k == 0, Vt[-1], cc)
        v_new, h, w = _bordered(Gz, b, cc)
        r = jnp.concatenate([xT - y[:6], (g @ (y[:6] - y0[:6]))[None], h[None]])
        Gy = jnp.concatenate([Gz, jnp.concatenate([D[:, 6], jnp.zeros(1, y.dtype)])[:, None]], 1)
        J = jnp.concatenate([Gy, -(w[:6] @ H)[None]])
        new, _, converged, finite = newton_update(r, J, Dense(), y, rtol=0, atol=-1.0, floor=tol)
        stop = (k > 0) & (converged | ~ok | ~finite | (y[6] <= 0) | (k >= max_newton))
        y = jnp.where(stop | (k == 0), y, new)
        res = jnp.max(jnp.abs(r))
        c = dict(v=v_new, b=b, c=cc, k=k + 1, res=res, ok=ok, M=D[:, :6], Gy=Gy)
        return y, c, jnp.where(stop, 0, -1)

    init = dict(
        v=jnp.zeros(7, y0.dtype),
        b=jnp.zeros(7, y0.dtype),
        c=jnp.zeros(7, y0.dtype),
        k=jnp.asarray(0),
        res=jnp.asarray(jnp.inf, y0.dtype),
        ok=jnp.asarray(True),
        M=jnp.zeros((6, 6), y0.dtype),
        Gy=jnp.zeros((7, 8), y0.dtype),
    )
    y, s, _, _ = iterate(step, y0, init, max_steps=max_newton + 2, exhausted=0)
    S = OrbitStatus
    status = S.where(s["res"] <= tol, S.successful, S.not_converged)
    status = S.where(s["ok"], status, S.solve_failed)
    status = S.where(y[6] > 0, status, S.nonpositive_period)
    mu = _sorted(jnp.linalg.eigvals(s["M"]))
    mu = jnp.where(s["ok"], mu, jnp.full_like(mu, jnp.nan))
    return y, s["res"], s["k"] - 1, enum.code(status), mu, s["c"], g, s["Gy"]


# One program per model structure: with the program store on (rbo_jax.enable_compilation_cache)
# a second process loads it traced.
_program = program(fold_program, small=True)


class _Residual(NamedTuple):
    r"""The shooting equations at $y \oplus x$ and the gauge $c\cdot x_z = 0$ ($c$ the right
    null vector of $G_z$ at the fold): $G_y\,dy = -G_p\,dp$ with it is regular, and its
    $d\alpha$ is the envelope theorem's $-w^TG_p\,dp/w^TG_\alpha$ (module docstring)."""

    static: Static

    def __call__(self, y, x, params):
        z, g, x_ref, c = y
        (p,) = params
        st, w = self.static, z + x
        model = _build(
            st.model_fn, {**unpack_parameters(st.names, st.shapes, p), st.parameter: w[7]}
        )
        xT, _ = flow(model, w[:6], w[6], rtol=st.rtol, atol=st.atol, max_steps=st.max_steps)
        gauge = c @ x[:7]
        return jnp.concatenate([xT - w[:6], (g @ (w[:6] - x_ref))[None], gauge[None]])


def _solve(params, static: Static, y0):
    (p,) = params
    y, res, k, code, mu, c, g, Gy = _program(*static, p, y0)
    good = code == enum.code(OrbitStatus.successful)
    # the shooting equations' Jacobian at the fold (its period column F(phi_T)) and the gauge
    operator = jnp.concatenate([Gy, jnp.concatenate([c, jnp.zeros(1, c.dtype)])[None]])
    return Implicit((y, g, y0[:6], c), operator, good, Raw(y, res, k, code, mu, c))


def solution(static: Static, p, y0) -> Raw:
    """The raw solution of the fold program; its ``y[7]`` (the fold's parameter) is
    differentiable with respect to ``p`` (the implicit rule of :mod:`rbo_jax.solvers` on the
    shooting equations and the gauge, :class:`_Residual`), nothing else is."""
    out = implicit(lambda params: _solve(params, static, y0), _Residual(static), (p,),
                   linear=Dense(), increment=lambda y, params: jnp.zeros_like(y[0]),
                   retract=lambda y, x, params: (y[0] + x,) + tuple(y[1:]),
                   forward=True)  # fmt: skip
    y = out.y[0]
    y = jnp.concatenate([jax.lax.stop_gradient(y[:7]), y[7:]])  # only alpha's derivative is right
    return out.extra._replace(y=y)


def _guess_vector(guess, parameter, dtype):
    try:
        parts = [guess["theta0"], guess["Omega0"], guess["period"], guess[parameter]]
    except (KeyError, TypeError) as e:
        raise TypeError(
            "guess must be a row of continue_limit_cycles' dataset (cycles.isel(point=j)) or a "
            f"mapping with 'theta0', 'Omega0', 'period' and {parameter!r}."
        ) from e
    flat = [np.ravel(np.asarray(x, dtype=dtype)) for x in parts]
    if [f.size for f in flat] != [3, 3, 1, 1]:
        raise ValueError("guess: theta0 and Omega0 need 3 components, period and the value 1.")
    return np.concatenate(flat)


def fold_of_cycles(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    guess,
    *,
    tol: float = 1e-9,
    max_newton: int = 30,
    rtol: float = 1e-11,
    atol: float = 1e-11,
    max_steps: int = 100_000,
) -> FoldOfCycles:
    r"""The fold of the limit cycles of ``model_fn(**params)`` in ``parameter`` nearest
    ``guess`` (module docstring): where the family of cycles turns back in the parameter and a
    second Floquet multiplier passes through 1 (a stable and an unstable cycle merge).

    ``guess``: a cycle near the fold, a row of :func:`rbo_jax.continue_limit_cycles`' dataset
    (``cycles.isel(point=j)``) or a mapping with ``theta0``, ``Omega0``, ``period`` and
    ``parameter``. ``params``: every other argument of ``model_fn`` (``parameter``'s entry, if
    present, is ignored); they may be traced. ``tol``: Newton's tolerance on the max norm of the
    shooting residual and the test function; ``rtol``, ``atol``, ``max_steps`` go to
    :func:`rbo_jax.fast_simulate`.

    **Returns** a :class:`FoldOfCycles`; never raises for a failed solve: ``status`` says why
    (e.g. ``solve_failed`` where an iterate's integration fails, such as a cycle through the
    singular sphere $|\theta| = 2\pi$ of (4.11)), and the cycle's fields are NaN.
    ``jax.grad``/``jax.jacfwd`` of ``value`` with respect to the entries of ``params`` work by
    the implicit function theorem ($d\alpha^*/dp = -w^TG_p/w^TG_\alpha$), running the same
    compiled program; the other fields' derivatives come out zero (they would need second
    derivatives of the flow with respect to $p$). Compiled once per structure of ``model_fn``
    and ``params``.
    """
    if not callable(model_fn):
        raise TypeError("model_fn must be a callable model_fn(**params) -> RigidBodyOscillator.")
    dtype = jnp.result_type(float)
    others = {str(k): v for k, v in params.items() if k != parameter}  # flat, by sorted name
    names, shapes, p = flat_parameters(others)
    static = Static(
        canonical(model_fn),
        parameter,
        names,
        shapes,
        float(rtol),
        float(atol),
        int(max_steps),
        float(tol),
        int(max_newton),
    )
    raw = solution(static, p, _guess_vector(guess, parameter, dtype))
    good = raw.status == enum.code(OrbitStatus.successful)
    y = jnp.where(good, raw.y, jnp.full_like(raw.y, jnp.nan))  # a failure is no fold
    return FoldOfCycles(
        value=y[7],
        period=y[6],
        theta0=y[:3],
        Omega0=y[3:6],
        multipliers=raw.multipliers,
        residual=raw.residual,
        num_steps=raw.num_steps,
        status=enum.from_code(OrbitStatus, raw.status),
    )
