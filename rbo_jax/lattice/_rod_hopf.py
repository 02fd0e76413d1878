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
(QR), with $\partial_P A$ by forward-mode autodiff through the equilibrium (the implicit
function theorem of :mod:`._rod_statics`). The rows are equilibrated first (each divided by
its norm): the stiff shear, stretch and hinge modes make rows of $A$ up to $10^{12}$ times
the others, and their rounding, unscaled, leaves the system inconsistent at $10^{-3}$ of the
soft rows (the derivative of Ziegler's flutter load was off by $10^{-4}$; equilibrated, the
least-squares residual is $10^{-16}$). ``residual`` is the max norm of the equilibrated
residual.

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
least-squares inverse of the Jacobian at the solution, exact for the consistent system): one
forward-mode derivative of $A$ per tangent. ``jax.grad`` of ``value`` and ``frequency`` works
(e.g. of Pflüger's flutter load with respect to the tip mass).
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
from .. import _programs
from ..bifurcation._hopf import canonical
from ..bifurcation._interface import Outcome
from ..bifurcation._system import HopfStatus
from ._rod import Rod, RodState
from ._rod_dynamics import linearize
from ._rod_statics import solve_equilibrium

__all__ = ["KINDS", "RodHopfPoint", "rod_continue_hopf", "rod_hopf_point"]

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


class Static(NamedTuple):
    """What the compiled pieces are specialised to (hashable)."""

    model_fn: Callable
    parameter: str
    kind: str
    steps: int


def _code(item) -> int:
    return int(np.asarray(enum.code(item)))


# --------------------------------------------------------------------------------------------
# The system, in compiled pieces.
# --------------------------------------------------------------------------------------------


def _rod_at(static: Static, P, others) -> Rod:
    rod = static.model_fn(**{**others, static.parameter: P})
    if not isinstance(rod, Rod):
        raise TypeError(f"model_fn must return a Rod here, got {type(rod).__name__}.")
    return rod


def _matrix(static: Static, P, others):
    """$A(P)$ at the equilibrium, whether the equilibrium was found, and the state."""
    rod = _rod_at(static, P, others)
    sol = solve_equilibrium(rod, steps=static.steps)
    return linearize(rod, sol.state), (sol.ok, sol.state)


def _eig(static: Static, P, others):
    A, (ok, _) = _matrix(static, P, others)
    p, V = jnp.linalg.eig(A)
    return p, V, ok


_eig_program = _programs.jit(_eig, fast_compile=True)


def _real(M):
    """The real matrix of the complex-linear map ``M`` on ``[Re z, Im z]``."""
    return jnp.block([[M.real, -M.imag], [M.imag, M.real]])


def _times_i(z):
    """$i z$ (no implicit promotion of a real ``z``)."""
    return jax.lax.complex(-jnp.imag(z), jnp.real(z))


def _split(z):
    return jnp.concatenate([z.real, z.imag])


def _unknowns(kind: str, y, m: int):
    """``(v, u, omega, P)`` from the real vector ``y`` (``u`` is ``None`` for Hopf)."""
    v = jax.lax.complex(y[:m], y[m : 2 * m])
    u = jax.lax.complex(y[2 * m : 3 * m], y[3 * m : 4 * m]) if kind == "collision" else None
    return v, u, y[-2], y[-1]


def _residual_of(kind, A, y, C):
    """The residual $F$ (real) of the module docstring's system at ``A``."""
    m = A.shape[0]
    v, u, omega, _ = _unknowns(kind, y, m)
    M = A.astype(v.dtype) - _times_i(omega) * jnp.eye(m, dtype=v.dtype)
    e1 = jnp.zeros(C.shape[1], v.dtype).at[0].set(1.0)
    if kind == "hopf":
        return jnp.concatenate([_split(M @ v), _split(C.conj().T @ v - e1)])
    return jnp.concatenate(
        [_split(M @ v), _split(M @ u - v), _split(C.conj().T @ v - e1), _split(C.conj().T @ u)]
    )


def _jacobian_of(kind, A, A_P, y, C):
    """The exact Jacobian of :func:`_residual_of` in ``y`` (columns: ``v``, [``u``], omega,
    P), real."""
    m = A.shape[0]
    v, u, omega, _ = _unknowns(kind, y, m)
    M = A.astype(v.dtype) - _times_i(omega) * jnp.eye(m, dtype=v.dtype)
    Ch = C.conj().T
    dv_P = A_P.astype(v.dtype) @ v
    if kind == "hopf":
        top = jnp.concatenate([_real(M), _split(-_times_i(v))[:, None], _split(dv_P)[:, None]], 1)
        bottom = jnp.concatenate([_real(Ch), jnp.zeros((2 * Ch.shape[0], 2), A.dtype)], 1)
        return jnp.concatenate([top, bottom], 0)
    du_P = A_P.astype(v.dtype) @ u
    Z, E = jnp.zeros_like(M), jnp.eye(m, dtype=v.dtype)
    Zc, zk = jnp.zeros_like(Ch), jnp.zeros((2 * Ch.shape[0], 2), A.dtype)
    rows = [
        [_real(M), _real(Z), _split(-_times_i(v))[:, None], _split(dv_P)[:, None]],
        [_real(-E), _real(M), _split(-_times_i(u))[:, None], _split(du_P)[:, None]],
        [_real(Ch), _real(Zc), zk],
        [_real(Zc), _real(Ch), zk],
    ]
    return jnp.concatenate([jnp.concatenate(r, 1) for r in rows], 0)


def _newton_step(static: Static, y, C, others):
    """At ``y``: the least-squares Newton step, the residual's max norm, the last two rows of
    the least-squares inverse of the Jacobian (for the implicit derivatives), whether the
    equilibrium was found, whether the step is finite, and the equilibrium state."""
    P = y[-1]
    A, A_P, aux = jax.jvp(
        lambda P: _matrix(static, P, others), (P,), (jnp.ones_like(P),), has_aux=True
    )
    ok, state = aux
    F = _residual_of(static.kind, A, y, C)
    J = _jacobian_of(static.kind, A, A_P, y, C)
    scale = jnp.linalg.norm(J, axis=1)  # rows equilibrated (module docstring)
    Q, R = jnp.linalg.qr(J / scale[:, None])
    dy = jax.scipy.linalg.solve_triangular(R, -(Q.T @ (F / scale)))
    last = jnp.zeros((R.shape[0], 2), R.dtype).at[-2:].set(jnp.eye(2, dtype=R.dtype))
    rows = (Q @ jax.scipy.linalg.solve_triangular(R.T, last, lower=True)).T / scale[None, :]
    return dy, jnp.max(jnp.abs(F / scale)), rows, ok, jnp.all(jnp.isfinite(dy)), state


_step_program = _programs.jit(_newton_step, fast_compile=True)


def _residual_tangent(static: Static, y, C, others, d_others):
    """$\\partial_pF\\,dp$ at ``y``: the derivative of the residual along the tangent of the
    other parameters, the load $P$ held."""

    def residual(o):
        A, _ = _matrix(static, y[-1], o)
        return _residual_of(static.kind, A, y, C)

    return jax.jvp(residual, (others,), (d_others,))[1]


_tangent_program = _programs.jit(_residual_tangent, fast_compile=True)


# --------------------------------------------------------------------------------------------
# The start (on the host) and Newton's iteration.
# --------------------------------------------------------------------------------------------


def _clusters(p, lam, cluster):
    return np.flatnonzero(np.abs(p - lam) <= cluster * max(abs(lam), 1e-300))


def _lowest(p, cluster, count):
    """Indices of one eigenvalue of each of the ``count`` lowest distinct frequencies
    (imaginary parts > 0), ascending."""
    osc = np.flatnonzero(p.imag > 1e-9 * np.max(np.abs(p)))
    reps: list = []
    for i in osc[np.argsort(p[osc].imag)]:
        if all(abs(p[i] - p[j]) > cluster * abs(p[j]) for j in reps):
            reps.append(i)
        if len(reps) == count:
            break
    return reps


def _start_hopf(p, V, P0, cluster, frequency=None):
    """``(y0, C)`` from the eigenvalues ``p`` and eigenvectors ``V`` at the guess, or ``None``
    when there is no oscillatory pair: the pair nearest ``frequency`` if given, else of the two
    lowest frequencies the one with the larger real part (a rod's fast shear, stretch, twist
    and hinge modes may be undamped, their real parts zero: they are not followed)."""
    osc = np.flatnonzero(p.imag > 1e-9 * np.max(np.abs(p)))
    if osc.size == 0:
        return None
    if frequency is not None:
        lam = p[osc[np.argmin(np.abs(p[osc].imag - frequency))]]
    else:
        lam = max((p[i] for i in _lowest(p, cluster, 2)), key=lambda z: z.real)
    C, _ = np.linalg.qr(V[:, _clusters(p, lam, cluster)])
    v = C[:, 0]
    return np.concatenate([v.real, v.imag, [lam.imag, P0]]), C


def _start_collision(p, V, P0, cluster):
    """``(y0, C)`` of the Jordan chain (module docstring) or ``None``."""
    reps = _lowest(p, cluster, 2)
    if len(reps) < 2:
        return None
    lam1, lam2 = p[reps[0]], p[reps[1]]
    one, two = _clusters(p, lam1, cluster), _clusters(p, lam2, cluster)
    k = min(one.size, two.size)
    C, _ = np.linalg.qr(V[:, one[:k]])
    v1 = V[:, one[:k]] @ np.linalg.solve(C.conj().T @ V[:, one[:k]], np.eye(k)[:, 0])
    v2 = V[:, two[:k]] @ np.linalg.solve(C.conj().T @ V[:, two[:k]], np.eye(k)[:, 0])
    v, u = 0.5 * (v1 + v2), (v1 - v2) / (lam1 - lam2)
    omega = 0.5 * (lam1 + lam2).imag
    return np.concatenate([v.real, v.imag, u.real, u.imag, [omega, P0]]), C


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
    rows: Array


def _failed(status, m, nb, dtype, steps=0, residual=np.inf):
    nan = np.full((), np.nan, dtype)
    return Raw(
        nan, nan, np.full(m, np.nan + 0j), np.full((nb, 3), np.nan, dtype),
        np.full((nb, 3), np.nan, dtype), np.asarray(residual, dtype), np.asarray(steps),
        np.asarray(_code(status), np.int32), np.zeros(0, dtype), np.zeros((m, 1), complex),
        np.zeros((2, 0), dtype),
    )  # fmt: skip


def _converged(dy, y, rtol, atol):
    return bool(np.all(np.abs(dy) <= atol + rtol * np.abs(y)))


def _solve_eager(static: Static, options, guess, others) -> Raw:
    """Start and Newton's iteration with concrete values (module docstring)."""
    rtol, atol, max_steps, cluster, frequency = options
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((guess, others))):
        raise TypeError(
            "hopf_point of a rod runs eagerly: jax.grad (and jax.jvp) of its value and "
            "frequency work, but not inside jax.jit, jax.vmap or jax.jacfwd."
        )
    dtype = jnp.result_type(float)
    P0 = np.asarray(guess, dtype)
    p, V, ok = (np.asarray(x) for x in _eig_program(static, jnp.asarray(P0), others))
    m, nb = p.shape[0], _rod_at(static, P0, others).n_bodies
    if not ok or not np.all(np.isfinite(p)):
        return _failed(HopfStatus.equilibrium_failed, m, nb, dtype)
    if static.kind == "hopf":
        start = _start_hopf(p, V, P0, cluster, frequency)
    else:
        start = _start_collision(p, V, P0, cluster)
    if start is None:
        return _failed(HopfStatus.no_oscillatory_pair, m, nb, dtype)
    y, C = jnp.asarray(start[0]), jnp.asarray(start[1])
    for it in range(1, max_steps + 1):
        dy, res, rows, ok, finite, state = _step_program(static, y, C, others)
        if not (bool(ok) and bool(finite)):
            status = HopfStatus.not_converged if ok else HopfStatus.equilibrium_failed
            return _failed(status, m, nb, dtype, it, res)
        if _converged(np.asarray(dy), np.asarray(y), rtol, atol):
            break
        y = y + dy
    else:
        return _failed(HopfStatus.not_converged, m, nb, dtype, max_steps, res)
    omega = float(y[-2])
    if not omega > 1e-9 * max(1.0, abs(float(y[-1]))):
        return _failed(HopfStatus.zero_frequency, m, nb, dtype, it, res)
    v = np.asarray(y[:m]) + 1j * np.asarray(y[m : 2 * m])
    return Raw(
        y[-1], y[-2], jnp.asarray(v / np.linalg.norm(v)), state.theta, state.r, res,
        jnp.asarray(it), jnp.asarray(_code(HopfStatus.successful), jnp.int32), y, C, rows,
    )  # fmt: skip


def _zero_tangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, dtype=jax.dtypes.float0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _solve(static: Static, options, guess, others) -> Raw:
    return _solve_eager(static, options, guess, others)


@_solve.defjvp
def _solve_jvp(static, options, primals, tangents):
    r"""The implicit function theorem (module docstring): $dy = -J^+\partial_pF\,dp$; the load
    and the frequency are the last two unknowns. The guess has no influence."""
    guess, others = primals
    raw = _solve(static, options, guess, others)
    zeros = Raw(*(_zero_tangent(x) for x in raw))
    if int(raw.status) != _code(HopfStatus.successful):
        return raw, zeros
    dF = _tangent_program(static, raw.y, raw.C, others, tangents[1])
    d_omega, d_value = -(raw.rows @ dF)
    return raw, zeros._replace(value=d_value, frequency=d_omega)


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
    distance under which eigenvalues count as one), `rtol`, `atol` (Newton stops when every
    step component is below ``atol + rtol`` × the unknown), `max_steps`. ``theta_eq_fn``,
    ``theta_guess`` and ``t`` of the rigid body's solver do not apply.

    **Returns** a :class:`RodHopfPoint`; a failed solve says why in ``status`` (the values
    NaN), never raises. ``jax.grad`` of ``value`` and ``frequency`` with respect to the other
    entries of ``params`` works by the implicit function theorem; the solve runs eagerly
    (compiled pieces in a Python loop), not inside ``jax.jit`` or ``jax.vmap``.
    """
    if not callable(model_fn):
        raise TypeError("model_fn must be a callable model_fn(**params) -> Rod.")
    if not isinstance(parameter, str):
        raise TypeError(f"parameter must be the name of an entry of params, got {parameter!r}.")
    _check_unused(theta_eq_fn, theta_guess, t)
    if int(steps) < 1 or int(max_steps) < 1 or not cluster > 0:
        raise ValueError("hopf_point of a rod: steps and max_steps must be >= 1, cluster > 0.")
    dtype = jnp.result_type(float)
    others = {str(k): jnp.asarray(v, dtype) for k, v in params.items() if k != parameter}
    kind = choose_kind(model_fn, others, parameter, jnp.asarray(guess, dtype), kind)
    static = Static(canonical(model_fn), parameter, kind, int(steps))
    frequency = None if frequency is None else float(frequency)
    options = (float(rtol), float(atol), int(max_steps), float(cluster), frequency)
    raw = _solve(static, options, jnp.asarray(guess, dtype), others)
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


def rod_continue_hopf(
    model_fn: Callable[..., Rod],
    params: Mapping[str, object],
    parameter: str,
    guess,
    along: str,
    values,
    *,
    method: str = "natural",
    **options,
):
    r"""The flutter boundary of a rod, the load ``parameter`` against ``along`` (what
    :func:`rbo_jax.continue_hopf` does for a rod): natural continuation, the flutter point
    (:func:`rod_hopf_point`, with ``options``) at each of ``values`` in order, started from
    the last point found (the first from ``guess``). The kind (``"auto"``) is chosen once, at
    the first point. **Returns** an :class:`xarray.Dataset` over ``along`` with the critical
    ``parameter``, ``frequency``, ``num_steps`` and ``status`` (int8 codes of
    :class:`rbo_jax.bifurcation.HopfStatus`; NaN values where it failed, and the next point
    starts from the last good one); ``attrs``: ``parameter``, ``along``, ``method``,
    ``kind``. Only ``method="natural"``; not differentiable as a whole (differentiate
    :func:`rod_hopf_point`)."""
    import xarray as xr

    if method != "natural":
        raise ValueError(f'continue_hopf of a rod: method must be "natural", got {method!r}.')
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.size < 1 or not np.all(np.isfinite(values)):
        raise ValueError("continue_hopf of a rod: values must be a 1-D array of finite values.")
    out = {f: np.full(values.size, np.nan) for f in ("value", "frequency")}
    status, steps = np.zeros(values.size, np.int8), np.zeros(values.size, np.int32)
    start, kind = guess, options.pop("kind", "auto")
    for i, b in enumerate(values):
        point = {**params, along: float(b)}
        h = rod_hopf_point(model_fn, point, parameter, start, kind=kind, **options)
        kind = h.kind
        status[i], steps[i] = int(np.asarray(enum.code(h.status))), int(h.num_steps)
        if bool(h.ok):
            out["value"][i], out["frequency"][i] = float(h.value), float(h.frequency)
            start = float(h.value)
    ds = xr.Dataset(
        {
            parameter: ((along,), out["value"]),
            "frequency": ((along,), out["frequency"]),
            "num_steps": ((along,), steps),
            "status": ((along,), status),
        },
        coords={along: values},
        attrs={"parameter": parameter, "along": along, "method": method, "kind": kind},
    )
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    return ds
