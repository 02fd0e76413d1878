r"""The flutter boundary of a rod in two parameters by pseudo-arclength continuation (what
:func:`rbo_jax.continue_hopf` does for a rod with ``method="arclength"``): it passes the
turning points of the boundary, where natural continuation fails.

With $y$ the unknowns of the flutter system of :mod:`._rod_hopf` (the eigenvector $v$, for a
collision also the chain vector $u$, the frequency $\omega$ and the critical ``parameter``
$\alpha$) and $\beta$ = ``along``, the boundary is the curve of solutions $Y = (y, \beta)$ of
$F(y; \beta) = 0$. Keller's pseudo-arclength method, as for a rigid body
(:mod:`rbo_jax.bifurcation._hopf_curve`): from $Y_k$ with unit tangent $\tau_k$, the predictor
$Y_k + s\,\tau_k$ is corrected by Newton's method on

$$F(y; \beta) = 0, \qquad \tau_k\cdot(Y - Y_k) = s,$$

whose Jacobian $\begin{pmatrix} F_y & F_\beta\\ \tau_k^T\end{pmatrix}$ stays of full column
rank where $\beta$ turns back. As in :mod:`._rod_hopf` the system is over-determined and
consistent, so each step is the least-squares step (rows equilibrated, QR), and Newton stops at
a step below the tolerances or a residual at the rounding level. $F_\beta$ is the residual's
derivative along $\partial_\beta A$, the central difference of the linearisation along the
equilibrium's tangent in $\beta$ (:func:`._rod_hopf_system._matrices`, as the load column:
it steers the iteration, the residual is exact). The new tangent solves
$\begin{pmatrix} F_y & F_\beta\\ \tau_k^T\end{pmatrix}\tau = e$ (the last unit vector),
normalised, so that it points along the previous one. The normalisation basis $C$ is the one
found at the first point, kept along the curve (it fixes the eigenvector's scale and phase as
long as the followed eigenspace does not turn orthogonal to it; a corrector that fails is
retried with a shorter step, down to ``ds_min``).

**Turning points** of the boundary in $\beta$: the $\beta$-component of the tangent changes
sign between two points; $\beta$ and $\alpha$ there are the vertices of the parabolas through
three points around it (arclength $\sigma$ along the chords, error $O(s^3)$). The first
Lyapunov coefficient and the codimension-two points of a rigid body's boundary are not computed
for rods.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .. import _programs
from ..bifurcation._hopf_curve import arclength_steps, label_boundary, progress_bar
from ..bifurcation._system import HopfStatus
from ._rod_hopf import _ROUNDING, _SUCCESSFUL, _solve
from ._rod_hopf_system import (
    Options,
    Static,
    _equilibrated,
    _jacobian_of,
    _matrices,
    _residual_of,
)

__all__ = ["rod_continue_hopf_arclength"]

MIN_COSINE = 0.9  # a step whose tangent turns further (tau_k . tau_k+1 below) is retried shorter

# The name under which `along` is passed to the model inside the corrector: it sorts before
# every other name, so that it is the first entry of the flattened parameters
# (jax.flatten_util.ravel_pytree sorts a dict's keys), whose derivative _matrices computes.
_FIRST = "\x00along"


class _Along(NamedTuple):
    """``model_fn`` with ``along`` passed as :data:`_FIRST` (hashable: part of the static
    arguments of the corrector's program)."""

    model_fn: object
    along: str

    def __call__(self, **params):
        beta = params.pop(_FIRST)
        return self.model_fn(**params, **{self.along: beta})


def _least_squares(B, R):
    """The least-squares solution of ``B x = R`` (consistent), rows equilibrated, by QR."""
    scale = _equilibrated(B)
    Q, T = jnp.linalg.qr(B / scale[:, None])
    return jax.scipy.linalg.solve_triangular(T, Q.T @ (R / scale)), jnp.max(jnp.abs(R / scale))


def _corrector(static: Static, options: Options, Y, tau, s, C, others, scale):
    """Predictor ``Y + s tau``, Newton's corrector on the bordered system, and the tangent at
    the last evaluation (module docstring). ``static.model_fn`` is an :class:`_Along`.
    Returns ``(Y, converged, num_steps, tangent, theta, r)``."""
    Y_pred = Y + s * tau
    kind = static.kind

    def bordered(V):
        y, beta = V[:-1], V[-1]
        A, dA, ok, state = _matrices(static, y[-1], {**others, _FIRST: beta}, 2, scale)

        def residual(A):
            return _residual_of(kind, A, y, C)

        F, F_beta = jax.jvp(residual, (A,), (dA[1],))  # the residual is affine in A
        J = _jacobian_of(kind, A, dA[0], y, C)
        B = jnp.concatenate([jnp.concatenate([J, F_beta[:, None]], 1), tau[None, :]], 0)
        return F, B, ok, state

    def body(c):
        V, k, _, _, _, _ = c
        F, B, ok, state = bordered(V)
        R = jnp.concatenate([F, (tau @ (V - Y_pred))[None]])
        delta, residual = _least_squares(B, -R)
        small = jnp.all(jnp.abs(delta) <= options.atol + options.rtol * jnp.abs(V))
        done = ok & (small | (residual <= _ROUNDING * jnp.finfo(V.dtype).eps))
        done = done & jnp.all(jnp.isfinite(delta))
        failed = ~ok | ~jnp.all(jnp.isfinite(delta))
        V = jnp.where(failed, V, V + delta)  # the last, small correction too
        return V, k + 1, done, failed, B, state

    _, B0, _, state0 = jax.eval_shape(bordered, Y_pred)
    false = jnp.zeros((), bool)
    state0 = jax.tree_util.tree_map(jnp.zeros_like, state0)
    init = (Y_pred, jnp.zeros((), jnp.int32), false, false, jnp.zeros(B0.shape, B0.dtype), state0)
    V, k, done, _, B, state = jax.lax.while_loop(
        lambda c: ~c[2] & ~c[3] & (c[1] < options.max_steps), body, init
    )
    tangent, _ = _least_squares(B, jnp.zeros(B.shape[0], B.dtype).at[-1].set(1.0))
    tangent = tangent / jnp.linalg.norm(tangent)
    return V, done, k, tangent, state.theta, state.r


_corrector_program = _programs.jit(_corrector, fast_compile=True)


class _Point(NamedTuple):
    """A corrected point: ``Y = [y, beta]``, its tangent, the arclength ``sigma`` along the
    chords, and the Newton steps it took."""

    Y: np.ndarray
    tau: np.ndarray
    sigma: float
    num_steps: int


class _Run(NamedTuple):
    static: Static  # its model_fn an _Along
    options: Options
    C: object
    others: dict
    scale: object


def _correct(run: _Run, point: _Point, ds: float, turn: bool = True):
    """The point at arclength ``ds`` from ``point`` along its tangent, or ``None`` where the
    corrector fails or (``turn``) the new tangent turns too far from it."""
    tau = point.tau
    dtype = run.scale.dtype
    Y, ok, k, tangent, _, _ = _corrector_program(
        run.static, run.options, jnp.asarray(point.Y, dtype), jnp.asarray(tau, dtype),
        jnp.asarray(ds, dtype), run.C, run.others, run.scale,
    )  # fmt: skip
    Y, tangent = np.asarray(Y), np.asarray(tangent)
    if not bool(ok) or (turn and float(tangent @ tau) < MIN_COSINE):
        return None
    sigma = point.sigma + float(np.linalg.norm(Y - point.Y))
    return _Point(Y, tangent, sigma, int(k))


def _turning_points(points: list[_Point]) -> list[tuple]:
    """``(beta, alpha, index)`` of every turning point in ``beta``: where the tangent's last
    component changes sign between points ``index`` and ``index + 1``; the vertices of the
    parabolas through three points around it (the chord's interpolation where they do not
    bracket it)."""
    found = []
    for i in range(len(points) - 1):
        a, b = points[i], points[i + 1]
        ta, tb = float(a.tau[-1]), float(b.tau[-1])
        if ta * tb >= 0:
            continue
        w = ta / (ta - tb)
        beta = float(a.Y[-1] + w * (b.Y[-1] - a.Y[-1]))
        alpha = float(a.Y[-2] + w * (b.Y[-2] - a.Y[-2]))
        lo = min(max(i - 1, 0), len(points) - 3)
        if lo >= 0:
            near = points[lo : lo + 3]
            sigma = np.array([p.sigma for p in near])
            c2, c1, c0 = np.polyfit(sigma, [p.Y[-1] for p in near], 2)
            if c2 != 0 and sigma[0] <= -c1 / (2 * c2) <= sigma[-1]:
                at = -c1 / (2 * c2)
                beta = float(c0 - c1 * c1 / (4 * c2))
                alpha = float(np.polyval(np.polyfit(sigma, [p.Y[-2] for p in near], 2), at))
        found.append((beta, alpha, i))
    return found


def rod_continue_hopf_arclength(
    static: Static, options: Options, guess, others: dict, along: str, values, *, ds, ds_min,
    ds_max, max_points, progress,
):  # fmt: skip
    r"""The flutter boundary by pseudo-arclength continuation (module docstring): from the
    flutter point at ``values[0]`` of ``along`` (solved as :func:`rod_hopf_point` from
    ``guess``), first towards ``values[1]``, until ``along`` leaves ``[min(values),
    max(values)]``, after ``max_points`` points, or when the step falls below ``ds_min``.
    Steps as :func:`rbo_jax.continue_hopf` documents. Returns an :class:`xarray.Dataset`."""
    values = np.asarray(values, dtype=float)
    lo, hi, ds, ds_min, ds_max = arclength_steps(values, along, ds, ds_min, ds_max)
    if int(max_points) < 1:
        raise ValueError(f"max_points must be at least 1, got {max_points}.")
    dtype = guess.dtype
    raw = _solve(static, options, guess, {**others, along: jnp.asarray(values[0], dtype)})
    if int(raw.status) != _SUCCESSFUL:
        raise ValueError(
            f"no flutter point found from the guess at {along} = {values[0]}: HopfStatus."
            f"{enum.name(enum.from_code(HopfStatus, int(raw.status)))}."
        )
    scale = jnp.where(guess != 0, jnp.abs(guess), jnp.ones_like(guess))
    run = _Run(static._replace(model_fn=_Along(static.model_fn, along)), options, raw.C,
               others, scale)  # fmt: skip
    Y0 = np.concatenate([np.asarray(raw.y), [values[0]]])
    tau0 = np.zeros_like(Y0)
    tau0[-1] = 1.0 if values[1] >= values[0] else -1.0
    first = _correct(run, _Point(Y0, tau0, 0.0, 0), 0.0, turn=False)  # its tangent
    if first is None:
        raise ValueError(f"the flutter point at {along} = {values[0]} is singular.")
    points, reason = [first._replace(num_steps=int(raw.num_steps))], "max_points"
    bar = progress_bar(progress, int(max_points), "flutter boundary")
    bar.update(1)
    while len(points) < max_points:
        new = _correct(run, points[-1], ds)
        if new is None:
            ds *= 0.5
            if ds < ds_min:
                reason = "step size below ds_min"
                break
            continue
        points.append(new)
        bar.update(1)
        ds = min(ds * 1.5, ds_max) if new.num_steps <= 3 else ds
        if not lo <= float(new.Y[-1]) <= hi:
            reason = f"{along} left [{lo}, {hi}]"
            break
    bar.close()
    return _dataset(points, _turning_points(points), static, along, reason)


def _dataset(points, special, static: Static, along: str, reason: str):
    import xarray as xr

    Y = np.stack([p.Y for p in points])
    parameter = static.parameter
    column = list(zip(*special)) if special else [()] * 3
    ds = xr.Dataset(
        {
            parameter: ("point", Y[:, -2]),
            along: ("point", Y[:, -1]),
            "frequency": ("point", Y[:, -3]),
            "num_steps": ("point", np.array([p.num_steps for p in points], np.int32)),
            "status": ("point", np.full(len(points), _SUCCESSFUL, np.int8)),
            "special_type": ("special", np.array(["turning_point"] * len(special), dtype=str)),
            "special_value": ("special", np.array(column[0], dtype=float)),
            "special_parameter": ("special", np.array(column[1], dtype=float)),
            "special_index": ("special", np.array(column[2], dtype=int)),
        },
        attrs={
            "parameter": parameter,
            "along": along,
            "method": "arclength",
            "kind": static.kind,
            "stop_reason": reason,
        },
    )
    return label_boundary(ds, parameter, along, "flutter point")
