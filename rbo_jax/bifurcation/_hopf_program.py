r"""The flutter solve (:mod:`._hopf_system`) as one program: one loop around one evaluation of
the system and its Jacobian (:func:`._hopf_system.evaluate`), its phases the steps of
:func:`rbo_jax.solvers.iterate`: Newton on the equilibrium at the guess, the start from its
eigenvalues (:mod:`._hopf_start`), Newton on the flutter system, the move of the chart to the
solution, the eigenvector there.

**At the solution** the chart moves to the critical equilibrium (the configuration
``retract(config, q)``), where the eigenvector (and the chain) are solved again (one
least-squares solve: the same numbers for a turn-vector added to, the eigenvector in the rod's
new increments otherwise), and the Jacobian of the system there is what the implicit
derivative of :mod:`._hopf` solves with. For a simple Hopf pair, Kuznetsov's first Lyapunov
coefficient $\ell_1$ (:mod:`._lyapunov`), the adjoint vector and the transversality
$d\,\mathrm{Re}\lambda/d\alpha = \mathrm{Re}\langle p, D^2\tilde F[\delta, q]\rangle$,
$\delta = (dq/d\alpha, 0, 1)$, $dq/d\alpha = -G_q^{-1}G_\alpha$ the motion of the equilibrium.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .. import _enumeration as enum
from ..mechanics import EquilibriumStatus
from ..solvers import Dense, LeastSquares, equilibrated_lstsq, iterate, newton_update
from ..stability import newton_equilibrium
from ._field import jets_by_row
from ._hopf_start import SHIFT, start
from ._hopf_system import (
    ROUNDING,
    ZERO_FREQUENCY,
    HopfStatus,
    Layout,
    Raw,
    Spec,
    _split,
    _times_i,
    adjoint_vector,
    code_of,
    equations,
    evaluate,
    model_at,
    oriented,
    unpack_parameters,
)
from ._lyapunov import STAGE_TWO_ROWS, from_stage_two, stage_one, stage_two_rows
from ._normal_form import EVALUATIONS, Schedule

__all__ = ["flutter_program"]


EQUILIBRIUM, SHIFT_PHASE, START, NEWTON, RECENTRE, EIGENVECTOR, OPERATOR, DONE = range(8)


def _lstsq_complex(A, b):
    """The least-squares solution of the complex system ``A z = b`` (its real form)."""
    real = jnp.block([[jnp.real(A), -jnp.imag(A)], [jnp.imag(A), jnp.real(A)]])
    z = equilibrated_lstsq(real, _split(b))
    n = A.shape[1]
    return jax.lax.complex(z[:n], z[n:])


class _Solve:
    """The phases of the program (module docstring), each a step of :func:`rbo_jax.solvers.
    iterate` from the system and its Jacobian at the current unknowns (one traced copy of
    them): Newton on the equilibrium at the guess, the start from the eigenvalues there,
    Newton on the flutter system, the move of the chart to the solution, the eigenvector
    there, the Jacobian there."""

    def __init__(self, spec: Spec, layout: Layout, p, t):
        self.spec, self.layout, self.p, self.t = spec, layout, p, t
        self.floor = ROUNDING * float(jnp.finfo(p.dtype).eps)

    def evaluate(self, s):
        central = (s["phase"] == NEWTON) | (s["phase"] == OPERATOR)
        return evaluate(self.spec, self.layout, s["u"], s["config"], s["C"], self.p, self.t,
                        central)  # fmt: skip

    def _stop(self, s, status):
        return {**s, "phase": DONE, "code": code_of(status)}

    def _recentre(self, s, q):
        model = model_at(self.spec, s["u"][self.layout.m], self.p)
        config = model.retract(s["config"], model.free_increments(q))
        return {**s, "config": config, "u": s["u"].at[: self.layout.m].set(0.0)}

    def equilibrium(self, s, r, Ju, J):
        m, spec = self.layout.m, self.spec
        q = s["u"][:m]
        new, _, done, finite = newton_update(
            r[:m], J[m:, :m], Dense(), q, rtol=spec.rtol, atol=spec.atol
        )
        k = s["k"] + 1
        # a guess on a singular sphere of Z (4.11), or outside a foundation's domain, fails:
        # where Z is infinite the first step's fate depends on the compiler's rounding
        model = model_at(spec, s["u"][m], self.p)
        admissible = enum.code(model.configuration_status(s["config"], 1e-6)) == 0
        s = {**s, "u": s["u"].at[:m].set(new), "k": k}
        ok = {**self._recentre(s, new), "phase": SHIFT_PHASE, "k": 0}
        failed = ~finite | (~done & (k >= spec.max_steps)) | ((k == 1) & ~admissible)
        return _select(failed, self._stop(s, HopfStatus.equilibrium_failed), _select(done, ok, s))

    def shift(self, s, r, Ju, J):
        """The eigenvalues at the equilibrium of the guess; the parameter moved for the next
        evaluation (:mod:`._hopf_start`)."""
        alpha = s["u"][self.layout.m]
        moved = alpha + SHIFT * jnp.maximum(jnp.abs(alpha), 1.0)
        u = s["u"].at[self.layout.m].set(moved)
        return {**s, "J0": J, "alpha": alpha, "u": u, "phase": START}

    def start(self, s, r, Ju, J):
        alpha, m = s["alpha"], self.layout.m
        if self.spec.kind == "hopf":
            # two passes: first one Newton step on the equilibrium at the moved parameter (a
            # follower load moves the spectrum only through its equilibrium: at a fixed
            # configuration the pair at the crossing would not move), then its eigenvalues
            step = -jnp.linalg.solve(J[m:, :m], r[:m])
            step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
            first = {**s, "u": s["u"].at[:m].set(step), "k": s["k"] + 1}
            shifted = jnp.linalg.eigvals(J)
        u, C, found, fits = start(self.spec, self.layout, s["J0"], alpha,
                                  shifted if self.spec.kind == "hopf" else None,
                                  s["frequency"])  # fmt: skip
        S = HopfStatus
        new = {**s, "u": u.astype(s["u"].dtype), "C": C.astype(s["C"].dtype), "phase": NEWTON,
               "k": jnp.zeros_like(s["k"])}  # fmt: skip
        code = jnp.where(found, code_of(S.not_converged), code_of(S.no_oscillatory_pair))
        done = _select(found & fits, new, {**s, "phase": DONE, "code": code})
        return _select(s["k"] == 0, first, done) if self.spec.kind == "hopf" else done

    def newton(self, s, r, Ju, J):
        spec = self.spec
        r, Ju = _equilibrated(r, Ju)
        u, _, done, finite = newton_update(
            r, Ju, LeastSquares(), s["u"], rtol=spec.rtol, atol=spec.atol, floor=self.floor
        )
        k = s["k"] + 1
        s = {**s, "u": u, "k": k, "phase": jnp.where(done, RECENTRE, NEWTON)}
        failed = ~finite | (~done & (k >= spec.max_steps))
        return _select(failed, self._stop(s, HopfStatus.not_converged), s)

    def recentre(self, s, r, Ju, J):
        return {**self._recentre(s, s["u"][: self.layout.m]), "phase": EIGENVECTOR}

    def eigenvector(self, s, r, Ju, J):
        layout, C = self.layout, s["C"]
        _, alpha, omega, _, chain = layout.unpack(s["u"])
        M = J.astype(C.dtype) - _times_i(omega) * jnp.eye(layout.n, dtype=C.dtype)
        A = jnp.concatenate([M, jnp.conj(C).T])
        e1 = jnp.zeros(C.shape[1], C.dtype).at[0].set(1.0)
        v = _lstsq_complex(A, jnp.concatenate([jnp.zeros(layout.n, C.dtype), e1]))
        if chain is not None:
            chain = _lstsq_complex(A, jnp.concatenate([v, jnp.zeros_like(e1)]))
        q = jnp.zeros(layout.m, s["u"].dtype)
        return {**s, "u": layout.pack(q, alpha, omega, v, chain), "phase": OPERATOR}

    def operator(self, s, r, Ju, J):
        res = jnp.max(jnp.abs(_equilibrated(r, Ju)[0]))
        s = {**s, "jacobian": J, "residual": res, "phase": DONE, "code": 0}
        return {**s, "Ju": Ju} if "Ju" in s else s

    def __call__(self, u, s):
        r, Ju, J = self.evaluate(s)
        phases = (self.equilibrium, self.shift, self.start, self.newton, self.recentre,
                  self.eigenvector, self.operator)  # fmt: skip
        branches = [lambda s, f=f: _typed(f(s, r, Ju, J), s) for f in phases]
        s = jax.lax.switch(jnp.minimum(s["phase"], OPERATOR), branches, s)
        running = s["phase"] < DONE
        return u, s, jnp.where(running, -1, s["code"])


def _equilibrated(r, J):
    """``(r, J)`` with every row divided by its norm in ``J`` (1 for a zero row)."""
    scale = jnp.linalg.norm(J, axis=1)
    scale = jnp.where(scale > 0, scale, 1.0)
    return r / scale, J / scale[:, None]


def _select(pred, a, b):
    """``a`` where ``pred``, else ``b``, leaf by leaf."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


def _typed(new, old):
    """``new`` with the dtypes of ``old`` (the branches of ``lax.switch`` must agree)."""
    return jax.tree_util.tree_map(lambda x, y: jnp.asarray(x, dtype=y.dtype), new, old)


class _Jet:
    r"""The extended field $\tilde F(z) = F(x; \alpha)$ of :func:`lyapunov`, $z = [x, \alpha]$
    (``parameters``: $z = [x, \alpha, p, t]$), and its rows of directions padded to $z$."""

    def __init__(self, spec: Spec, layout: Layout, u, config, p, t, parameters: bool):
        self.spec, self.config, self.p, self.t, n = spec, config, p, t, layout.n
        self.n_p = p.shape[0] if parameters else -1  # z's entries after alpha: p and t, or none
        tail = [jnp.asarray(p, u.dtype), jnp.asarray(t, u.dtype)[None]] if parameters else []
        self.z0 = jnp.concatenate([jnp.zeros(n, u.dtype), u[layout.m][None], *tail])
        self.n, self.nz, self.dtype = n, self.z0.shape[0], u.dtype

    def field(self, z):
        n, n_p = self.n, self.n_p
        if n_p < 0:
            return model_at(self.spec, z[n], self.p).field(self.t, self.config)(z[:n])
        return model_at(self.spec, z[n], z[n + 1 : n + 1 + n_p]).field(z[-1], self.config)(z[:n])

    def pad(self, x):
        return jnp.concatenate([x, jnp.zeros(self.nz - self.n, x.dtype)])

    def rows(self, r):
        return jnp.stack([jnp.stack([self.pad(x) for x in row]) for row in r])

    def fill(self, r, size):
        return jnp.concatenate([r, jnp.zeros((size - r.shape[0], 3, self.nz), self.dtype)])


def lyapunov(spec: Spec, layout: Layout, u, config, C, J, p, t, columns=None, second=None):
    r"""$(p, \ell_1, d\,\mathrm{Re}\lambda/d\alpha, D, \ell_2)$ at a simple Hopf pair (module
    docstring; values, not differentiated): the two stages of :mod:`._lyapunov` and the
    transversality's two directions in one loop of two iterations around one traced
    third-order jet of $\tilde F(z) = F(x; \alpha)$, $z = [x, \alpha]$ (:class:`_Jet`); the
    first iteration's fourth row $(e_\alpha, 0, 0)$ gives $F_\alpha$, whence the
    transversality's $\delta$.

    With ``columns`` (a flag, traced or not, or ``None``) $z = [x, \alpha, p, t]$, and where it is
    true the first iteration also takes the rows $(e_j, v_r)$, $(e_j, v_i)$ for $z_j$ in $q$,
    $\alpha$, $p$ and $t$: $D\tilde F[e_j]$ and $D^2\tilde F[e_j, v]$, whence ``D``, the
    flutter system's exact derivatives in those unknowns and parameters (:func:`_columns`;
    zero where the flag is false: no row computed); ``None`` without ``columns``. With
    ``second`` (a traced flag, or ``None``) where it is true the loop goes on with the
    evaluations of the second Lyapunov coefficient $\ell_2$ (:class:`._normal_form.Schedule`,
    one row each, the jet at shifted points): the same traced jet, not a second one."""
    u, J = jax.lax.stop_gradient((u, J))
    m, n = layout.m, layout.n
    omega, q = oriented(layout, u)
    adjoint = adjoint_vector(J, omega, q)
    jet = _Jet(spec, layout, u, config, p, t, columns is not None)
    a, b, z = jnp.real(q), jnp.imag(q), jnp.zeros(n, u.dtype)
    e_alpha = jnp.zeros_like(jet.z0).at[n].set(1.0)  # its row gives F_alpha (D1 at row 3)
    alpha_row = jnp.stack([e_alpha, 0 * e_alpha, 0 * e_alpha])[None]
    one, first = jnp.concatenate([jet.rows(((a, a, z), (b, b, z), (a, b, z))), alpha_row]), 4
    if columns is not None:  # the directions e_j: q, then alpha, p and t
        vr, vi = (jet.pad(x) for x in _split(layout.unpack(u)[3]).reshape(2, n))
        index = jnp.concatenate([jnp.arange(m), n + jnp.arange(jet.nz - n)])
        e = jnp.eye(jet.nz, dtype=u.dtype)[index]
        one = jnp.concatenate(
            [one, jnp.stack([jnp.stack([d, w, 0 * d]) for d in e for w in (vr, vi)])]
        )
        first = jnp.where(columns, one.shape[0], 4)
    size = max(STAGE_TWO_ROWS + 2, one.shape[0])
    schedule = Schedule(n, u.dtype)
    st0 = None if second is None else schedule.initial_state(J, omega, q, adjoint)

    def transversal(F_alpha):  # the rows (delta, a), (delta, b), delta = (dq/dalpha, 0, 1)
        dq = -jnp.linalg.solve(J[m:, :m], F_alpha[m:])
        delta = jet.pad(jnp.concatenate([dq, jnp.zeros(m, u.dtype)])).at[n].set(1.0)
        return jnp.stack([jnp.stack([delta, jet.pad(x), 0 * delta]) for x in (a, b)])

    def stage(i, carry):
        directions, shifts, scale, first1, first2, D2l, D3l, st = carry
        count = jnp.where(i == 0, first, jnp.where(i == 1, STAGE_TWO_ROWS + 2, 1))
        D1, D2, D3 = jets_by_row(jet.field, jet.z0, directions, count, shifts, size=n)
        h11, h20 = stage_one(J, omega, D2[0], D2[1], D2[2])
        two = jet.fill(
            jnp.concatenate([jet.rows(stage_two_rows(a, b, h11, h20)), transversal(D1[3])]), size
        )
        if second is not None:  # l2: advanced from i = 2 on, its next evaluation from i = 1 on
            st = _select(i >= 2, schedule.advance(st, scale, D1[0], D2[0], D3[0]), st)
            shift, directions, scale = schedule.evaluation(st)
            two = jnp.where(i == 0, two, jet.fill(jet.rows((tuple(directions),)), size))
            shifts = jnp.where(i == 0, shifts, shifts.at[0].set(jet.pad(shift)))
        first1, first2 = jnp.where(i == 0, D1, first1), jnp.where(i == 0, D2, first2)
        D2l, D3l = jnp.where(i == 1, D2, D2l), jnp.where(i == 1, D3, D3l)
        return two, shifts, scale, first1, first2, D2l, D3l, st

    D = jnp.zeros((size, n), u.dtype)
    shifts, scale = jnp.zeros((size, jet.nz), u.dtype), jnp.ones((), u.dtype)
    stop = 2 if second is None else jnp.where(second, 2 + EVALUATIONS, 2)
    carry = (jet.fill(one, size), shifts, scale, D, D, D, D, st0)
    _, _, _, first1, first2, D2, D3, st = jax.lax.fori_loop(0, stop, stage, carry)
    l1 = from_stage_two(adjoint, omega, D2, D3)
    dJq = jax.lax.complex(D2[STAGE_TWO_ROWS], D2[STAGE_TWO_ROWS + 1])
    D = None
    if columns is not None:
        k = one.shape[0] - 4
        D = _columns(layout, u, C, first1[4 : 4 + k : 2], first2[4 : 4 + k].reshape(k // 2, 2, n))
    l2 = None if second is None else Schedule.result(st)
    return adjoint, l1, jnp.real(jnp.vdot(adjoint, dJq)), D, l2


def _columns(layout: Layout, u, C, dF, d2F):
    r"""The flutter system's derivatives (one column per direction $e_j$): column $j$ from
    $D\tilde F[e_j]$ (``dF[j]``) and $D^2\tilde F[e_j, v_r]$, $D^2\tilde F[e_j, v_i]$
    (``d2F[j]``): the system is linear in the field's value and its products with $v$."""
    _, _, omega, v, chain = layout.unpack(u)

    def column(df, d2f):
        fn = lambda f0, products: equations(layout, f0, products, omega, v, chain, C)  # noqa: E731
        zero = jnp.zeros_like(df), jnp.zeros_like(d2f)
        return jax.jvp(fn, zero, (df, d2f))[1]

    return jax.vmap(column)(dF, d2F).T


def _status(spec: Spec, layout: Layout, code, u, config, J, p, alpha0, singular_tol=1e-6):
    """The solve's status checked at the solution: the frequency against the spectrum's
    scale, the configuration, the parameters (invalid at the guess: ``invalid_parameters``;
    valid there but not at the solution: the solve left the model's range, ``not_converged``)."""
    S = HopfStatus
    model = model_at(spec, u[layout.m], p)
    scale = jnp.max(jnp.abs(jnp.linalg.eigvals(J)))
    omega = u[layout.m + 1]
    checked = jnp.where(jnp.abs(omega) > ZERO_FREQUENCY * scale, code, code_of(S.zero_frequency))
    admissible = enum.code(model.configuration_status(config, singular_tol))
    singular = admissible == code_of(EquilibriumStatus.singular_point)
    checked = jnp.where(singular, code_of(S.singular_point), checked)
    outside = admissible == code_of(EquilibriumStatus.domain_error)
    checked = jnp.where(outside, code_of(S.equilibrium_failed), checked)
    checked = jnp.where(model.parameter_status()[0], checked, code_of(S.not_converged))
    code = jnp.where(code == code_of(S.successful), checked, code)
    valid = model_at(spec, alpha0, p).parameter_status()[0]
    return jnp.where(valid, code, code_of(S.invalid_parameters)).astype(jnp.int32)


def _initial(spec: Spec, layout: Layout, p, alpha0, guess, t, warm, u0, C0):
    """The loop's first state: Newton on the flutter system from ``u0``, ``C0`` at the
    configuration ``guess`` (``warm``), or the equilibrium from ``guess`` at ``alpha0``."""
    model = model_at(spec, alpha0, p)
    guess = model.configuration(guess, "theta_guess")  # None: at rest
    cold_phase = EQUILIBRIUM
    if spec.state_fn is not None:
        point = {**unpack_parameters(spec.names, spec.shapes, p), spec.parameter: alpha0}
        closed = model.configuration(spec.state_fn(**point), "theta_eq_fn(...)")
        guess = jax.lax.cond(warm, lambda: guess, lambda: _typed(closed, guess))
    if spec.steps > 1:  # load steps: the equilibrium by the statics' solver, then the start
        solved, _, _, _ = newton_equilibrium(model, guess, t, steps=spec.steps)
        guess = jax.lax.cond(warm, lambda: guess, lambda: _typed(solved, guess))
        cold_phase = SHIFT_PHASE
    cold = jnp.zeros(layout.size, p.dtype).at[layout.m].set(alpha0)
    return {
        "phase": jnp.where(warm, NEWTON, cold_phase).astype(jnp.int32),
        "config": guess,
        "u": jnp.where(warm, u0, cold),
        "C": jnp.asarray(C0),
        "code": jnp.asarray(code_of(HopfStatus.not_converged), jnp.int32),
        "k": jnp.asarray(0, jnp.int32),
        "jacobian": jnp.zeros((layout.n, layout.n), p.dtype),
        "J0": jnp.zeros((layout.n, layout.n), p.dtype),
        "alpha": jnp.asarray(alpha0, p.dtype),
        "residual": jnp.asarray(jnp.inf, p.dtype),
    }


def flutter_program(
    spec: Spec, p, alpha0, guess, t, warm, u0, C0, columns=None, second=None, frequency=None
):
    r"""The flutter point (module docstring) of ``spec.model_fn`` in ``spec.parameter``, the
    other parameters flattened into ``p``: from the equilibrium guess ``guess`` at ``alpha0``
    (``spec.state_fn``: its closed form, refined by Newton), or (``warm``) from the unknowns
    ``u0`` and basis ``C0`` in the chart at the configuration ``guess`` (a continuation's last
    point). Returns a :class:`Raw` with the status code of :class:`HopfStatus`.

    ``columns`` (a flag, traced or not; a Hopf spec with ``lyapunov``): also
    ``(operator, partials)``, where the flag is true the system's exact Jacobian in the
    unknowns and its derivatives in ``p`` and ``t`` at the solution, from the third-order jet of
    $\ell_1$'s loop: what the implicit derivative of :mod:`._hopf` solves with (traced there:
    the same program as the value; :mod:`._bautin`'s differentiated solve, a program of its
    own, sets it on its last solve).
    ``second`` (a traced flag; a Hopf spec with ``lyapunov``): also $\ell_2$ at the solution
    where the flag is true (:func:`lyapunov`; the Bautin point's last solve).
    ``frequency`` (traced; a spec ``by_frequency``): the start follows the pair nearest it."""
    layout = Layout(model_at(spec, alpha0, p).free_size(), spec.kind)
    solve = _Solve(spec, layout, p, t)
    s0 = _initial(spec, layout, p, alpha0, guess, t, warm, u0, C0)
    s0["frequency"] = jnp.asarray(jnp.nan if frequency is None else frequency, p.dtype)
    if not (spec.kind == "hopf" and spec.lyapunov) and (columns, second) != (None, None):
        raise ValueError("flutter_program: columns and second need a Hopf spec with lyapunov.")
    if columns is not None:
        s0["Ju"] = jnp.zeros((layout.rows(s0["C"].shape[1]), layout.size), p.dtype)
    _, s, code, _ = iterate(solve, None, s0, max_steps=2 * spec.max_steps + 5,
                            exhausted=code_of(HopfStatus.not_converged))  # fmt: skip
    u, config, J = s["u"], s["config"], s["jacobian"]
    code = _status(spec, layout, code, u, config, J, p, alpha0)
    nan = jnp.full((), jnp.nan, p.dtype)
    adjoint, l1, trans = jnp.full(layout.n, jnp.nan, s["C"].dtype), nan, nan
    if spec.kind == "hopf" and spec.lyapunov:
        simple = jnp.sum(jnp.any(s["C"] != 0, axis=0)) == 1
        *values, D, l2 = lyapunov(spec, layout, u, config, s["C"], J, p, t, columns, second)
        adjoint, l1, trans = (jnp.where(simple, x, jnp.nan) for x in values)
    raw = Raw(config, u, s["C"], J, s["residual"], s["k"], code, adjoint, l1, trans)
    extras = ()
    if columns is not None:
        k, n_p = layout.m + 1, p.shape[0]
        operator = jnp.concatenate([D[:, :k], s["Ju"][:, k:]], axis=1)
        extras += (operator, (D[:, k : k + n_p], D[:, k + n_p :]))
    if second is not None:
        extras += (jnp.where(simple, l2, jnp.nan),)
    return (raw, *extras) if extras else raw
