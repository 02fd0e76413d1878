r"""The Hopf boundary in two parameters by pseudo-arclength continuation: it passes turning points
of the boundary, carries the first Lyapunov coefficient and finds the codimension-two points.

With $u = (\theta, \alpha, \omega, v_r, v_i)$ the 17 unknowns of the Hopf system $r(u; \beta) = 0$
of :mod:`._hopf` (the moment balance (4.61), $Jv_r + \omega v_i = 0$, $Jv_i - \omega v_r = 0$
with $J$ the linearization (4.63)–(4.67), and $\mathrm{Re}(w^Hq) = 1$, $\mathrm{Im}(w^Hq) = 0$),
$\alpha$ = ``parameter`` and $\beta$ = ``along``, the boundary is the curve of solutions
$U = (u, \beta) \in \mathbb R^{18}$ of the 17 equations. Keller's pseudo-arclength method follows
it: from a point $U_k$ with unit tangent $\tau_k$ (the null vector of $[r_u, r_\beta]$, oriented
along the previous tangent), the predictor $U_k + s\,\tau_k$ is corrected by Newton's method on

$$r(u; \beta) = 0, \qquad \tau_k\cdot(U - U_k) = s,$$

whose Jacobian $\begin{pmatrix} r_u & r_\beta\\ \tau_k^T\end{pmatrix}$ stays regular where
$\beta$ turns back (there $r_u$ alone, the Jacobian of natural continuation, is singular). The
new tangent solves $\begin{pmatrix} r_u & r_\beta\\ \tau_k^T\end{pmatrix}\tau = e_{18}$,
normalised. $r_u$ and $r_\beta$ are those of :mod:`._system` (directional derivatives of the
vector field, :func:`._field.jet`) with $\beta$ the last entry of the flat parameter vector,
in one small compiled program per model structure (:func:`_corrector`). After each corrected
point the normalisation vector becomes $w = v/|v|^2$ (so that $w^Hv = 1$ there), and the Hopf
program of :mod:`._system` started at the point (one Newton step at fixed $\beta$) gives the
first Lyapunov coefficient $\ell_1$, the transversality and the status.

**Special points** between consecutive points $U_k$, $U_{k+1}$ (arclength $\sigma$ measured
along the chords):

- **turning point** of the boundary in $\beta$: the $\beta$-component of the tangent changes
  sign; located by the vertex of the parabola $\beta(\sigma)$ through three points around it
  (error $O(s^3)$), as the folds of :mod:`._equilibria`;
- **Bautin point** (generalised Hopf): $\ell_1$ changes sign; located by linear interpolation
  of $\ell_1(\sigma)$ (:func:`_locate_bautin`, error $O(s^2)$);
- **Bogdanov–Takens point**: the frequency tends to 0 (a double zero eigenvalue). Along the
  solution curve of the Hopf system $\omega$ is a regular coordinate through such a point (the
  curve goes on with $-\omega$ and the conjugate eigenvector, retracing the boundary), so
  $\omega$, not $\omega^2$, is linear in the arclength, while $\omega^2$ is linear in the
  distance along the boundary in the $(\alpha, \beta)$ plane. It is reported when $\omega$
  changes sign between two points, when the Hopf solve returns ``zero_frequency``, or when
  $|\omega|$ falls below ``1e-3`` of the Jacobian's scale $\max|J_{ij}|$, at the zero of the
  line $\omega(\sigma)$ through the last two points; the branch ends there.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .._programs import jit
from ._field import jet
from ._hopf import HopfStatus, Raw, Static, solution
from ._system import _Problem, _rows, _small, _system, normalisation_vector

__all__ = ["continue_hopf_arclength"]

_SUCCESSFUL = int(np.asarray(enum.code(HopfStatus.successful)))
_ZERO_FREQUENCY = int(np.asarray(enum.code(HopfStatus.zero_frequency)))
SMALL_FREQUENCY = 1e-3  # |omega| below this times max|J|: the end at a Bogdanov-Takens point
MIN_COSINE = 0.9  # a step whose tangent turns further (tau_k . tau_k+1 below) is retried shorter


def _derivatives(problem: _Problem, p, X, w):
    r"""$r$, $r_u$, $r_\beta$ and $\max|J_{ij}|$ at $U = X$ (``X = [u, beta]``): the rows of
    :func:`._system._rows` evaluated one per iteration of a loop (one traced copy of
    :func:`._field.jet`, as in the Hopf program), then :func:`._system._system`."""
    dtype, m, n_p = problem.dtype, problem.m, problem.n_p
    u = X[:17]
    y = jnp.concatenate([u[:3], jnp.zeros(3, dtype), u[3:4], p, X[17:]])
    rows = _rows(m, u[5:11], u[11:17], n_p)

    def body(i, carry):
        _, D1, D2 = carry
        f0, d1, d2, _ = jet(problem.field, y, rows[i, 0], rows[i, 1], rows[i, 2])
        put = jax.lax.dynamic_update_index_in_dim
        return f0, put(D1, d1, i, 0), put(D2, d2, i, 0)

    zeros = jnp.zeros((rows.shape[0], 6), dtype)
    f0, D1, D2 = jax.lax.fori_loop(0, rows.shape[0], body, (jnp.zeros(6, dtype), zeros, zeros))
    r, Ju, Jp, J, _, _ = _system(u, w, f0, D1, D2, n_p)
    return r, Ju, Jp[:, -1], jnp.max(jnp.abs(J)), (f0, D1, D2)


def _bordered(Ju, Jb, tau):
    return jnp.concatenate([jnp.concatenate([Ju, Jb[:, None]], axis=1), tau[None, :]])


@functools.partial(jit, small=True)
def _corrector(static: Static, t, p, X, tau, s, w, max_newton):
    r"""Predictor $X + s\tau$, Newton's corrector on the bordered system (module docstring),
    the new normalisation vector $w = v/|v|^2$ and the new tangent (at the last evaluation,
    whose correction is below the tolerance, with the new $w$). Returns ``(X, converged,
    num_steps, tangent, w, scale)``."""
    problem = _Problem(  # its parameter vector: p and beta, the last unknown
        static.model_fn, static.parameter, static.names, static.shapes,
        static.rtol, static.atol, static.max_steps, jnp.concatenate([p, X[17:]]), t,
    )  # fmt: skip
    dtype = p.dtype
    X_pred = X + s * tau
    e = jnp.zeros(18, dtype).at[17].set(1.0)

    def body(carry):
        V, k, _, _, _ = carry
        r, Ju, Jb, scale, D = _derivatives(problem, p, V, w)
        R = jnp.concatenate([r, (tau @ (V - X_pred))[None]])
        delta = jnp.linalg.solve(_bordered(Ju, Jb, tau), -R)
        done = _small(delta, V, static.rtol, static.atol) & jnp.all(jnp.isfinite(delta))
        return V + delta, k + 1, done, scale, (V, D)

    zeros = jnp.zeros((18 + 3 * problem.n_p, 6), dtype)
    init = (X_pred, jnp.asarray(0), jnp.asarray(False), jnp.asarray(0.0, dtype))
    init = init + ((X_pred, (jnp.zeros(6, dtype), zeros, zeros)),)
    V, k, done, scale, (V_last, D) = jax.lax.while_loop(
        lambda c: ~c[2] & (c[1] < max_newton), body, init
    )
    converged = done & jnp.all(jnp.isfinite(V))
    w_new = normalisation_vector(V)
    _, Ju, Jp, _, _, _ = _system(V_last[:17], w_new, *D, problem.n_p)
    tangent = jnp.linalg.solve(_bordered(Ju, Jp[:, -1], tau), e)
    return V, converged, k, tangent / jnp.linalg.norm(tangent), w_new, scale


class _Point(NamedTuple):
    """A corrected point: ``X = [u, beta]``, the tangent, the normalisation vector, the
    arclength ``sigma`` (along the chords) and the Hopf program's outputs."""

    X: np.ndarray
    tau: np.ndarray
    w: np.ndarray
    sigma: float
    scale: float
    raw: Raw


class _Run(NamedTuple):
    static: Static
    t: object
    p: object
    beta0: float
    direction: float
    bounds: tuple[float, float]
    max_newton: int


def _hopf_at(run: _Run, X, w) -> Raw:
    """The Hopf program at the point ``X`` (fixed beta), warm-started: l1, transversality,
    status."""
    q = jnp.concatenate([run.p, jnp.asarray(X[17:])])
    X = jnp.asarray(X)
    return solution(run.static, q, X[3], X[:3], run.t, X[:17], jnp.asarray(w), jnp.asarray(True))


def _first_point(run: _Run, guess, theta_guess) -> _Point:
    """The Hopf point at beta0 (cold start from ``guess``, as :func:`rbo_jax.hopf_point`) and
    its tangent oriented along ``run.direction`` in beta."""
    beta0 = run.beta0
    q = jnp.concatenate([run.p, jnp.asarray([beta0], dtype=run.p.dtype)])
    dtype = run.p.dtype
    raw = solution(
        run.static, q, guess, theta_guess, run.t, jnp.zeros(17, dtype), jnp.zeros(12, dtype),
        jnp.asarray(False),
    )  # fmt: skip
    status = int(raw.status)
    if status != _SUCCESSFUL:
        raise ValueError(
            f"no Hopf point found from the guess at {run.static.names[-1]} = {beta0}: "
            f"HopfStatus.{enum.name(enum.from_code(HopfStatus, status))}."
        )
    u = np.asarray(raw.u)
    w = np.asarray(normalisation_vector(u))
    X = np.concatenate([u, [beta0]])
    tau0 = np.zeros(18)
    tau0[17] = run.direction
    X1, ok, _, tau, w, scale = _corrector(
        run.static, run.t, run.p, jnp.asarray(X), jnp.asarray(tau0), jnp.asarray(0.0, dtype),
        jnp.asarray(w), run.max_newton,
    )  # fmt: skip
    if not bool(ok):
        raise ValueError(f"the Hopf point at {run.static.names[-1]} = {beta0} is singular.")
    raw = _hopf_at(run, np.asarray(X1), w)
    return _Point(np.asarray(X1), np.asarray(tau), np.asarray(w), 0.0, float(scale), raw)


def _advance(run: _Run, point: _Point, ds: float):
    """One step of length ``ds`` from ``point``: the new point and the number of Newton steps,
    or ``(None, 0)`` when the corrector, the tangent's turn or the Hopf program fails."""
    X, ok, k, tau, w, scale = _corrector(
        run.static, run.t, run.p, jnp.asarray(point.X), jnp.asarray(point.tau),
        jnp.asarray(ds, dtype=run.p.dtype), jnp.asarray(point.w), run.max_newton,
    )  # fmt: skip
    X, tau = np.asarray(X), np.asarray(tau)
    if not bool(ok) or float(tau @ point.tau) < MIN_COSINE:
        return None, 0
    raw = _hopf_at(run, X, w)
    if int(raw.status) not in (_SUCCESSFUL, _ZERO_FREQUENCY):
        return None, 0
    sigma = point.sigma + float(np.linalg.norm(X - point.X))
    return _Point(X, tau, np.asarray(w), sigma, float(scale), raw), int(k)


def _frequency_test(run_sign: float, point: _Point) -> float:
    """The Bogdanov-Takens test function: the signed frequency, positive along the boundary."""
    return run_sign * float(point.X[4])


def _on_line(a: _Point, b: _Point, fa: float, fb: float):
    """The point where the line through ``(a.sigma, fa)``, ``(b.sigma, fb)`` crosses zero:
    ``(alpha, beta, weight)`` (``weight`` 0 at ``a``, 1 at ``b``, above 1 beyond ``b``)."""
    weight = fa / (fa - fb) if fa != fb else 1.0
    X = a.X + weight * (b.X - a.X)
    return float(X[3]), float(X[17]), weight


def _locate_bautin(model_fn, params, parameter, along, before: _Point, after: _Point):
    r"""The Bautin point (generalised Hopf, $\ell_1 = 0$) between two points of the boundary
    whose first Lyapunov coefficients have opposite signs: :func:`rbo_jax.bautin_point` started
    from the linear interpolation of $\ell_1$ along the chord, ``(alpha, beta)``; the
    interpolation itself (error $O(s^2)$) if that solve fails. ``before.X``/``after.X`` are
    ``[θ(3), α, ω, v_r(6), v_i(6), β]`` and ``before.raw.first_lyapunov`` its $\ell_1$."""
    from ._bautin import bautin_point

    fa, fb = float(before.raw.first_lyapunov), float(after.raw.first_lyapunov)
    alpha, beta, _ = _on_line(before, after, fa, fb)
    point = bautin_point(
        model_fn,
        params,
        (parameter, along),
        (alpha, beta),
        theta_guess=np.asarray(before.X[:3]),
    )
    if bool(point.ok):
        return float(point.value[0]), float(point.value[1])
    return alpha, beta


def _bogdanov_takens(near: list, f: list):
    r"""The end of the boundary where the frequency tends to 0, from the last (up to three)
    points ``near`` of the branch, all with $\omega > 0$ (``f``): $\sigma_*$ where the line
    $\omega(\sigma)$ through the last two vanishes, $\alpha$ and $\beta$ at $\sigma_*$ on the
    parabolas through the three (both have a vertex there: the solution curve of the Hopf
    system retraces the boundary with $-\omega$ beyond it, module docstring)."""
    if len(near) < 2:
        X = near[-1].X
        return ("bogdanov_takens", float(X[17]), float(X[3]), 0, 0.0, np.nan)
    (a, b), (fa, fb) = near[-2:], f[-2:]
    at = b.sigma if fa == fb else a.sigma + fa * (b.sigma - a.sigma) / (fa - fb)
    at = max(at, b.sigma)  # a frequency that does not decrease: the end is the last point
    sigma = np.array([p.sigma for p in near])

    def fit(values):
        return float(np.polyval(np.polyfit(sigma, values, len(near) - 1), at))

    alpha, beta = fit([p.X[3] for p in near]), fit([p.X[17] for p in near])
    return ("bogdanov_takens", beta, alpha, -1, 0.0, np.nan)


def _detect(context, special, points: list, new: _Point, sign: float):
    """Special points between the last point and ``new`` (module docstring): appends
    ``(type, beta, alpha, index, frequency, l1)`` to ``special``. Returns whether the branch
    ends at a Bogdanov-Takens point, and whether ``new`` is kept."""
    old, index = points[-1], len(points) - 1
    f_new = _frequency_test(sign, new)
    zero = int(new.raw.status) == _ZERO_FREQUENCY or f_new <= 0
    if zero or abs(f_new) < SMALL_FREQUENCY * new.scale:
        near = (points + ([] if zero else [new]))[-3:]
        special.append(_bogdanov_takens(near, [_frequency_test(sign, p) for p in near]))
        return True, not zero
    if float(old.tau[17]) * float(new.tau[17]) < 0:
        _, beta, w = _on_line(old, new, float(old.tau[17]), float(new.tau[17]))
        alpha = float(old.X[3] + w * (new.X[3] - old.X[3]))
        special.append(("turning_point", beta, alpha, index, np.nan, np.nan))
    l1_old, l1_new = float(old.raw.first_lyapunov), float(new.raw.first_lyapunov)
    if l1_old * l1_new < 0:
        alpha, beta = _locate_bautin(*context, old, new)
        w = l1_old / (l1_old - l1_new)
        frequency = abs(float(old.X[4] + w * (new.X[4] - old.X[4])))
        special.append(("bautin", beta, alpha, index, frequency, 0.0))
    return False, True


def _refine_turning_points(special, points):
    """A turning point's beta as the vertex of the parabola beta(sigma) through three points
    around it (error O(s^3)); alpha, the frequency and l1 from the parabolas through the same
    points, at the vertex."""
    for i, item in enumerate(special):
        kind, index = item[0], item[3]
        lo = min(max(index - 1, 0), len(points) - 3)
        if kind != "turning_point" or lo < 0:
            continue
        near = points[lo : lo + 3]
        sigma = np.array([p.sigma for p in near])
        a, b, c = np.polyfit(sigma, [p.X[17] for p in near], 2)
        if a == 0 or not sigma[0] <= -b / (2 * a) <= sigma[-1]:
            continue
        at = -b / (2 * a)

        def fit(values):
            return float(np.polyval(np.polyfit(sigma, values, 2), at))

        alpha = fit([p.X[3] for p in near])
        frequency = fit([abs(p.X[4]) for p in near])
        l1 = fit([float(p.raw.first_lyapunov) for p in near])
        special[i] = (kind, float(c - b * b / (4 * a)), alpha, index, frequency, l1)


def progress_bar(progress: bool, total: int, desc: str = "Hopf boundary"):
    """A tqdm bar of ``total`` points, or one that does nothing."""
    from ._equilibria import _NoBar

    if not progress:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="point")


def _follow(run: _Run, context, first: _Point, ds, ds_min, ds_max, max_points, progress):
    """The continuation loop: step control (×1.5 after corrections of at most 3 Newton steps,
    ×0.5 after failures), detection, stopping rules. Returns ``(points, special, reason)``."""
    points, special = [first], []
    sign = 1.0 if float(first.X[4]) >= 0 else -1.0
    lo, hi = run.bounds
    reason = "max_points"
    bar = progress_bar(progress, max_points)
    bar.update(1)
    while len(points) < max_points:
        new, k = _advance(run, points[-1], ds)
        if new is None:
            ds *= 0.5
            if ds < ds_min:
                reason = "step size below ds_min"
                break
            continue
        end, keep = _detect(context, special, points, new, sign)
        if keep:
            points.append(new)
            bar.update(1)
        if end:
            special[-1] = special[-1][:3] + (len(points) - 1,) + special[-1][4:]
            reason = "Bogdanov-Takens point: the frequency tends to 0"
            break
        ds = min(ds * 1.5, ds_max) if k <= 3 else ds
        if not lo <= float(new.X[17]) <= hi:
            reason = f"{context[3]} left [{lo}, {hi}]"
            break
    bar.close()
    _refine_turning_points(special, points)
    return points, special, reason


def _dataset(points, special, parameter, along, reason):
    import xarray as xr

    X = np.stack([p.X for p in points])
    raws = [p.raw for p in points]
    special = sorted(special, key=lambda s: s[3])
    column = list(zip(*special)) if special else [()] * 6
    ds = xr.Dataset(
        {
            parameter: ("point", X[:, 3]),
            along: ("point", X[:, 17]),
            "frequency": ("point", np.abs(X[:, 4])),
            "first_lyapunov": ("point", np.array([float(r.first_lyapunov) for r in raws])),
            "transversality": ("point", np.array([float(r.transversality) for r in raws])),
            "theta": (("point", "component"), X[:, :3]),
            "status": ("point", np.array([int(r.status) for r in raws], dtype=np.int8)),
            "special_type": ("special", np.array(column[0], dtype=str)),
            "special_value": ("special", np.array(column[1], dtype=float)),
            "special_parameter": ("special", np.array(column[2], dtype=float)),
            "special_index": ("special", np.array(column[3], dtype=int)),
            "special_frequency": ("special", np.array(column[4], dtype=float)),
            "special_first_lyapunov": ("special", np.array(column[5], dtype=float)),
        },
        coords={"component": ["x", "y", "z"]},
        attrs={
            "parameter": parameter,
            "along": along,
            "method": "arclength",
            "stop_reason": reason,
        },
    )
    return label_boundary(ds, parameter, along)


def arclength_steps(values, along: str, ds, ds_min, ds_max):
    """The bounds and steps of a boundary's arclength continuation over ``values`` of
    ``along`` (checked): ``(lo, hi, ds, ds_min, ds_max)``, the steps by default 0.02, 1e-6 and
    0.1 of the span ``hi - lo`` (:func:`rbo_jax.continue_hopf`)."""
    values = np.asarray(values, dtype=float)
    if values.size < 2 or not values.max() > values.min():
        raise ValueError(
            f'method="arclength" needs values of {along!r} with at least two distinct entries '
            "(the start values[0], the first direction towards values[1], the bounds "
            "min(values), max(values))."
        )
    lo, hi = float(values.min()), float(values.max())
    span = hi - lo
    ds = 0.02 * span if ds is None else float(ds)
    ds_max = max(0.1 * span, ds) if ds_max is None else float(ds_max)
    ds_min = 1e-6 * span if ds_min is None else float(ds_min)
    if not (0 < ds_min <= ds <= ds_max):
        raise ValueError(f"need 0 < ds_min <= ds <= ds_max, got {ds_min}, {ds}, {ds_max}.")
    return lo, hi, ds, ds_min, ds_max


def label_boundary(ds, parameter: str, along: str, point: str = "Hopf point"):
    """The attributes of a boundary of :func:`continue_hopf_arclength` (and of a rod's,
    :mod:`rbo_jax.lattice._rod_hopf_arclength`): the status's flag meanings, long names."""
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    ds[parameter].attrs["long_name"] = f"critical {parameter} ({point})"
    ds["special_value"].attrs["long_name"] = f"{along} at the special point"
    ds["special_parameter"].attrs["long_name"] = f"{parameter} at the special point"
    return ds


def continue_hopf_arclength(
    static: Static, context, others, guess, values, theta_guess, t, *, ds, ds_min, ds_max,
    max_points, progress,
):  # fmt: skip
    r"""The Hopf boundary by pseudo-arclength continuation (module docstring), for
    :func:`rbo_jax.continue_hopf` with ``method="arclength"``: from the Hopf point at
    ``values[0]`` (``static`` names the parameters, the ``along`` parameter last; ``context``
    is ``(model_fn, params, parameter, along)``), first towards ``values[1]``, until β leaves
    ``[min(values), max(values)]``."""
    dtype = jnp.result_type(float)
    parts = [jnp.ravel(v) for v in others.values()]
    p = jnp.concatenate(parts) if parts else jnp.zeros(0, dtype)
    values = np.asarray(values, dtype=float)
    lo, hi, ds, ds_min, ds_max = arclength_steps(values, static.names[-1], ds, ds_min, ds_max)
    run = _Run(
        static, jnp.asarray(t, dtype=dtype), p, float(values[0]),
        1.0 if values[1] >= values[0] else -1.0, (lo, hi), max(int(static.max_steps), 1),
    )  # fmt: skip
    first = _first_point(run, jnp.asarray(guess, dtype=dtype), theta_guess)
    points, special, reason = _follow(run, context, first, ds, ds_min, ds_max, max_points, progress)
    return _dataset(points, special, context[2], context[3], reason)
