r"""The Hopf system as one small program: equilibrium, eigenvalue pair, Newton's method, the first
Lyapunov coefficient and the transversality in one ``lax.while_loop`` around one traced copy of
the vector field's derivatives.

The unknowns and equations are those of :mod:`._hopf` (17 of each). Every quantity the solve
needs is a directional derivative of $\tilde F(y) = F(x; \alpha, p)$ in the extended variable
$y = [x, \alpha, p]$ ($x = [\theta, \Omega]$, $\alpha$ the free parameter, $p$ the other
parameters, flattened), evaluated by :func:`._field.jet` along rows of directions that the
phase of the loop chooses (one row per iteration):

0. **equilibrium** at the guess: Newton's method on $\dot\Omega(\theta, 0; \alpha_0) = 0$
   (4.61), Jacobian from the rows $e_j$;
1. **start**: the complex pair of the linearization (4.63)–(4.67) with the largest real part,
   its eigenvector $v$ (the normalisation vector $w = v$);
2. **Newton** on the Hopf system: its residual and exact Jacobian from the rows $(e_j)$,
   $(v_r, e_i)$, $(v_i, e_i)$ ($J v = DF[v]$, $\partial_i(Jv) = D^2F[v, e_i]$), with the
   derivatives with respect to $p$ (rows $e_{p_k}$, $(v_r, e_{p_k})$, $(v_i, e_{p_k})$) for
   the implicit function theorem, and $B(v_r, v_r)$, $B(v_i, v_i)$, $B(v_r, v_i)$;
3. **final**: the same rows at the converged point (its residual, Jacobians and $J$), stage one
   of :mod:`._lyapunov`, the adjoint vector and the motion of the equilibrium
   $d\theta/d\alpha = -(\partial_\theta\dot\Omega)^{-1}\partial_\alpha\dot\Omega$;
4. **Lyapunov**: stage two of :mod:`._lyapunov` and the transversality
   $\mathrm{Re}\langle p, D^2\tilde F[\delta, q]\rangle$, $\delta = (d\theta/d\alpha, 0, 1, 0)$.

So the compiled program holds the vector field's third-order directional derivative once (it
includes every lower order), not one copy per use. The derivative of the solution with respect
to $p$ is the implicit one, $du = -(\partial_u r)^{-1}\partial_p r\,dp$, from the Jacobians of
the final phase (:mod:`._hopf` applies it; nothing is traced twice).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from ..kinematics import _as_vector, distance_to_singularity
from ..model import RigidBodyOscillator
from ._field import flat_field, jet
from ._lyapunov import STAGE_TWO_ROWS, from_stage_two, stage_one, stage_two_rows

__all__ = [
    "EQUILIBRIUM_TOLERANCE",
    "HopfStatus",
    "hopf_program",
    "normalisation_vector",
    "unpack_parameters",
]

EQUILIBRIUM, START, NEWTON, FINAL, LYAPUNOV, DONE = range(6)
EQUILIBRIUM_TOLERANCE = 1e-12  # Newton's rtol and atol at the guess (solve_equilibrium's)


class HopfStatus(eqx.Enumeration):
    """Outcome of :func:`rbo_jax.hopf_point`."""

    successful = ""
    equilibrium_failed = (
        "The equilibrium at the guess could not be computed (Newton on the moment balance (4.61) "
        "failed, or theta_eq_fn gave non-finite values): try another theta_guess."
    )
    no_oscillatory_pair = (
        "At the guess the linearization (4.63)-(4.67) has no complex pair of eigenvalues to "
        "follow to the imaginary axis."
    )
    not_converged = (
        "Newton's method on the Hopf system (equilibrium, eigenvalue pair on the imaginary axis) "
        "did not converge: start from a guess closer to the stability boundary."
    )
    zero_frequency = (
        "The solve reached a zero frequency: a double zero eigenvalue (Bogdanov-Takens point) "
        "or a real pair, not a Hopf point."
    )
    singular_point = "The equilibrium lies on a singular sphere |theta| = 2*pi*k of Z (4.11)."
    invalid_parameters = (
        "A model parameter is invalid (built from traced values its constructors could not "
        "check); RigidBodyOscillator.parameter_status() names it."
    )


def _code(item) -> int:
    return int(np.asarray(enum.code(item)))


def _build(model_fn, point) -> RigidBodyOscillator:
    model = model_fn(**point)
    if not isinstance(model, RigidBodyOscillator):
        raise TypeError(f"model_fn must return a RigidBodyOscillator, got {type(model).__name__}.")
    return model


def unpack_parameters(names, shapes, p) -> dict:
    """``{name: value}`` from the flat vector ``p`` of the parameters ``names`` (shapes
    ``shapes``)."""
    out, i = {}, 0
    for name, shape in zip(names, shapes):
        n = int(np.prod(shape, dtype=int))
        out[name] = p[i : i + n].reshape(shape)
        i += n
    return out


def _rows(m, vr, vi, n_p):
    """The Newton rows (module docstring), ``(18 + 3 n_p, 3, m)``."""
    E = jnp.eye(m, dtype=vr.dtype)
    z = jnp.zeros(m, dtype=vr.dtype)
    ext = jnp.zeros(m - 6, dtype=vr.dtype)
    r, i = jnp.concatenate([vr, ext]), jnp.concatenate([vi, ext])
    free = (0, 1, 2, 6)  # theta and alpha
    rows = [(E[j], z, z) for j in range(7)]
    rows += [(r, E[j], z) for j in free] + [(i, E[j], z) for j in free]
    rows += [(r, r, z), (i, i, z), (r, i, z)]
    rows += [(E[7 + k], z, z) for k in range(n_p)]
    rows += [(r, E[7 + k], z) for k in range(n_p)] + [(i, E[7 + k], z) for k in range(n_p)]
    return jnp.stack([jnp.stack(row) for row in rows])


def _system(u, w, f0, D1, D2, n_p):
    """Residual, its Jacobians with respect to the unknowns and to ``p``, ``J`` and the B's."""
    vr, vi, omega = u[5:11], u[11:17], u[4]
    wr, wi = w[:6], w[6:]
    J = D1[:6].T
    Fa, Jvr, Jvi = D1[6], D1[7], D1[11]
    Hr, Hi = D2[7:11].T, D2[11:15].T
    B = D2[15:18]
    Fp = D1[18 : 18 + n_p].T
    Hrp, Hip = D2[18 + n_p : 18 + 2 * n_p].T, D2[18 + 2 * n_p : 18 + 3 * n_p].T
    r = jnp.concatenate(
        [
            f0[3:],
            Jvr + omega * vi,
            Jvi - omega * vr,
            jnp.stack([wr @ vr + wi @ vi - 1.0, wr @ vi - wi @ vr]),
        ]
    )
    I6 = jnp.eye(6, dtype=u.dtype)
    z3 = jnp.zeros((3, 6), u.dtype)
    col_theta_alpha = jnp.concatenate(
        [jnp.concatenate([J[3:, :3], Fa[3:, None]], axis=1), Hr, Hi, jnp.zeros((2, 4), u.dtype)]
    )
    col_omega = jnp.concatenate([jnp.zeros(3, u.dtype), vi, -vr, jnp.zeros(2, u.dtype)])
    cols_vr = jnp.concatenate([z3, J, -omega * I6, wr[None], -wi[None]])
    cols_vi = jnp.concatenate([z3, omega * I6, J, wi[None], wr[None]])
    Ju = jnp.concatenate([col_theta_alpha, col_omega[:, None], cols_vr, cols_vi], axis=1)
    Jp = jnp.concatenate([Fp[3:], Hrp, Hip, jnp.zeros((2, n_p), u.dtype)])
    return r, Ju, Jp, J, Fa, B


def _small(step, x, rtol, atol):
    return jnp.max(jnp.abs(step) / (atol + rtol * jnp.abs(x))) <= 1.0


def _pick_pair(J):
    """The complex pair with the largest real part: ``(found, omega, v)``."""
    lam, V = jnp.linalg.eig(J)
    tol = 1e-8 * jnp.maximum(jnp.max(jnp.abs(lam)), 1.0)
    score = jnp.where(jnp.imag(lam) > tol, jnp.real(lam), -jnp.inf)
    i = jnp.argmax(score)
    return jnp.isfinite(score[i]), jnp.imag(lam[i]), V[:, i]


def _adjoint_vector(J, omega, q):
    r"""$p$ with $J^Tp = -i\omega p$ and $\bar p^Tq = 1$: the bordered system
    $\begin{pmatrix}J^T + i\omega E & q\\ q^H & 0\end{pmatrix}\begin{pmatrix}p\\ s\end{pmatrix}
    = \begin{pmatrix}0\\ 1\end{pmatrix}$, regular at a simple pair ($q$ spans the null space of
    $(J^T + i\omega E)^H = J - i\omega E$, so it is not in the range of $J^T + i\omega E$;
    $s = 0$)."""
    n = J.shape[0]
    A = jax.lax.complex(J.T, omega * jnp.eye(n, dtype=J.dtype))
    top = jnp.concatenate([A, q[:, None]], axis=1)
    bottom = jnp.concatenate([jnp.conj(q), jnp.zeros(1, q.dtype)])[None, :]
    rhs = jnp.asarray(np.eye(n + 1)[n], dtype=q.dtype)
    return jnp.linalg.solve(jnp.concatenate([top, bottom]), rhs)[:n]


def normalisation_vector(u):
    r"""$w = [v_r, v_i]/|v|^2$ for the eigenvector $v = v_r + iv_i$ of the Hopf solution ``u``:
    $w^Hv = 1$ there, so a warm start from ``u`` keeps its scale and phase (continuations)."""
    vr, vi = u[5:11], u[11:17]
    return jnp.concatenate([vr, vi]) / (vr @ vr + vi @ vi)


def _oriented(u):
    r"""$(\omega > 0, a, b)$: $q = a + ib$ the unit eigenvector, conjugated where the solve
    found $-\omega$."""
    vr, vi, omega = u[5:11], u[11:17], u[4]
    sign = jnp.where(omega < 0, -1.0, 1.0)
    n = jnp.sqrt(vr @ vr + vi @ vi)
    return jnp.abs(omega), vr / n, sign * vi / n, sign, n


class _Problem:
    """The Hopf system of one call: the model, the parameters and the solver's settings, and the
    steps of the loop (module docstring), one method per phase."""

    def __init__(self, model_fn, parameter, names, shapes, rtol, atol, max_steps, p, t):
        self.model_fn, self.parameter, self.names, self.shapes = model_fn, parameter, names, shapes
        self.rtol, self.atol, self.max_steps, self.p, self.t = rtol, atol, max_steps, p, t
        self.dtype, self.n_p = p.dtype, p.shape[0]
        self.m, self.n_rows = 7 + self.n_p, 18 + 3 * self.n_p

    def point(self, alpha, q=None) -> dict:
        q = self.p if q is None else q
        return {**unpack_parameters(self.names, self.shapes, q), self.parameter: alpha}

    def model(self, alpha) -> RigidBodyOscillator:
        return _build(self.model_fn, self.point(alpha))

    def field(self, y):
        r"""$\tilde F(y)$, $y = [x, \alpha, p]$."""
        model = _build(self.model_fn, self.point(y[6], y[7:]))
        return flat_field(model, self.t, throw=False)(y[:6])

    def initial_state(self, u, w, warm, theta_eq) -> dict:
        dtype, cdtype, i32 = self.dtype, np.result_type(self.dtype, np.complex64), jnp.int32
        state = dict(
            phase=jnp.where(warm, NEWTON, EQUILIBRIUM).astype(i32),
            k=jnp.asarray(0, i32),
            u=u,
            w=w,
            status=jnp.asarray(_code(HopfStatus.successful), i32),
            steps=jnp.asarray(0, i32),
            Ju=jnp.zeros((17, 17), dtype),
            Jp=jnp.zeros((17, self.n_p), dtype),
            J=jnp.zeros((6, 6), dtype),
            residual=jnp.asarray(jnp.inf, dtype),
            h11=jnp.zeros(6, dtype),
            h20=jnp.zeros(6, cdtype),
            adjoint=jnp.zeros(6, cdtype),
            dtheta=jnp.zeros(3, dtype),
            first_lyapunov=jnp.asarray(jnp.nan, dtype),
            transversality=jnp.asarray(jnp.nan, dtype),
            theta_eq=theta_eq,
            row=jnp.asarray(0, i32),
            f0=jnp.zeros(6, dtype),
            D1=jnp.zeros((self.n_rows, 6), dtype),
            D2=jnp.zeros((self.n_rows, 6), dtype),
            D3=jnp.zeros((self.n_rows, 6), dtype),
        )
        return {key: jnp.asarray(v) for key, v in state.items()}

    def directions(self, s):
        """The rows of the phase: Newton's, or stage two of the Lyapunov coefficient and the
        transversality's two (padded to the same number)."""
        u, dtype, m = s["u"], self.dtype, self.m
        newton = _rows(m, u[5:11], u[11:17], self.n_p)
        _, a, b, _, _ = _oriented(u)
        ext = jnp.zeros(m - 6, dtype)
        a, b, h11 = (jnp.concatenate([v, ext]) for v in (a, b, s["h11"]))
        h20 = jnp.concatenate([s["h20"], ext.astype(s["h20"].dtype)])
        delta = jnp.concatenate(
            [s["dtheta"], jnp.zeros(3, dtype), jnp.ones(1, dtype), jnp.zeros(self.n_p, dtype)]
        )
        z = jnp.zeros(m, dtype)
        two = jnp.concatenate(
            [
                stage_two_rows(a, b, h11, h20),
                jnp.stack([jnp.stack([delta, a, z]), jnp.stack([delta, b, z])]),
            ]
        )
        two = jnp.concatenate([two, jnp.zeros((self.n_rows - two.shape[0], 3, m), dtype)])
        return jnp.where(s["phase"] == LYAPUNOV, two, newton)

    def equilibrium(self, s, f0, D1, D2, D3):
        """Newton's step on the moment balance (4.61) at the guess."""
        J = D1[:6].T
        step = jnp.linalg.solve(J[3:, :3], -f0[3:])
        theta = s["u"][:3] + step
        k = s["k"] + 1
        done = _small(step, s["u"][:3], EQUILIBRIUM_TOLERANCE, EQUILIBRIUM_TOLERANCE)
        finite = jnp.all(jnp.isfinite(theta))
        good = done & finite & (distance_to_singularity(theta) > 1e-6)
        # a guess on a singular sphere of Z (4.11), where Z is infinite, fails: whether its first
        # step comes out finite depends on the compiler's rounding (fused multiply-adds)
        singular = (s["k"] == 0) & (distance_to_singularity(s["u"][:3]) <= 1e-6)
        failed = ~finite | singular | (done & ~good) | (~done & (k >= self.max_steps))
        new = {
            **s,
            "u": jnp.concatenate([theta, s["u"][3:]]),
            "theta_eq": theta,
            "phase": jnp.where(done, START, EQUILIBRIUM),
            "k": jnp.where(done, 0, k),
        }
        return _select(failed, _stop(new, HopfStatus.equilibrium_failed), new)

    def start(self, s, f0, D1, D2, D3):
        """The eigenvalue pair to follow, at the equilibrium."""
        found, omega, v = _pick_pair(D1[:6].T)
        u = jnp.concatenate([s["u"][:4], omega[None], jnp.real(v), jnp.imag(v)])
        new = {
            **s,
            "u": u,
            "w": jnp.concatenate([jnp.real(v), jnp.imag(v)]),
            "phase": jnp.asarray(NEWTON),
            "k": jnp.asarray(0),
        }
        return _select(found, new, _stop(s, HopfStatus.no_oscillatory_pair))

    def newton(self, s, f0, D1, D2, D3):
        """Newton's step on the Hopf system."""
        r, Ju, _, _, _, _ = _system(s["u"], s["w"], f0, D1, D2, self.n_p)
        step = jnp.linalg.solve(Ju, -r)
        u = s["u"] + step
        k = s["k"] + 1
        done = _small(step, s["u"], self.rtol, self.atol)
        new = {**s, "u": u, "k": k, "steps": k, "phase": jnp.where(done, FINAL, NEWTON)}
        failed = ~jnp.all(jnp.isfinite(u)) | (~done & (k >= self.max_steps))
        return _select(failed, _stop(new, HopfStatus.not_converged), new)

    def final(self, s, f0, D1, D2, D3):
        """At the solution: its residual and Jacobians, stage one, the adjoint vector and
        $d\theta/d\alpha$."""
        r, Ju, Jp, J, Fa, B = _system(s["u"], s["w"], f0, D1, D2, self.n_p)
        omega, a, b, sign, n = _oriented(s["u"])
        h11, h20 = stage_one(J, omega, B[0] / n**2, B[1] / n**2, sign * B[2] / n**2)
        adjoint = _adjoint_vector(J, omega, jax.lax.complex(a, b))
        dtheta = -jnp.linalg.solve(J[3:, :3], Fa[3:])
        return {
            **s,
            "Ju": Ju,
            "Jp": Jp,
            "J": J,
            "residual": jnp.max(jnp.abs(r)),
            "h11": h11,
            "h20": h20,
            "adjoint": adjoint,
            "dtheta": dtheta,
            "phase": jnp.asarray(LYAPUNOV),
        }

    def lyapunov(self, s, f0, D1, D2, D3):
        r"""$\ell_1$ and the transversality
        $\mathrm{Re}\langle p, D^2\tilde F[\delta, q]\rangle$."""
        omega = _oriented(s["u"])[0]
        l1 = from_stage_two(s["adjoint"], omega, D2, D3)
        dJq = jax.lax.complex(D2[STAGE_TWO_ROWS], D2[STAGE_TWO_ROWS + 1])
        trans = jnp.real(jnp.vdot(s["adjoint"], dJq))
        return {**s, "first_lyapunov": l1, "transversality": trans, "phase": jnp.asarray(DONE)}

    def evaluation(self, s):
        """The point $y$ and the row of directions $(t_1, t_2, t_3)$ of this iteration."""
        u = s["u"]
        y = jnp.concatenate([u[:3], jnp.zeros(3, self.dtype), u[3:4], self.p])
        return y, self.directions(s)[s["row"]]

    def advance(self, s, f0, d1, d2, d3):
        """The state after the row of this iteration (its derivatives ``f0``, ``d1``, ``d2``,
        ``d3`` by :func:`._field.jet` at :meth:`evaluation`); after the phase's last row, its
        step."""
        row = s["row"]
        put = jax.lax.dynamic_update_index_in_dim
        s = {
            **s,
            "f0": f0,
            "D1": put(s["D1"], d1, row, 0),
            "D2": put(s["D2"], d2, row, 0),
            "D3": put(s["D3"], d3, row, 0),
        }
        counts = jnp.asarray([7, 7, self.n_rows, self.n_rows, STAGE_TWO_ROWS + 2], jnp.int32)
        last = row + 1 >= counts[jnp.minimum(s["phase"], LYAPUNOV)]
        steps = (self.equilibrium, self.start, self.newton, self.final, self.lyapunov)
        branches = [
            lambda s, f=f: _typed(
                {**f(s, s["f0"], s["D1"], s["D2"], s["D3"]), "row": jnp.asarray(0)}, s
            )
            for f in steps
        ]
        branches.append(lambda s: {**s, "row": s["row"] + 1})
        return jax.lax.switch(
            jnp.where(last, jnp.minimum(s["phase"], LYAPUNOV), len(steps)), branches, s
        )

    def body(self, s):
        """One row of derivatives (:func:`._field.jet`); after the phase's last row, its step.
        A row per iteration, not the rows vmapped: XLA compiles the loop's single row faster
        (about 25 % of the program's compile time), and the solve's run time stays ~1 ms."""
        y, t = self.evaluation(s)
        return self.advance(s, *jet(self.field, y, t[0], t[1], t[2]))

    def first_state(self, theta_eq_fn, alpha0, theta0, u0, w0, warm) -> dict:
        """The loop's first state: from the equilibrium guess ``theta0`` at ``alpha0``
        (``theta_eq_fn``: its closed form, refined by Newton), or (``warm``) from the unknowns
        ``u0`` and normalisation vector ``w0``."""
        theta_start = theta0
        if theta_eq_fn is not None:
            theta_start = _as_vector(theta_eq_fn(**self.point(alpha0)), "theta_eq_fn(...)")
            theta_start = theta_start.astype(self.dtype)
        cold = jnp.concatenate([theta_start, alpha0[None], jnp.zeros(13, self.dtype)])
        return self.initial_state(
            jnp.where(warm, u0, cold),
            jnp.where(warm, w0, jnp.zeros(12, self.dtype)),
            warm,
            theta_start,
        )

    def outputs(self, s, alpha0, warm) -> tuple:
        """``(u, Ju, Jp, residual, num_steps, status, adjoint, first_lyapunov,
        transversality)`` of a finished state (:func:`hopf_program`)."""
        return (
            s["u"],
            s["Ju"],
            s["Jp"],
            s["residual"],
            s["steps"],
            self.status(s, alpha0, warm),
            s["adjoint"],
            s["first_lyapunov"],
            s["transversality"],
        )

    def status(self, s, alpha0, warm):
        """The loop's status, checked at the solution (frequency, singular sphere, parameters)
        and at the equilibrium of the guess (the foundation's domain)."""
        S, u, status = HopfStatus, s["u"], s["status"]
        scale = jnp.maximum(jnp.max(jnp.abs(s["J"])), 1.0)
        code = jnp.where(jnp.abs(u[4]) > 1e-6 * scale, status, _code(S.zero_frequency))
        code = jnp.where(distance_to_singularity(u[:3]) > 1e-6, code, _code(S.singular_point))
        ok, _, _ = self.model(u[3]).parameter_status()
        code = jnp.where(ok, code, _code(S.invalid_parameters))
        status = jnp.where(status == _code(S.successful), code, status)
        in_domain = self.model(alpha0).domain_margin(s["theta_eq"]) > 0
        return jnp.where(in_domain | warm, status, _code(S.equilibrium_failed)).astype(jnp.int32)


def _stop(s, status):
    return {**s, "phase": jnp.asarray(DONE), "status": jnp.asarray(_code(status))}


def hopf_program(
    model_fn,
    theta_eq_fn,
    parameter,
    names,
    shapes,
    rtol,
    atol,
    max_steps,
    p,
    alpha0,
    theta0,
    t,
    u0,
    w0,
    warm,
):
    r"""The Hopf point (module docstring) of ``model_fn`` in ``parameter`` with the other
    parameters ``names`` (shapes ``shapes``) flattened into ``p``, from ``alpha0`` and the
    equilibrium guess ``theta0`` (``theta_eq_fn``: its closed form, refined by Newton), or
    (``warm``) from the unknowns ``u0`` and normalisation vector ``w0`` (``[Re w, Im w]``).

    Returns plain arrays: ``(u, Ju, Jp, residual, num_steps, status, adjoint, first_lyapunov,
    transversality)`` with the status code of :class:`HopfStatus`."""
    problem = _Problem(model_fn, parameter, names, shapes, rtol, atol, max_steps, p, t)
    state = problem.first_state(theta_eq_fn, alpha0, theta0, u0, w0, warm)
    s = jax.lax.while_loop(lambda s: s["phase"] < DONE, problem.body, state)
    return problem.outputs(s, alpha0, warm)


def _select(pred, a, b):
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def _typed(new, old):
    """``new`` with the dtypes of ``old`` (the branches of ``lax.switch`` must agree)."""
    return jax.tree.map(lambda x, y: jnp.asarray(x, dtype=y.dtype), new, old)
