r"""Hopf points of equilibria: the extended system, the first Lyapunov coefficient and exact
derivatives of the critical parameter.

With $x = [\theta, \Omega]$ and $F(x; \alpha)$ the right form (4.55)–(4.56), an equilibrium has
$\Omega = 0$ and $\dot\Omega(\theta, 0; \alpha) = 0$ (the moment balance (4.61)), and its
linearization $J = \partial F/\partial x$ is the matrix of (4.63)–(4.67). A Hopf point is an
equilibrium at which $J$ has a pair of eigenvalues $\pm i\omega$, $\omega > 0$. With the
eigenvector $q = v_r + i v_i$ it solves the 17 real equations in the 17 unknowns
$(\theta, \alpha, \omega, v_r, v_i)$

$$\dot\Omega(\theta, 0; \alpha) = 0,\quad J v_r + \omega v_i = 0,\quad J v_i - \omega v_r = 0,
  \quad \mathrm{Re}(w^H q) = 1,\quad \mathrm{Im}(w^H q) = 0,$$

($w$ the eigenvector at the guess, which fixes the scale and phase of $q$), solved by Newton's
method in one compiled program with the first Lyapunov coefficient (:mod:`._system`). Its
solution is a regular point of the system at a generic Hopf point, so the implicit function
theorem gives the derivatives of the solution $u$ with respect to every other parameter $p$,
$du = -(\partial_u r)^{-1}\partial_p r\,dp$, from the Jacobians of the converged system that
the program returns: ``jax.grad`` and ``jax.jacfwd`` work through :func:`hopf_point`, and the
gradient runs the same compiled program as the value (a ``jax.custom_jvp`` around it).

**First Lyapunov coefficient** (Kuznetsov, *Elements of Applied Bifurcation Theory*, 3rd ed.,
eq. (3.20)): with $Jq = i\omega q$, $J^Tp = -i\omega p$, $\langle q, q\rangle = 1$,
$\langle p, q\rangle = \bar p^Tq = 1$, and the multilinear forms $B = D^2F$, $C = D^3F$ at the
Hopf point (directional derivatives, :mod:`._lyapunov`),

$$\ell_1 = \frac{1}{2\omega}\mathrm{Re}\Big[\langle p, C(q, q, \bar q)\rangle
  - 2\langle p, B(q, J^{-1}B(q, \bar q))\rangle
  + \langle p, B(\bar q, (2i\omega E - J)^{-1}B(q, q))\rangle\Big].$$

$\ell_1 < 0$: supercritical (soft) flutter, a stable limit cycle of amplitude
$\propto\sqrt{\alpha - \alpha_H}$ on the unstable side; $\ell_1 > 0$: subcritical (hard), an
unstable cycle on the stable side. The **transversality** $d\,\mathrm{Re}\lambda/d\alpha =
\mathrm{Re}[\langle p, (dJ/d\alpha)q\rangle]$ includes the motion of the equilibrium,
$d\theta/d\alpha = -(\partial_\theta\dot\Omega)^{-1}\partial_\alpha\dot\Omega$. For a cycle of
the normal form, $|z|^2 = -\,\mathrm{transversality}\,(\alpha - \alpha_H)/(\omega\ell_1)$ with
$x = x_H + 2\,\mathrm{Re}(z q)$ (used to start the family of limit cycles).
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
from .._callables import callable_key
from .._programs import jit, program
from ..model import RigidBodyOscillator
from ._interface import (
    Outcome,
    check_model_fn,
    check_params,
    check_theta_eq_fn,
    model_solver,
    theta_guess_vector,
)
from ._lyapunov import first_lyapunov_coefficient
from ._system import HopfStatus, hopf_program

__all__ = ["HopfStatus", "HopfPoint", "hopf_point", "first_lyapunov_coefficient"]


class HopfPoint(Outcome):
    r"""A Hopf point (module docstring): the critical ``value`` of the parameter, the
    ``frequency`` $\omega > 0$ of the eigenvalue pair $\pm i\omega$, the equilibrium ``theta``,
    the critical ``eigenvector`` $q$ ($Jq = i\omega q$, $|q| = 1$) and adjoint ``adjoint``
    ($\bar p^Tq = 1$) of the flat state $[\theta, \Omega]$, the ``transversality``
    $d\,\mathrm{Re}\lambda/d\alpha$, the ``first_lyapunov`` coefficient $\ell_1$, the Newton
    ``residual`` (max norm at the solution) and ``num_steps``, and the ``status``
    (:class:`HopfStatus`)."""

    # this result's own fields, declared here (its pytree and its docs); `ok` is Outcome's
    value: Float[Array, ""]
    frequency: Float[Array, ""]
    theta: Float[Array, "3"]
    eigenvector: Complex[Array, "6"]
    adjoint: Complex[Array, "6"]
    transversality: Float[Array, ""]
    first_lyapunov: Float[Array, ""]
    residual: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: HopfStatus

    @property
    def supercritical(self):
        r"""$\ell_1 < 0$: a stable limit cycle is born on the unstable side (soft flutter)."""
        return self.first_lyapunov < 0

    @property
    def period(self):
        return 2 * jnp.pi / self.frequency


def _point(others: dict, parameter: str, value) -> dict:
    return {**others, parameter: value}


# --------------------------------------------------------------------------------------------
# The compiled program, its implicit derivative and the result
# --------------------------------------------------------------------------------------------

_SEEN: dict = {}


def canonical(fn):
    """The first function seen that computes what ``fn`` computes
    (:func:`rbo_jax._callables.callable_key`): a new but identical lambda (a notebook cell run
    again) is then the same static argument, and its program is not traced again."""
    if fn is None:
        return None
    try:
        return _SEEN.setdefault(callable_key(fn), fn)
    except TypeError:  # an unhashable key: the function itself
        return fn


class Static(NamedTuple):
    """What the program of :func:`hopf_point` is compiled for (hashable, stable reprs)."""

    # alike _cycle_fold.Static, but the static data of another program (hopf_program)
    model_fn: Callable
    theta_eq_fn: Callable | None
    parameter: str
    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    rtol: float
    atol: float
    max_steps: int


class Raw(NamedTuple):
    # this program's outputs, in its order (alike other programs' Raw, not the same)
    u: Array
    Ju: Array
    Jp: Array
    residual: Array
    num_steps: Array
    status: Array
    adjoint: Array
    first_lyapunov: Array
    transversality: Array


# One program per model structure: with the program store on (rbo_jax.enable_compilation_cache)
# a second process loads it traced (user functions keyed by their code, _programs).
_program = program(hopf_program, fast_compile=True)  # XLA options: run in ms, compile fast


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def solution(static: Static, p, alpha0, theta0, t, u0, w0, warm) -> Raw:
    """The raw solution of the Hopf program (:func:`._system.hopf_program`); differentiable with
    respect to the flat parameters ``p`` by the implicit function theorem (module docstring),
    not with respect to the starting values."""
    return Raw(*_program(*static, p, alpha0, theta0, t, u0, w0, warm))


@solution.defjvp
def _solution_jvp(static, primals, tangents):
    raw = solution(static, *primals)
    du = _implicit_tangent(raw.Ju, raw.Jp, tangents[0])
    zeros = jax.tree.map(_zero_tangent, raw)
    return raw, zeros._replace(u=du)


@jax.jit
def _implicit_tangent(Ju, Jp, dp):
    return -jnp.linalg.solve(Ju, Jp @ dp)


def _zero_tangent(x):
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, dtype=jax.dtypes.float0)


def _nan_unless(good, x):
    return jnp.where(good, x, jnp.full_like(x, jnp.nan))


@functools.partial(jit, fast_compile=True)
def finish(raw: Raw) -> HopfPoint:
    """The :class:`HopfPoint` of a raw solution (the eigenvector normalised, conjugated where
    Newton found $-\\omega$), NaN values where the status is not successful."""
    u = raw.u
    vr, vi, omega = u[5:11], u[11:17], u[4]
    sign = jnp.where(omega < 0, -1.0, 1.0)
    n = jnp.sqrt(vr @ vr + vi @ vi)
    q = jax.lax.complex(vr / n, sign * vi / n)
    status = enum.from_code(HopfStatus, raw.status)
    good = raw.status == enum.code(HopfStatus.successful)
    return HopfPoint(
        value=_nan_unless(good, u[3]),
        frequency=_nan_unless(good, jnp.abs(omega)),
        theta=_nan_unless(good, u[:3]),
        eigenvector=_nan_unless(good, q),
        adjoint=_nan_unless(good, raw.adjoint),
        transversality=_nan_unless(good, raw.transversality),
        first_lyapunov=_nan_unless(good, raw.first_lyapunov),
        residual=raw.residual,
        num_steps=raw.num_steps,
        status=status,
    )


def _is_traced(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


def flat_parameters(others: dict):
    """``(names, shapes, p)``: the parameters flattened in the order of their names (NumPy
    when concrete: no small eager programs). Sorted, so that the same parameters give the same
    program whatever the order of the mapping (``jax.grad`` sorts a dict's keys)."""
    names = tuple(sorted(others))
    values = [others[k] for k in names]
    shapes = tuple(tuple(int(d) for d in jnp.shape(v)) for v in values)
    dtype = jnp.result_type(float)
    if _is_traced(others):
        parts = [jnp.ravel(jnp.asarray(v, dtype=dtype)) for v in values]
        p = jnp.concatenate(parts) if parts else jnp.zeros(0, dtype)
    else:
        parts = [np.ravel(np.asarray(v, dtype=dtype)) for v in values]
        p = np.concatenate(parts) if parts else np.zeros(0, dtype)
    return names, shapes, p


def _scalar(x, dtype):
    return x if _is_traced(x) else np.asarray(x, dtype=dtype)


def hopf_point(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    guess,
    *,
    # keywords shared with bautin_point, continue_hopf (a public, documented signature)
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    t=0.0,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 64,
    **options,
) -> HopfPoint:
    r"""The Hopf point nearest ``guess`` of the equilibria of ``model_fn(**params)`` as the
    parameter ``parameter`` varies: where a complex pair of eigenvalues of the linearization
    (4.63)–(4.67) crosses the imaginary axis (flutter).

    **Arguments:**

    - `model_fn`: ``model_fn(**params) -> RigidBodyOscillator``, as for
      :func:`rbo_jax.stability_map`; values may be traced (build the model from them).
    - `params`: ``{name: value}`` of every argument of ``model_fn``; the entry ``parameter`` (it
      may be absent) is the unknown, the others are fixed and differentiable.
    - `guess`: starting value of ``parameter``, near the boundary. At the guess the equilibrium
      is Newton's from ``theta_eq_fn(**params)`` if given (a closed form such as (4.62)), else
      from ``theta_guess`` (default 0); the complex eigenvalue pair with the largest real part
      is followed.
    - `rtol`, `atol`, `max_steps`: Newton's tolerances (a step below ``atol + rtol * |u|`` in
      every unknown ends it) and budget.

    **Returns** a :class:`HopfPoint` (module docstring for the system, $\ell_1$ and the
    transversality). Never raises for a failed solve: ``status`` says why, and the values are
    NaN. ``jax.grad``/``jax.jacfwd`` of ``value`` (and ``frequency``, ``theta``,
    ``eigenvector``) with respect to the other entries of ``params`` work by the implicit
    function theorem; ``jax.vmap`` over them works too. ``first_lyapunov``, ``transversality``
    and ``adjoint`` are computed from stopped values (their derivatives would need fourth
    derivatives of the vector field): their derivatives come out zero, differentiate them by
    finite differences. Compiled once per structure of ``model_fn`` and ``params`` (a new but
    identical ``model_fn`` reuses the program; so does the gradient), and kept by the program
    store when it is on (:func:`rbo_jax.enable_compilation_cache`).

    **Other models.** A ``model_fn`` that returns a :class:`rbo_jax.lattice.Rod` is handed to
    :func:`rbo_jax.lattice.rod_hopf_point` (the protocol of
    :func:`rbo_jax.bifurcation._interface.model_solver`), with ``options`` (``kind=``,
    ``steps=``, ``frequency=``, ...): it returns a :class:`rbo_jax.lattice.RodHopfPoint` with
    ``value``, ``frequency``, ``eigenvector``, ``state``, ``residual``, ``num_steps`` and
    ``status``. ``options`` are refused for a rigid body oscillator.

    Example: the Nikolai problem with friction (4.84), ``hopf_point(lambda M, b:
    nikolai_model(M, friction=b), {"b": 0.1}, "M", 0.1)`` gives the critical follower moment
    $M_{cr} = 2b\sqrt{K(M_{cr})/A_1}$ and $\omega = \sqrt{K/A_1}$.
    """
    check_model_fn(model_fn)
    check_params(params)
    if not isinstance(parameter, str):
        raise TypeError(f"parameter must be the name of an entry of params, got {parameter!r}.")
    own = model_solver(model_fn, {**params, parameter: guess}, "rbo_hopf_point")
    if own is not None:
        shared = dict(theta_eq_fn=theta_eq_fn, theta_guess=theta_guess, t=t, rtol=rtol)
        return own(model_fn, params, parameter, guess, **shared, atol=atol, **options,
                   max_steps=max_steps)  # fmt: skip
    if options:
        raise TypeError(
            f"hopf_point: unexpected keyword arguments {sorted(options)} for a "
            "RigidBodyOscillator (they are the options of other models' solvers, e.g. a rod's)."
        )
    check_theta_eq_fn(theta_eq_fn)
    dtype = jnp.result_type(float)
    others = {str(k): v for k, v in params.items() if k != parameter}
    guess = _scalar(guess, dtype)
    if jnp.shape(guess) != ():
        raise ValueError(
            f"guess must be a scalar value of {parameter!r}, got shape {jnp.shape(guess)}."
        )
    theta_guess = theta_guess_vector(theta_guess, dtype)
    names, shapes, p = flat_parameters(others)
    static = Static(
        canonical(model_fn),
        canonical(theta_eq_fn),
        parameter,
        names,
        shapes,
        float(rtol),
        float(atol),
        int(max_steps),
    )
    raw = solution(
        static,
        p,
        guess,
        theta_guess,
        _scalar(t, dtype),
        np.zeros(17, dtype),
        np.zeros(12, dtype),
        np.asarray(False),
    )
    return finish(raw)
