r"""The flutter boundary in two parameters by pseudo-arclength continuation, for every model: it
passes turning points of the boundary, carries the first Lyapunov coefficient and finds the
codimension-two points.

With $u$ the unknowns of the flutter system $r(u; \beta) = 0$ of :mod:`._hopf_system` (the
configuration's increments $q$, $\alpha$ = ``parameter``, $\omega$, the eigenvector, for a
collision the Jordan chain) and $\beta$ = ``along``, the boundary is the curve of solutions
$U = (u, \beta)$. Keller's pseudo-arclength method follows it: from a point $U_k$ with unit
tangent $\tau_k$, the predictor $U_k + s\,\tau_k$ is corrected by Newton's method (the one loop
of :mod:`rbo_jax.solvers`) on

$$r(u; \beta) = 0, \qquad \tau_k\cdot(U - U_k) = s,$$

whose Jacobian $\begin{pmatrix} r_u & r_\beta\\ \tau_k^T\end{pmatrix}$ keeps full column rank
where $\beta$ turns back (there $r_u$ alone, the Jacobian of natural continuation, is
singular): least-squares steps, rows equilibrated, $r_u$ as the flutter program builds it
(:func:`._hopf_system.evaluate`) and $r_\beta$ by forward mode. The new tangent solves
$\begin{pmatrix} r_u & r_\beta\\ \tau_k^T\end{pmatrix}\tau = e$ (the last unit vector),
normalised. Each corrected point is then handed to the flutter program, warm-started there (its
chart moved to the point's equilibrium, one Newton step at fixed $\beta$), which gives the
point's status, the first Lyapunov coefficient $\ell_1$ and the transversality. The step
control and the detection are the continuation's (:mod:`rbo_jax.continuation`).

**Special points** between consecutive points $U_k$, $U_{k+1}$ (arclength $\sigma$ along the
chords):

- **turning point** of the boundary in $\beta$: the $\beta$-component of the tangent changes
  sign; located by the vertex of the parabola $\beta(\sigma)$ through three points around it
  (error $O(s^3)$), as the folds of equilibria;
- **Bautin point** (generalised Hopf): $\ell_1$ changes sign; located by
  :func:`rbo_jax.bautin_point` from the linear interpolation of $\ell_1(\sigma)$ (the
  interpolation itself, error $O(s^2)$, where that solve fails);
- **Bogdanov–Takens point**: the frequency tends to 0 (a double zero eigenvalue). Along the
  solution curve of the flutter system $\omega$ is a regular coordinate through such a point
  (the curve goes on with $-\omega$ and the conjugate eigenvector, retracing the boundary), so
  $\omega$, not $\omega^2$, is linear in the arclength. It is reported when $\omega$ changes
  sign between two points, when the flutter program returns ``zero_frequency``, or when
  $|\omega|$ falls below ``1e-3`` of the largest frequency met along the boundary, at the zero
  of the line $\omega(\sigma)$ through the last two points; the branch ends there.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from .._programs import jit
from ..continuation import Steps, crossing, follow, parabola_vertex, sign_changes
from ..solvers import converged, equilibrated_lstsq, iterate
from ._hopf import cold_start, prepare, solution
from ._hopf_system import HopfStatus, Layout, Spec, code_of, evaluate, residual

__all__ = ["arclength_steps", "continue_hopf_arclength", "label_boundary"]

SMALL_FREQUENCY = 1e-3  # |omega| below this times the largest met: a Bogdanov-Takens end
MAX_OVERSHOOTS = 12  # steps past the Bogdanov-Takens point retried shorter before it is taken
BOGDANOV_TAKENS = "Bogdanov-Takens point: the frequency tends to 0"
MIN_COSINE = 0.9  # a step whose tangent turns further (tau_k . tau_k+1 below) is retried shorter
_ROUNDING = 64  # machine epsilons: an equilibrated residual at the rounding level has converged


def _system(spec: Spec, layout: Layout, X, config, C, p, t):
    """``(r, [r_u, r_beta])`` at ``X = [u, beta]``: the flutter system with beta as the last
    of the flat parameters."""
    u, beta = X[:-1], X[-1]
    q = jnp.concatenate([p, beta[None]])
    r, Ju, _ = evaluate(spec, layout, u, config, C, q, t)

    def of_beta(b):
        return residual(spec, layout, u, config, C, jnp.concatenate([p, b[None]]), t)

    _, r_beta = jax.jvp(of_beta, (beta,), (jnp.ones_like(beta),))
    return r, jnp.concatenate([Ju, r_beta[:, None]], axis=1)


def _corrector(spec: Spec, layout: Layout, config, C, p, t, X, tau, s):
    r"""Predictor $X + s\tau$, Newton's corrector on the bordered system (module docstring)
    and the new tangent at the last evaluation. Returns ``(X, converged, num_steps,
    tangent)``."""
    X_pred = X + s * tau
    floor = _ROUNDING * float(jnp.finfo(X.dtype).eps)

    def bordered(V):
        r, B = _system(spec, layout, V, config, C, p, t)
        R = jnp.concatenate([r, (tau @ (V - X_pred))[None]])
        return R, jnp.concatenate([B, tau[None, :]], axis=0)

    def step(V, _):
        R, B = bordered(V)
        scale = jnp.linalg.norm(B, axis=1)
        scale = jnp.where(scale > 0, scale, 1.0)
        delta = equilibrated_lstsq(B, -R)
        finite = jnp.all(jnp.isfinite(delta))
        done = converged(delta, V, spec.rtol, spec.atol) | (jnp.max(jnp.abs(R / scale)) <= floor)
        new = jnp.where(finite, V + delta, V)
        return new, B, jnp.where(finite, jnp.where(done, 0, -1), 1)

    # the bordered Jacobian's shape from the system's rows (nothing traced for it)
    B0 = jnp.zeros((layout.rows(C.shape[1]) + 1, X.shape[0]), X.dtype)
    V, B, code, k = iterate(step, X_pred, B0, max_steps=spec.max_steps, exhausted=1)
    tangent = equilibrated_lstsq(B, jnp.zeros(B.shape[0], B.dtype).at[-1].set(1.0))
    return V, code == 0, k, tangent / jnp.linalg.norm(tangent)


_corrector_program = jit(_corrector, fast_compile=True)


class _Point(NamedTuple):
    """A point of the boundary: ``X = [u, beta]`` (its $q$ zero: the chart at ``config``),
    the configuration, the normalisation basis, the tangent, the arclength ``sigma`` and the
    flutter program's outputs there."""

    X: np.ndarray
    config: object
    C: object
    tau: np.ndarray
    sigma: float
    raw: object


class _Run(NamedTuple):
    spec: Spec
    layout: Layout
    model: object
    p: object  # the flat parameters without beta
    t: object
    direction: float
    bounds: tuple[float, float]
    frequency: float | None  # the pair to start from (hopf_point's frequency)


def _at(run: _Run, X, config, C, alpha0):
    """The flutter program warm-started at ``X`` (fixed beta): the point in its own chart,
    with its status, l1 and transversality."""
    q = jnp.concatenate([run.p, jnp.asarray(X[-1:])])
    y, raw = solution(run.spec, q, run.t, alpha0, config, jnp.asarray(True), jnp.asarray(X[:-1]), C,
                      run.frequency)  # fmt: skip
    return y, raw


def _first_point(run: _Run, alpha0, config, beta0):
    spec, layout = run.spec, run.layout
    u0, C0 = cold_start(spec, run.model, run.p.dtype)
    q = jnp.concatenate([run.p, jnp.asarray([beta0], run.p.dtype)])
    (config, u, C), raw = solution(spec, q, run.t, alpha0, config, jnp.asarray(False), u0, C0,
                                   run.frequency)  # fmt: skip
    if int(raw.status) != 0:
        raise ValueError(
            f"no flutter point found from the guess at {spec.names[-1]} = {beta0}: "
            f"HopfStatus.{enum.name(enum.from_code(HopfStatus, int(raw.status)))}."
        )
    X = np.concatenate([np.asarray(u), [beta0]])
    tau0 = np.zeros_like(X)
    tau0[-1] = run.direction
    _, ok, _, tau = _corrector_program(spec, layout, config, C, run.p, run.t, jnp.asarray(X),
                                       jnp.asarray(tau0), jnp.asarray(0.0, X.dtype))  # fmt: skip
    if not bool(ok):
        raise ValueError(f"the flutter point at {spec.names[-1]} = {beta0} is singular.")
    return _Point(X, config, C, np.asarray(tau), 0.0, raw)


def _advance(run: _Run, point: _Point, ds: float):
    """One step of length ``ds``: the new point and the number of Newton steps, or ``(None,
    0)`` where the corrector, the tangent's turn or the flutter program fails."""
    X, ok, k, tau = _corrector_program(
        run.spec, run.layout, point.config, point.C, run.p, run.t, jnp.asarray(point.X),
        jnp.asarray(point.tau), jnp.asarray(ds, point.X.dtype),
    )  # fmt: skip
    X, tau = np.asarray(X), np.asarray(tau)
    if not bool(ok) or float(tau @ point.tau) < MIN_COSINE:
        return None, 0
    (config, u, C), raw = _at(run, X, point.config, point.C, X[run.layout.m])
    if int(raw.status) not in (0, code_of(HopfStatus.zero_frequency)):
        return None, 0
    X = np.concatenate([np.asarray(u), X[-1:]])
    sigma = point.sigma + float(np.linalg.norm(X - point.X))
    return _Point(X, config, C, tau, sigma, raw), int(k)


def _l1(point: _Point) -> float:
    return float(point.raw.first_lyapunov)


def _locate_bautin(context, before: _Point, after: _Point, m: int):
    r"""The Bautin point between two points whose $\ell_1$ have opposite signs:
    :func:`rbo_jax.bautin_point` from the linear interpolation of $\ell_1$ along the chord,
    ``(alpha, beta)``; the interpolation itself where that solve fails."""
    from ._bautin import bautin_point

    model_fn, params, parameter, along, options = context
    X, _ = crossing(_l1(before), _l1(after), before.X, after.X)
    alpha, beta = float(X[m]), float(X[-1])
    point = bautin_point(model_fn, params, (parameter, along), (alpha, beta),
                         theta_guess=before.config, theta_eq_fn=options["theta_eq_fn"])  # fmt: skip
    if bool(point.ok):
        return float(point.value[0]), float(point.value[1])
    return alpha, beta


def _bogdanov_takens(near: list, m: int):
    r"""The end of the boundary where the frequency tends to 0, from the last (up to three)
    points ``near`` (all with $\omega > 0$): $\sigma_*$ where the line $\omega(\sigma)$ through
    the last two vanishes, $\alpha$ and $\beta$ there on the parabolas through the three."""
    if len(near) < 2:
        X = near[-1].X
        return ("bogdanov_takens", float(X[-1]), float(X[m]), 0, 0.0, np.nan)
    a, b = near[-2:]
    fa, fb = float(a.X[m + 1]), float(b.X[m + 1])
    at = b.sigma if fa == fb else a.sigma + fa * (b.sigma - a.sigma) / (fa - fb)
    at = max(at, b.sigma)  # a frequency that does not decrease: the end is the last point
    sigma = np.array([p.sigma for p in near])

    def fit(values):
        return float(np.polyval(np.polyfit(sigma, values, len(near) - 1), at))

    alpha, beta = fit([p.X[m] for p in near]), fit([p.X[-1] for p in near])
    return ("bogdanov_takens", beta, alpha, -1, 0.0, np.nan)


def _accept(run: _Run, special: list):
    """Whether a new point joins the boundary, and whether the boundary ends there (module
    docstring: a Bogdanov-Takens point, or beta leaving its bounds). A step whose frequency
    vanished or changed sign overshot the Bogdanov-Takens point: it is refused (the step
    halves, :func:`rbo_jax.continuation.follow`) so that the boundary comes to the end with
    steps short enough for the extrapolation, at most ``MAX_OVERSHOOTS`` times."""
    m, lo, hi = run.layout.m, *run.bounds
    largest, overshoots = [0.0], [0]

    def accept(points, new):
        largest[0] = max(largest[0], *(abs(float(p.X[m + 1])) for p in points))
        omega = float(new.X[m + 1]) * np.sign(float(points[0].X[m + 1]))
        zero = int(new.raw.status) == code_of(HopfStatus.zero_frequency) or omega <= 0
        if zero and overshoots[0] < MAX_OVERSHOOTS:
            overshoots[0] += 1
            return False, None
        if zero or abs(omega) < SMALL_FREQUENCY * largest[0]:
            special.append(bogdanov_takens(points + ([] if zero else [new])))
            return not zero, BOGDANOV_TAKENS
        if not lo <= float(new.X[-1]) <= hi:
            return True, f"{run.spec.names[-1]} left [{lo}, {hi}]"
        return True, None

    def bogdanov_takens(points):
        item = _bogdanov_takens(points[-3:], m)
        return item[:3] + (len(points) - 1,) + item[4:]  # the last point of the boundary

    accept.overshot = lambda: overshoots[0] > 0
    accept.end = bogdanov_takens
    return accept


def _special(context, points: list, m: int) -> list:
    """Turning points and Bautin points between consecutive points (module docstring):
    ``(type, beta, alpha, index, frequency, l1)``."""
    special = []
    for i in sign_changes([p.tau[-1] for p in points]):
        X, _ = crossing(points[i].tau[-1], points[i + 1].tau[-1], points[i].X, points[i + 1].X)
        item = ("turning_point", float(X[-1]), float(X[m]), i, np.nan, np.nan)
        lo = min(max(i - 1, 0), len(points) - 3)
        if lo >= 0:
            near = points[lo : lo + 3]
            others = ([p.X[m] for p in near], [abs(p.X[m + 1]) for p in near],
                      [_l1(p) for p in near])  # fmt: skip
            vertex = parabola_vertex([p.sigma for p in near], [p.X[-1] for p in near], others)
            if vertex is not None:
                beta, (alpha, frequency, l1) = vertex
                item = ("turning_point", beta, alpha, i, frequency, l1)
        special.append(item)
    for i in sign_changes([_l1(p) for p in points]):
        alpha, beta = _locate_bautin(context, points[i], points[i + 1], m)
        X, _ = crossing(_l1(points[i]), _l1(points[i + 1]), points[i].X, points[i + 1].X)
        special.append(("bautin", beta, alpha, i, abs(float(X[m + 1])), 0.0))
    return special


def arclength_steps(values, along: str, ds, ds_min, ds_max):
    """The bounds and steps of a boundary's arclength continuation over ``values`` of
    ``along`` (checked): ``(lo, hi, steps)``, the steps by default 0.02, 1e-6 and 0.1 of the
    span ``hi - lo`` (:func:`rbo_jax.continue_hopf`)."""
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
    return lo, hi, Steps(ds, ds_min, ds_max).check("continue_hopf")


def label_boundary(ds, parameter: str, along: str):
    """The attributes of a boundary's Dataset: the status's flag meanings, long names."""
    ds["status"].attrs["flag_meanings"] = " ".join(enum.names(HopfStatus))
    ds[parameter].attrs["long_name"] = f"critical {parameter} (flutter point)"
    ds["special_value"].attrs["long_name"] = f"{along} at the special point"
    ds["special_parameter"].attrs["long_name"] = f"{parameter} at the special point"
    return ds


def continue_hopf_arclength(model_fn, params, parameter, guess, along, values, options, *, ds,
                            ds_min, ds_max, max_points, progress):  # fmt: skip
    r"""The flutter boundary by pseudo-arclength continuation (module docstring), for
    :func:`rbo_jax.continue_hopf` with ``method="arclength"``: from the flutter point at
    ``values[0]``, first towards ``values[1]``, until β leaves ``[min(values),
    max(values)]``."""
    lo, hi, steps = arclength_steps(values, along, ds, ds_min, ds_max)
    if max_points < 1:
        raise ValueError(f"max_points must be at least 1, got {max_points}.")
    spec, model, p, alpha0, config, t = prepare(model_fn, params, parameter, guess, options,
                                                along=(along, values[0]))  # fmt: skip
    layout = Layout(model.free_size(), spec.kind)
    direction = 1.0 if values[1] >= values[0] else -1.0
    run = _Run(spec, layout, model, jnp.asarray(p[:-1]), t, direction, (lo, hi),
               options["frequency"])  # fmt: skip
    first = _first_point(run, alpha0, config, float(values[0]))
    end_points: list = []
    accept = _accept(run, end_points)
    points, reason = follow(lambda point, ds: _advance(run, point, ds), first, steps,
                            max_points=max_points, accept=accept, progress=progress,
                            desc="flutter boundary")  # fmt: skip
    if reason == "step size below ds_min" and accept.overshot():  # halved to the end
        end_points.append(accept.end(points))
        reason = BOGDANOV_TAKENS
    context = (model_fn, {k: v for k, v in params.items() if k != parameter}, parameter, along,
               options)  # fmt: skip
    special = sorted(_special(context, points, layout.m) + end_points, key=lambda s: s[3])
    return _dataset(points, special, spec, model, along, reason)


def _dataset(points, special, spec: Spec, model, along: str, reason: str):
    import xarray as xr

    m = model.free_size()
    X = np.stack([p.X for p in points])
    states = [model.state_at_rest(p.config) for p in points]
    theta = np.stack([np.asarray(getattr(s, "theta", s)) for s in states])
    turn = ("point", "component") if theta.ndim == 2 else ("point", "body", "component")
    column = list(zip(*special)) if special else [()] * 6
    raws = [p.raw for p in points]
    ds = xr.Dataset(
        {
            spec.parameter: ("point", X[:, m]),
            along: ("point", X[:, -1]),
            "frequency": ("point", np.abs(X[:, m + 1])),
            "first_lyapunov": ("point", np.array([float(r.first_lyapunov) for r in raws])),
            "transversality": ("point", np.array([float(r.transversality) for r in raws])),
            "theta": (turn, theta),
            "num_steps": ("point", np.array([int(r.num_steps) for r in raws], np.int32)),
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
            "parameter": spec.parameter,
            "along": along,
            "method": "arclength",
            "kind": spec.kind,
            "stop_reason": reason,
        },  # fmt: skip
    )
    return label_boundary(ds, spec.parameter, along)
