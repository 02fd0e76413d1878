r"""Pseudo-arclength continuation of equilibria in one parameter, for every model, with fold,
branch-point and Hopf detection.

The equilibria $R(c, \lambda) = 0$ of ``model_fn(**params, parameter=λ)`` (the balance of
forces and moments at rest, :meth:`rbo_jax.mechanics.AbstractMechanics.static_residual`: the
moment balance (4.61) of one body, the forces and moments on every body of a lattice or a rod)
form a curve in $(c, \lambda)$, $c$ the configuration. Keller's pseudo-arclength method follows
it: from a point $u_k$ with unit tangent $\tau_k$, the predictor $u_k + s\,\tau_k$ is corrected
by Newton's method on

$$R(c, \lambda) = 0, \qquad \langle \tau_k, u - u_k \rangle_W = s,$$

so a limit point (fold) of $\lambda$, where $J = \partial R/\partial c$ is singular, is passed.
The steps are the model's local increments $x$ (turn-vectors added for bodies on a foundation,
turns composed (4.5) for a rod), the inner product weighs a turn by 1, a displacement by one
over the model's size and the parameter by one over ``parameter_scale``. Each Newton step solves
the bordered system

$$\begin{pmatrix} J & R_\lambda \\ \tau_x^T W & \tau_\lambda w_\lambda \end{pmatrix}
\begin{pmatrix} \delta x \\ \delta\lambda \end{pmatrix} = -\begin{pmatrix} R \\ c \end{pmatrix}$$

by Keller's bordering algorithm with the model's own linear solver (two solves with $J$: dense
for one body or a grid, block-tridiagonal for an open chain or a rod, O(N);
:func:`rbo_jax.solvers.bordered_solve`). The same two solves give the new tangent,
$t = (-J^{-1}R_\lambda, 1)\,t_\lambda$ oriented along $\tau_k$, and the sign of the bordered
determinant (the branch-point test), $\det J$ from the model's solver. Along the branch
(:mod:`._detectors`):

- **fold**: the $\lambda$-component of the tangent changes sign; located at the vertex of the
  parabola $\lambda(\sigma)$ through three points around it (error $O(s^3)$);
- **branch point**: the bordered determinant changes sign; located by linear interpolation;
- **Hopf point**: the number of unstable oscillatory roots of the spectrum
  (:func:`rbo_jax.classify`'s test) changes; located exactly by :func:`rbo_jax.hopf_point`
  started from the last point before the change.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._callables import canonical
from .._programs import jit
from ..mechanics import AbstractMechanics
from ..solvers import bordered_solve, iterate, linear_solver
from ..stability import eigenvalues, solve_equilibrium, unstable_roots
from ._detectors import crossing, parabola_vertex, sign_changes
from ._steps import Steps, follow

__all__ = ["follow_equilibria"]

_RUNNING, _SUCCESSFUL, _FAILED = -1, 0, 1


def _model(model_fn, parameter, others, lam) -> AbstractMechanics:
    model = model_fn(**{**others, parameter: lam})
    if not isinstance(model, AbstractMechanics):
        raise TypeError(
            "model_fn must return a RigidBodyOscillator, a Lattice or a Rod, got "
            f"{type(model).__name__}."
        )
    return model


def _inner(tx, tl, x, lam, w, wl):
    return jnp.sum(tx * x * w**2) + tl * lam * wl**2


def _linear_parts(model_fn, parameter, others, t, config, lam):
    """``R``, its Jacobian in the increments (the model's structure) and ``R_lambda`` at
    ``(config, lam)``."""
    model = _model(model_fn, parameter, others, lam)
    x0 = jnp.zeros(model.block_shape(), lam.dtype)
    fn = lambda x: model.static_residual(t, config, x)  # noqa: E731
    R, J = linear_solver(model.structure()).value_and_jacobian(fn, x0)

    def at(lam):
        return _model(model_fn, parameter, others, lam).static_residual(t, config, x0)

    _, R_lam = jax.jvp(at, (lam,), (jnp.ones_like(lam),))
    return model, R, J, R_lam


def _step(model_fn, parameter, others, t, config0, lam0, tau_x, tau_l, s, w, wl, tol, max_newton,
          spectra):  # fmt: skip
    """Predictor, Newton's corrector on the bordered system (module docstring) in the one loop
    of :func:`rbo_jax.solvers.iterate`, the new tangent, the branch-point test and the
    spectrum. The loop's last evaluation (at the point whose correction is below ``tol``)
    gives the tangent and the test."""
    model0 = _model(model_fn, parameter, others, lam0)
    linear = linear_solver(model0.structure())
    y0 = (model0.retract(config0, s * tau_x), lam0 + s * tau_l, s * tau_x, s * tau_l)

    def step(y, _):
        config, lam, Dx, Dl = y
        model, R, J, R_lam = _linear_parts(model_fn, parameter, others, t, config, lam)
        gap = _inner(tau_x, tau_l, Dx, Dl, w, wl) - s
        dx, dl, b, pivot = bordered_solve(linear, J, R_lam, tau_x * w**2, tau_l * wl**2, -R, -gap)
        size = jnp.maximum(jnp.max(jnp.abs(dx * w)), jnp.abs(dl * wl))
        finite = jnp.isfinite(size)
        new = (model.retract(config, dx), lam + dl, Dx + dx, Dl + dl)
        new = jax.tree_util.tree_map(lambda a, c: jnp.where(finite, a, c), new, y)
        sign = linear.det_sign(J) * jnp.sign(pivot)
        code = jnp.where(size <= tol, _SUCCESSFUL, _RUNNING)
        return new, (b, pivot, sign), jnp.where(finite, code, _FAILED)

    # the loop's carry (b, pivot, sign): b shaped as the residual; shapes from the residual's
    # output, not by tracing a whole step (its Jacobian and solves) once more
    R = jax.eval_shape(
        lambda: model0.static_residual(t, config0, jnp.zeros(model0.block_shape(), lam0.dtype))
    )
    dtype = jnp.result_type(R.dtype, lam0.dtype)
    carry = (jnp.zeros(R.shape, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype))
    (config, lam, _, _), (b, pivot, sign), code, k = iterate(
        step, y0, carry, max_steps=max_newton, exhausted=_FAILED
    )
    t_l = 1.0 / pivot
    t_x = -t_l * b
    norm = jnp.sqrt(_inner(t_x, t_l, t_x, t_l, w, wl))
    model = _model(model_fn, parameter, others, lam)
    p = eigenvalues(model, config, t) if spectra else jnp.zeros(0, jnp.result_type(lam, 1j))
    return config, lam, code == _SUCCESSFUL, k, t_x / norm, t_l / norm, sign, p


_step_program = jit(_step, fast_compile=True)


class _Point:
    """A point of the branch: its configuration, parameter, tangent, test and spectrum."""

    def __init__(self, config, lam, tx, tl, sign, p, sigma):
        self.config, self.lam, self.tx, self.tl = config, float(lam), tx, float(tl)
        self.sign, self.p, self.sigma = float(sign), np.asarray(p), sigma


def follow_equilibria(model_fn, params, parameter, start, stop, *, theta_guess=None, steps=1,
                      ds=0.02, ds_min=1e-6, ds_max=0.1, max_points=500, tol=1e-10,
                      parameter_scale=1.0, spectra=True, locate_hopf=None, t=0.0,
                      progress=False):  # fmt: skip
    r"""Follow the equilibria of ``model_fn(**params, parameter=λ)`` (any model) from
    λ = ``start`` towards ``stop`` by pseudo-arclength continuation (module docstring),
    detecting folds, branch points and Hopf points.

    The first equilibrium is :func:`rbo_jax.solve_equilibrium`'s from ``theta_guess`` (the
    model's configuration; default: at rest) in ``steps`` load steps. The arclength step, in
    the norm of turns, displacements over the model's size and the parameter over
    ``parameter_scale``, starts at ``ds``, grows ×1.5 (up to ``ds_max``) after corrections of
    at most three Newton steps and halves after failed ones; the run stops when λ passes
    ``stop``, after ``max_points`` points, or when the step falls below ``ds_min``. ``tol``:
    Newton stops when no weighted correction exceeds it (never below 100 machine epsilons).
    ``spectra``: the eigenvalues at every point (a dense eigenvalue problem per point), needed
    for the stability and the Hopf test.

    **Returns** an :class:`xarray.Dataset` over ``point``: ``parameter`` (λ), ``theta`` (the
    turn-vectors: ``component``, and ``body`` for a lattice or a rod), ``r`` for a rod (the
    bodies' positions), ``eigenvalues`` (mode), ``spectral_abscissa``, ``stable`` (every root
    stable by :func:`rbo_jax.classify`'s test), and over ``special``: ``special_type``
    (``"fold"``, ``"branch_point"``, ``"hopf"``), ``special_value`` (λ), ``special_index`` (the
    point before it), and for Hopf points ``special_frequency`` and ``special_first_lyapunov``
    (from ``locate_hopf``, :func:`rbo_jax.hopf_point` for :func:`rbo_jax.continue_equilibria`;
    NaN otherwise). ``attrs["stop_reason"]`` says why the run ended. Not differentiable (a
    loop in Python around compiled steps).
    """
    import xarray as xr

    Steps(float(ds), float(ds_min), float(ds_max)).check("continue_equilibria")
    if not (np.isfinite(start) and np.isfinite(stop)) or start == stop:
        raise ValueError(f"continue_equilibria: start and stop must be finite and differ, got "
                         f"{start}, {stop}.")  # fmt: skip
    if int(max_points) < 2:
        raise ValueError(f"continue_equilibria: max_points must be >= 2, got {max_points}.")
    if not (np.isfinite(parameter_scale) and parameter_scale > 0):
        raise ValueError(
            f"continue_equilibria: parameter_scale must be > 0, got {parameter_scale}."
        )
    if not callable(model_fn):
        raise TypeError(f"continue_equilibria: model_fn must be callable, got {type(model_fn)}.")
    dtype = jnp.result_type(float)
    others = {str(k): jnp.asarray(v, dtype) for k, v in params.items() if k != parameter}
    model = _model(model_fn, parameter, others, jnp.asarray(float(start), dtype))
    sol = solve_equilibrium(model, theta_guess, steps=steps, t=t)
    if not bool(sol.ok):
        raise ValueError(
            f"continue_equilibria: no equilibrium found at {parameter} = {start} from the guess: "
            f"EquilibriumStatus.{_name(sol.status)}."
        )
    points, reason = _follow(model_fn, parameter, others, model, sol.state, float(start),
                             float(stop), Steps(float(ds), float(ds_min), float(ds_max)),
                             float(parameter_scale), int(max_points), float(tol), bool(spectra),
                             jnp.asarray(t, dtype), progress)  # fmt: skip
    special = _locate_hopf(_special(points, spectra), points, model_fn, others, parameter,
                           locate_hopf)  # fmt: skip
    return _dataset(xr, parameter, model, points, special, reason)


def _name(item):
    from .. import _enumeration as enum

    return enum.name(item)


def _follow(model_fn, parameter, others, model, config, start, stop, steps, scale, max_points,
            tol, spectra, t, progress):  # fmt: skip
    """The loop of :func:`continue_equilibria` around the compiled corrector."""
    dtype = t.dtype
    tol = max(tol, 100 * float(jnp.finfo(dtype).eps))  # as the static solve's floor
    w = 1.0 / model.increment_scale(model.rest())
    wl = jnp.asarray(1.0 / scale, dtype)
    direction = 1.0 if stop > start else -1.0
    fn = canonical(model_fn)  # a new but identical function: the same program

    def correct(config, lam, tx, tl, s):
        return _step_program(fn, parameter, others, t, config, jnp.asarray(lam, dtype), tx,
                             jnp.asarray(tl, dtype), jnp.asarray(s, dtype), w, wl, tol, 20,
                             spectra)  # fmt: skip

    zeros = jnp.zeros(model.block_shape(), dtype)
    out = correct(config, start, zeros, direction * scale, 0.0)  # the first tangent
    first = _Point(out[0], out[1], out[4], out[5], out[6], out[7], 0.0)

    def advance(point, ds):
        config, lam, ok, k, tx, tl, sign, p = correct(point.config, point.lam, point.tx,
                                                      point.tl, ds)  # fmt: skip
        if not bool(ok):
            return None, 0
        sigma = point.sigma + float(np.sqrt(float(ds) ** 2))
        return _Point(config, lam, tx, tl, sign, p, sigma), int(k)

    def accept(points, new):
        if direction * (new.lam - stop) >= 0:
            return True, "reached stop"
        return True, None

    return follow(advance, first, steps, max_points=max_points, accept=accept,
                  progress=progress, desc="equilibria")  # fmt: skip


def _special(points, spectra):
    """Folds, branch points and Hopf points between consecutive points (module docstring):
    ``(type, value, index, frequency)``, folds at the vertex of the parabola through three
    points, one Hopf point for every pair that crosses the imaginary axis (its frequency at the
    point before; NaN for the others)."""
    lam = [q.lam for q in points]
    special = []
    for i in sign_changes([q.tl for q in points]):
        value = float(crossing(points[i].tl, points[i + 1].tl, lam[i], lam[i + 1])[0])
        lo = min(max(i - 1, 0), len(points) - 3)
        if lo >= 0:
            near = points[lo : lo + 3]
            vertex = parabola_vertex([q.sigma for q in near], [q.lam for q in near])
            value = value if vertex is None else vertex[0]
        special.append(("fold", value, i, np.nan))
    for i in sign_changes([q.sign for q in points]):
        value = float(crossing(points[i].sign, points[i + 1].sign, lam[i], lam[i + 1])[0])
        special.append(("branch_point", value, i, np.nan))
    if spectra:
        for i in range(len(points) - 1):
            for frequency in _crossings(points[i].p, points[i + 1].p):
                special.append(("hopf", 0.5 * (lam[i] + lam[i + 1]), i, frequency))
    return sorted(special, key=lambda s: s[2])


def _crossings(before, after) -> list[float]:
    """The frequencies at the point ``before`` of the pairs that cross the imaginary axis
    between the spectra ``before`` and ``after``: roots of the upper half plane unstable by
    :func:`rbo_jax.classify`'s test at one point and not at the other (each matched to the
    nearest root of the other spectrum)."""
    if before.size == 0:
        return []
    unstable_b, unstable_a = np.asarray(unstable_roots(before)), np.asarray(unstable_roots(after))
    found = []
    for p, q, unstable_p, unstable_q, from_after in (
        (after, before, unstable_a, unstable_b, True),  # pairs that turn unstable
        (before, after, unstable_b, unstable_a, False),  # pairs that turn stable again
    ):
        for i in np.flatnonzero(unstable_p & (np.abs(p.imag) > 0) & (p.imag > 0)):
            j = int(np.argmin(np.abs(q - p[i])))
            if not unstable_q[j]:
                found.append(float(abs((q[j] if from_after else p[i]).imag)))
    return sorted(found)


def _locate_hopf(special, points, model_fn, others, parameter, hopf_point):
    """Each Hopf point solved by ``hopf_point`` from the point before it, for its pair:
    ``(type, value, index, frequency, first Lyapunov coefficient)``."""
    out = []
    for kind, value, index, frequency in special:
        if kind != "hopf" or hopf_point is None:
            out.append((kind, value, index, np.nan, np.nan))
            continue
        point = points[index]
        h = hopf_point(model_fn, others, parameter, point.lam, theta_guess=point.config,
                       frequency=frequency)  # fmt: skip
        if bool(h.ok):
            out.append((kind, float(h.value), index, float(h.frequency), float(h.first_lyapunov)))
        else:
            out.append((kind, value, index, np.nan, np.nan))
    return sorted(out, key=lambda s: (s[2], s[1]))


def _dataset(xr, parameter, model, points, special, reason):
    """The branch as a Dataset (:func:`continue_equilibria`'s)."""
    states = [model.state_at_rest(q.config) for q in points]
    stack = lambda name: np.stack([np.asarray(getattr(s, name, s)) for s in states])  # noqa: E731
    theta = stack("theta")
    turn_dims = ("point", "component") if theta.ndim == 2 else ("point", "body", "component")
    P = np.stack([np.sort_complex(q.p) for q in points])
    abscissa = np.max(P.real, axis=1) if P.shape[1] else np.full(len(points), np.nan)
    stable = np.array([bool(np.all(np.asarray(unstable_roots(-p)))) if p.size else False
                       for p in P])  # fmt: skip
    column = list(zip(*special)) if special else [()] * 5
    data = {
        parameter: ("point", np.array([q.lam for q in points])),
        "theta": (turn_dims, theta),
        "eigenvalues": (("point", "mode"), P),
        "spectral_abscissa": ("point", abscissa),
        "stable": ("point", stable),
        "special_type": ("special", np.array(column[0], dtype=str)),
        "special_value": ("special", np.array(column[1], dtype=float)),
        "special_index": ("special", np.array(column[2], dtype=int)),
        "special_frequency": ("special", np.array(column[3], dtype=float)),
        "special_first_lyapunov": ("special", np.array(column[4], dtype=float)),
    }
    if hasattr(states[0], "r"):  # bodies that translate: their positions
        data["r"] = (turn_dims, stack("r"))
    return xr.Dataset(
        data,
        coords={"component": ["x", "y", "z"], "mode": np.arange(P.shape[1])},
        attrs={"parameter": parameter, "stop_reason": reason},
    )
