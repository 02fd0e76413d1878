r"""Flutter points of equilibria, for any model: Hopf points (a pair crossing the imaginary
axis) and Krein collisions (two imaginary pairs merging), the first Lyapunov coefficient and
exact derivatives of the critical parameter.

The extended system and its solve are :mod:`._hopf_system`'s: one compiled program per model
structure (the equilibrium at the guess, the start from its eigenvalues, Newton's method in the
one loop of :mod:`rbo_jax.solvers`, the solution's chart, $\ell_1$). Its solution is a regular
point of the system at a generic flutter point, so the implicit function theorem gives the
derivatives of the solution with respect to every other parameter $p$,
$du = -J^{+}\,\partial_p r\,dp$ ($J^{+}$ the least-squares inverse of the system's Jacobian at
the solution, exact for the consistent system), by the one implicit rule of
:mod:`rbo_jax.solvers`: ``jax.grad`` and ``jax.jacfwd`` work through :func:`hopf_point`.
Where $\ell_1$ is computed, $J$ and $\partial_p r$ are exact columns of the program's own
third-order jet ($DF[e_j]$, $D^2F[e_j, v]$, rows taken only when the solution is
differentiated), so the derivative compiles no program of the model's second derivatives;
otherwise the rule takes them by forward mode of the residual.

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
$dq/d\alpha = -G_q^{-1}G_\alpha$. For a cycle of the normal form,
$|z|^2 = -\,\mathrm{transversality}\,(\alpha - \alpha_H)/(\omega\ell_1)$ with
$x = x_H + 2\,\mathrm{Re}(z q)$ (used to start the family of limit cycles). They are computed
for a simple Hopf pair of any model whose equations have third derivatives (every model here).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from .. import _enumeration as enum
from .._callables import canonical
from .._programs import jit, program
from .._validation import array_namespace
from ..mechanics import AbstractMechanics
from ..solvers import Implicit, LeastSquares, Outcome, implicit
from ._hopf_program import flutter_program
from ._hopf_system import (
    KINDS,
    HopfStatus,
    Layout,
    Raw,
    Spec,
    model_at,
    oriented,
    residual,
    unpack_parameters,
)
from ._lyapunov import first_lyapunov_coefficient

__all__ = ["HopfStatus", "HopfPoint", "hopf_point", "first_lyapunov_coefficient"]


class HopfPoint(Outcome):
    r"""A flutter point (module docstring): the critical ``value`` of the parameter, the
    ``frequency`` $\omega > 0$ of the eigenvalue $i\omega$, the equilibrium ``state`` there (the
    model's configuration; ``theta`` its turn-vectors), the critical ``eigenvector`` $q$ of the
    linearisation over its first-order state ($Jq = i\omega q$, $|q| = 1$; for one body over
    $[\theta, \Omega]$), the ``adjoint`` ($\bar p^Tq = 1$), the ``transversality``
    $d\,\mathrm{Re}\lambda/d\alpha$, the ``first_lyapunov`` coefficient $\ell_1$ (the last three
    NaN at a collision or a multiple pair), the Newton ``residual`` (max norm, rows
    equilibrated), ``num_steps``, the ``status`` (:class:`HopfStatus`) and the ``kind`` solved
    for (``"hopf"`` or ``"collision"``)."""

    value: Float[Array, ""]
    frequency: Float[Array, ""]
    state: Any
    eigenvector: Complex[Array, " n"]
    adjoint: Complex[Array, " n"]
    transversality: Float[Array, ""]
    first_lyapunov: Float[Array, ""]
    residual: Float[Array, ""]
    num_steps: Int[Array, ""]
    status: HopfStatus
    kind: str = eqx.field(static=True, default="hopf")

    @property
    def theta(self):
        """The turn-vector(s) of the critical equilibrium."""
        return getattr(self.state, "theta", self.state)

    @property
    def supercritical(self):
        r"""$\ell_1 < 0$: a stable limit cycle is born on the unstable side (soft flutter)."""
        return self.first_lyapunov < 0

    @property
    def period(self):
        return 2 * jnp.pi / self.frequency


# --------------------------------------------------------------------------------------------
# The compiled program, its implicit derivative and the result
# --------------------------------------------------------------------------------------------


# One program per model structure: with the program store on (rbo_jax.enable_compilation_cache)
# a second process loads it traced (user functions keyed by their code, _programs).
def hopf_program(spec: Spec, tree, p, alpha0, leaves, t, warm, u0, C0, columns, frequency):
    r""":func:`._hopf_program.flutter_program` on flat containers (the program store exports plain
    arrays: the configurations in and out as their leaves, their structure ``tree`` static);
    at a simple Hopf pair with $\ell_1$ the operator and the partials follow (computed where
    the traced flag ``columns`` is true: one program for the value and its derivative); the
    start's ``frequency`` is traced (``spec.by_frequency``: one program for every value)."""
    guess = None if tree is None else jax.tree_util.tree_unflatten(tree, leaves)
    exact = spec.kind == "hopf" and spec.lyapunov
    out = flutter_program(
        spec, p, alpha0, guess, t, warm, u0, C0, columns if exact else None, frequency=frequency
    )
    raw, more = (out[0], out[1:]) if exact else (out, ())
    return (tuple(jax.tree_util.tree_leaves(raw.config)),) + tuple(raw[1:]) + more


_program = program(hopf_program, fast_compile=True)


def _config_tree(spec: Spec, p, alpha0):
    """The structure of the model's configuration (traced abstractly)."""
    shape = eqx.filter_eval_shape(lambda p, a: model_at(spec, a, p).rest(), p, alpha0)
    return jax.tree_util.tree_structure(shape)


def _layout(spec: Spec, p, alpha) -> Layout:
    return Layout(model_at(spec, alpha, p).free_size(), spec.kind)


def _solve(params, spec: Spec, columns=False) -> Implicit:
    """The program's solution; with ``columns`` (differentiated) also the system's exact
    Jacobian and its derivatives in ``p`` and ``t`` (the other inputs are starting values)."""
    p, t, (alpha0, guess, warm, u0, C0, frequency) = params
    leaves, tree = jax.tree_util.tree_flatten(guess)
    out = _program(spec, None if guess is None else tree, p, alpha0, tuple(leaves), t, warm, u0,
                   C0, np.bool_(columns), frequency)  # fmt: skip
    config = jax.tree_util.tree_unflatten(_config_tree(spec, p, alpha0), out[0])
    n = len(Raw._fields)
    raw = Raw(config, *out[1:n])
    good = array_namespace(raw.status).asarray(raw.status) == 0  # NumPy where concrete
    if not columns:
        return Implicit((raw.config, raw.u, raw.C), None, good, raw)
    operator, (dp, dt) = out[n:]
    others = jax.tree_util.tree_map(lambda _: None, params[2])
    return Implicit((raw.config, raw.u, raw.C), operator, good, raw, (dp, dt, others))


class _Residual(NamedTuple):
    """The flutter system at ``y ⊕ x`` (hashable: the implicit tangent's program is kept)."""

    spec: Spec

    def __call__(self, y, x, params):
        config, u, C = y
        p, t, (alpha0, *_) = params
        return residual(self.spec, _layout(self.spec, p, alpha0), u + x, config, C, p, t)


class _Retract(NamedTuple):
    """``y ⊕ x``: the configuration moved by the increments of ``x``, the rest added."""

    spec: Spec

    def __call__(self, y, x, params):
        config, u, C = y
        p, _, (alpha0, *_) = params
        layout = _layout(self.spec, p, alpha0)
        model = model_at(self.spec, u[layout.m], p)
        config = model.retract(config, model.free_increments(x[: layout.m]))
        return config, u + x.at[: layout.m].set(0.0), C


def _increment(y, params):
    return jnp.zeros_like(y[1])


def solution(spec: Spec, p, t, alpha0, guess, warm, u0, C0, frequency=None):
    r"""``((config, u, C), raw)``: the flutter program's solution, differentiable with respect to
    the flat parameters ``p`` (and ``t``) by the implicit function theorem (module docstring),
    not with respect to the starting values (``frequency``: the pair to start from, for a spec
    ``by_frequency``). At a simple Hopf pair with $\ell_1$ the program
    that is differentiated also returns the system's exact Jacobian and its derivatives in the
    parameters, from $\ell_1$'s third-order jet; otherwise the tangent computes them."""
    exact = spec.kind == "hopf" and spec.lyapunov
    if spec.by_frequency and frequency is None:
        raise ValueError("solution: a spec by_frequency needs the frequency.")
    frequency = jnp.asarray(jnp.nan if frequency is None else frequency, p.dtype)
    out = implicit(
        lambda params: _solve(params, spec),
        _Residual(spec),
        (p, t, (alpha0, guess, warm, u0, C0, frequency)),
        linear=LeastSquares(),
        retract=_Retract(spec),
        increment=_increment,
        forward=True,
        exact=(lambda params: _solve(params, spec, True)) if exact else None,
    )
    return out.y, out.extra


def _nan_unless(good, x):
    return jnp.where(good, x, jnp.full_like(x, jnp.nan))


def _finish(spec: Spec, model: AbstractMechanics, y, raw: Raw) -> HopfPoint:
    """The :class:`HopfPoint` of a solution: NaN values where the status is not successful."""
    config, u, _ = y
    layout = Layout(model.free_size(), spec.kind)
    frequency, q = oriented(layout, u)
    good = raw.status == 0
    state = jax.tree_util.tree_map(lambda x: _nan_unless(good, x), model.state_at_rest(config))
    return HopfPoint(
        value=_nan_unless(good, u[layout.m]),
        frequency=_nan_unless(good, frequency),
        state=state,
        eigenvector=_nan_unless(good, q),
        adjoint=_nan_unless(good, raw.adjoint),
        transversality=_nan_unless(good, raw.transversality),
        first_lyapunov=_nan_unless(good, raw.first_lyapunov),
        residual=raw.residual,
        num_steps=raw.num_steps,
        status=enum.from_code(HopfStatus, raw.status),
        kind=spec.kind,
    )


# one small program, not a dozen eager ones (each compiled on first use), compiled fast
finish = jit(_finish, fast_compile=True)


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


def resolve_kind(kind: str, model: AbstractMechanics) -> str:
    """``kind`` with ``"auto"`` resolved at the guess: ``"hopf"`` where a force depends on the
    velocities (friction, damping: a damped pair crosses the axis), else ``"collision"`` (an
    undamped system flutters by a Krein collision)."""
    if kind not in KINDS:
        raise ValueError(f"hopf_point: kind must be one of {KINDS}, got {kind!r}.")
    if kind != "auto":
        return kind
    return "hopf" if model.depends_on_velocity() else "collision"


def hopf_keywords(given: Mapping, caller: str) -> dict:
    """The keywords of :func:`hopf_point` (after its four arguments), ``given`` over its
    defaults; an unknown keyword is a ``TypeError`` naming ``caller``."""
    defaults = {
        name: p.default
        for name, p in inspect.signature(hopf_point).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    }
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise TypeError(
            f"{caller}() got unexpected keyword argument(s) {', '.join(map(repr, unknown))}; "
            f"the keywords of hopf_point are {', '.join(defaults)}."
        )
    return {**defaults, **given}


def prepare(model_fn, params, parameter, guess, options: dict, along=None):
    """The checked arguments of a flutter solve: ``(spec, model, p, alpha0, config, t)``;
    ``along``: ``(name, first value)`` of a continuation's second parameter, the last entry of
    the flat parameters."""
    if not callable(model_fn):
        raise TypeError("model_fn must be a callable model_fn(**params) -> a model.")
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping {{name: value}}, got {type(params).__name__}.")
    if not isinstance(parameter, str):
        raise TypeError(f"parameter must be the name of an entry of params, got {parameter!r}.")
    o = options
    if int(o["steps"]) < 1 or int(o["max_steps"]) < 1 or int(o["multiplicity"]) < 1:
        raise ValueError("hopf_point: steps, max_steps and multiplicity must be >= 1.")
    if not o["cluster"] > 0:
        raise ValueError(f"hopf_point: cluster must be > 0, got {o['cluster']}.")
    state_fn = o["theta_eq_fn"]
    if state_fn is not None and not callable(state_fn):
        raise TypeError("theta_eq_fn must be a callable theta_eq_fn(**params) -> theta.")
    dtype = jnp.result_type(float)
    alpha0 = _scalar(guess, dtype)
    if jnp.shape(alpha0) != ():
        raise ValueError(
            f"guess must be a scalar value of {parameter!r}, got shape {jnp.shape(alpha0)}."
        )
    others = {str(k): v for k, v in params.items() if k != parameter}
    names, shapes, p = flat_parameters(others)
    if along is not None:  # the continuation's parameter: last, after the sorted others
        names, shapes = names + (along[0],), shapes + ((),)
        p = (jnp if _is_traced(p) else np).concatenate([p, np.asarray([along[1]], dtype)])
    model = _model_at_guess(model_fn, {**unpack_parameters(names, shapes, p), parameter: alpha0})
    spec = Spec(
        canonical(model_fn), canonical(state_fn), parameter, names, shapes,
        resolve_kind(o["kind"], model), float(o["rtol"]), float(o["atol"]),
        int(o["max_steps"]), float(o["cluster"]),
        o["frequency"] is not None, int(o["multiplicity"]),
        int(o["steps"]), _lyapunov(o["lyapunov"], model),
    )  # fmt: skip
    guess = o["theta_guess"]
    if guess is not None:  # checked now; the program makes the configuration of it
        try:
            guess = model.configuration(guess, "theta_guess")
        except TypeError as e:  # a guess of another model's kind of configuration
            raise ValueError(str(e)) from e
    return spec, model, p, alpha0, guess, _scalar(o["t"], dtype)


def _model_at_guess(model_fn, point) -> AbstractMechanics:
    """The model at the guess, for its structure (its kind of flutter, its size, its
    configuration): built from the values where they are valid, else traced abstractly (a NaN
    guess, a guess outside the parameters' range: the solve reports it as a status)."""
    try:
        model = model_fn(**point)
    except ValueError:
        model = eqx.filter_eval_shape(lambda p: model_fn(**p), point)
    if not isinstance(model, AbstractMechanics):
        raise TypeError(
            "model_fn must return a RigidBodyOscillator, a Lattice or a Rod, got "
            f"{type(model).__name__}."
        )
    return model


LYAPUNOV_UP_TO = 6  # free coordinates of the models whose l1 hopf_point computes by default


def _lyapunov(lyapunov, model: AbstractMechanics) -> bool:
    r"""Whether to compute $\ell_1$: ``lyapunov``, or by default for models of at most
    :data:`LYAPUNOV_UP_TO` free coordinates (a rigid body, a pair of bodies): its program holds
    the model's third derivatives, which for a rod's forces or a chain of bodies take two to
    three times as long to compile as the rest of the program (benchmarks/README.md)."""
    return model.free_size() <= LYAPUNOV_UP_TO if lyapunov is None else bool(lyapunov)


def cold_start(spec: Spec, model: AbstractMechanics, dtype):
    """The (unused) warm-start arguments of a cold solve: ``(u0, C0)``."""
    layout = Layout(model.free_size(), spec.kind)
    cdtype = jnp.complex64 if dtype == jnp.float32 else jnp.complex128
    return np.zeros(layout.size, dtype), np.zeros((layout.n, spec.multiplicity), cdtype)


def hopf_point(
    model_fn: Callable[..., AbstractMechanics],
    params: Mapping[str, object],
    parameter: str,
    guess,
    *,
    kind: str = "auto",
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    t=0.0,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 64,
    steps: int = 1,
    cluster: float = 1e-5,
    frequency=None,
    multiplicity: int = 2,
    lyapunov: bool | None = None,
) -> HopfPoint:
    r"""The flutter point nearest ``guess`` of the equilibria of ``model_fn(**params)`` as the
    parameter ``parameter`` varies: where a complex pair of eigenvalues of the linearization
    (4.63)–(4.67) crosses the imaginary axis (``kind="hopf"``), or where two imaginary pairs
    merge and leave it (``kind="collision"``, a Krein collision); any model.

    **Arguments:**

    - `model_fn`: ``model_fn(**params)`` returning a :class:`rbo_jax.RigidBodyOscillator`, a
      :class:`rbo_jax.lattice.Lattice` or a :class:`rbo_jax.lattice.Rod`; values may be
      traced (build the model from them).
    - `params`: ``{name: value}`` of every argument of ``model_fn``; the entry ``parameter``
      (it may be absent) is the unknown, the others are fixed and differentiable.
    - `guess`: starting value of ``parameter``, near the boundary.
    - `kind`: ``"hopf"``, ``"collision"``, or ``"auto"`` (default): ``"hopf"`` where a force
      depends on the velocities at the guess (friction, Kelvin–Voigt damping), else
      ``"collision"`` (Beck's, Pflüger's, Ziegler's undamped columns).
    - `theta_eq_fn`, `theta_guess`: the equilibrium at the guess is Newton's
      (:func:`rbo_jax.solve_equilibrium`, in ``steps`` load steps) from ``theta_eq_fn(**params)``
      if given (a closed form such as (4.62)), else from ``theta_guess`` (the model's
      configuration; default: at rest).
    - `frequency`: for ``"hopf"``, follow the pair nearest this frequency at the guess (default:
      of the pairs off the imaginary axis, the one with the largest real part).
    - `cluster`, `multiplicity`: eigenvalues within ``cluster`` × $|\lambda|$ of each other are
      one eigenvalue of up to ``multiplicity`` eigenvectors (2: a rod bending alike in two
      planes; a start with more fails with ``not_converged``).
    - `rtol`, `atol`, `max_steps`: Newton's tolerances (a step below ``atol + rtol * |u|`` in
      every unknown, or an equilibrated residual at the rounding level, ends it) and budget.
    - `lyapunov`: compute the first Lyapunov coefficient, the adjoint and the transversality
      at a simple Hopf pair; default (``None``): for models of at most six free coordinates (a
      rigid body, two bodies of a lattice): a larger model's third derivatives take long to
      compile (a rod's forces or a chain of bodies: two to three times the rest of the
      program); pass ``True`` to have them.

    **Returns** a :class:`HopfPoint` (:mod:`._hopf_system` for the system). Never raises for a
    failed solve: ``status`` says why, and the values are NaN. ``jax.grad``/``jax.jacfwd`` of
    ``value`` (and ``frequency``, ``state``, ``eigenvector``) with respect to the other entries
    of ``params`` work by the implicit function theorem; ``jax.vmap`` over them works too.
    ``first_lyapunov``, ``transversality`` and ``adjoint`` are computed from stopped values
    (their derivatives would need fourth derivatives of the vector field): their derivatives
    come out zero, differentiate them by finite differences. Compiled once per structure of
    ``model_fn`` and ``params`` (a new but identical ``model_fn`` reuses the program), and kept
    by the program store when it is on (:func:`rbo_jax.enable_compilation_cache`).

    Example: the Nikolai problem with friction (4.84), ``hopf_point(lambda M, b:
    nikolai_model(M, friction=b), {"b": 0.1}, "M", 0.1)`` gives the critical follower moment
    $M_{cr} = 2b\sqrt{K(M_{cr})/A_1}$ and $\omega = \sqrt{K/A_1}$.
    """
    options = dict(kind=kind, theta_eq_fn=theta_eq_fn, theta_guess=theta_guess, t=t, rtol=rtol,
                   atol=atol, max_steps=max_steps, steps=steps, cluster=cluster,
                   frequency=frequency, multiplicity=multiplicity, lyapunov=lyapunov)  # fmt: skip
    spec, model, p, alpha0, config, t = prepare(model_fn, params, parameter, guess, options)
    u0, C0 = cold_start(spec, model, p.dtype)
    y, raw = solution(spec, p, t, alpha0, config, np.asarray(False), u0, C0, frequency)
    return finish(spec, model, y, raw)
