r"""A fast explicit integrator for rods: a Lie-group position–velocity Verlet (a splitting).

Without loads and damping a rod (:mod:`._rod`) is a Hamiltonian system on
$(T^*SE(3))^{N+1}$ with
$H = \sum_i \tfrac12\,\Pi_i\cdot A_i^{-1}\Pi_i + \tfrac{1}{2m_i}\,p_i^2 + U(Q, r)$,
$\Pi_i = A_i\,\Omega_i$ the body-frame kinetic moment (4.44) and $p_i = m_i v_i$. It splits into
flows solved exactly, as the lattices' splitting (:mod:`._splitting`):

- the **kick** of the potential, turns and positions fixed:
  $\dot\Pi_i = M_i$, $\dot p_i = F_i$ with the body-frame moments and world forces of
  :func:`._rod_field.forces_tangent` (couplings, foundation, loads), constant over the substep;
- the **drift** of the translational kinetic energy: $r_i \to r_i + \tau\,v_i$;
- the **free rotation** of every body, $T = \tfrac12\Pi\cdot A^{-1}\Pi$ split as
  $\tfrac{1}{2a_1}|\Pi|^2 + \sum_{k=2,3}\tfrac12(1/a_k - 1/a_1)(d_k\cdot\Pi)^2$ ($a_1$ the
  smallest principal moment, $d_k$ the principal axes): the first flow turns the body about
  $\Pi$ at the rate $|\Pi|/a_1$ with $\Pi$ constant in its frame, the others about $d_k$ at
  the rates $(1/a_k - 1/a_1)\,d_k\cdot\Pi$ with $\Pi \to Q(-\alpha d_k)\,\Pi$ (the
  $\Omega\times A\Omega$ of (4.55)), as $R_h = C_{h/2}\,S_h\,C_{h/2}$. Each turn is taken by
  the Cayley map: $2\arctan(x)$ instead of $2x$, the exact flow of a kinetic energy that is a
  function of $|\Pi|$ (or of $d_k\cdot\Pi$) alone and differs at $O(h^2)$, so each flow stays
  symplectic, and no trigonometric function is evaluated (one ``rsqrt`` per turn). A rod's
  section ($a_1 = a_2$) skips the flow about $d_2$.

One step of size $h$ is the symmetric (Strang) composition

$$K_{h/2}\;D_h\,R_h\;K_{h/2},$$

position Verlet's kick–drift–kick on the Lie group: second order, and for a conservative rod
(no follower load, no dead moment, no damping) symplectic and time-reversible, so its energy
error stays bounded (it oscillates at $O(h^2)$, it does not drift), and a free rod's kinetic
moment $\sum_i r_i\times p_i + Q_i\,\Pi_i$ is kept to rounding (every flow keeps it). The
second kick's forces are the next step's first: **one evaluation of the forces per step**.
The turns are unit quaternions, renormalised at every sample; the turn-vector of a sample is
the principal logarithm continued from the previous sample (the branch nearest to it): a body
must turn by less than $\pi$ between two samples for its turn count to be kept.

**Loads** enter the kick as they are (a follower force through the current turn): explicit and
second order, no longer symplectic. **Kelvin–Voigt damping** depends on the velocities, which
change within the kick: the second kick takes them predicted by the first kick's forces,
$\hat v = v_{n+1/2} + \tfrac h2\,F_n/m$, $\hat\Pi = \Pi_{n+1/2} + \tfrac h2\,M_n$ (an
$O(h^2)$ error in the velocities, so the scheme stays second order; explicit, no longer
time-reversible).

**The step.** Verlet is stable while $\omega h < 2$ on every mode of frequency $\omega$ (on a
damped mode $\ddot x + \eta\omega^2\dot x + \omega^2 x = 0$ with the predicted velocities:
$\omega h < 2(\sqrt{1 + \eta^2\omega^2} - \eta\omega)$, from the amplification matrix). The
stiffest mode of a slender rod is the turn of a segment against its shear or an axial wave,
many times the bending frequencies. The default step is

$$h = s\cdot 2\,(\sqrt{1 + \eta^2\bar\omega^2} - \eta\bar\omega)/\bar\omega$$

with the safety factor $s$ = :data:`SAFETY` and $\bar\omega^2$ the block Gershgorin bound
(Feingold & Varga 1962) of the couplings' stiffness scaled by the masses,
$S = D^{-1/2} K D^{-1/2}$ in the $6\times 6$ blocks of the bodies:
$\bar\omega^2 = \max_i \lambda_{max}(S_{ii}) + \sum_{j \ne i}\|S_{ij}\|_2 \ge
\omega_{max}^2$ ($K$ summed from every
coupling's $B_s^T\,\mathrm{diag}(K^\varphi_s, K^g_s)\,B_s$, $B_s$ the Jacobian of its strains
with respect to the turn increments and displacements of its two bodies at the initial state;
$D$ the masses and the smallest principal moments of inertia, $\eta$ the largest Kelvin–Voigt
time). The foundation's and the loads' stiffness are left out of the bound (small beside the
couplings' on a rod; pass ``dt`` where they are not).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import _programs
from .._validation import is_traced
from ..models.rod import (
    Rod,
    RodState,
    attached,
    forces_tangent,
    log_unit,
    matrix_of,
    strains,
    tensors,
)
from ..trajectory import SolveStatus

__all__ = [
    "SAFETY",
    "failed_after_first",
    "fixed_step_status",
    "stable_step",
    "step_of",
    "step_counts",
    "traced_counts",
    "verlet",
    "verlet_traced",
]

SAFETY = 0.9
TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------------------------
# Unit quaternions: (w (B,), v (B, 3)) by rows, or components (w, q1, q2, q3) in the step.
# --------------------------------------------------------------------------------------------


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _quaternion_of_vector(theta):
    r"""$(\cos(|\theta|/2), \sin(|\theta|/2)\,\hat\theta)$ by rows: the unit quaternions of
    turn-vectors (the identity at $\theta = 0$; not differentiated)."""
    t = jnp.sqrt(_dot(theta, theta))
    safe = jnp.where(t > 0, t, 1.0)
    return jnp.cos(0.5 * t), jnp.where(
        (t > 0)[:, None], jnp.sin(0.5 * safe)[:, None] / safe[:, None] * theta, 0.0
    )


def _log_continued(w, v, theta_old):
    r"""The turn-vector of the unit quaternions $(w, v)$: the principal one
    (:func:`._rod_field.log_unit` with $w \ge 0$) moved by $2\pi m$ along its axis to the branch
    nearest to ``theta_old``."""
    sign = jnp.where(w < 0, -1.0, 1.0)
    p = log_unit(sign * w, sign[:, None] * v)
    n2 = _dot(p, p)
    tiny = n2 < 1e-24
    o2 = _dot(theta_old, theta_old)
    axis = jnp.where(
        tiny[:, None],
        theta_old / jnp.sqrt(jnp.where(o2 > 0, o2, 1.0))[:, None],
        p / jnp.sqrt(jnp.where(tiny, 1.0, n2))[:, None],
    )
    along = jnp.sqrt(jnp.where(tiny, 0.0, n2))
    m = jnp.round((_dot(axis, theta_old) - along) / TWO_PI)
    return p + (TWO_PI * m)[:, None] * axis


# --------------------------------------------------------------------------------------------
# The default step.
# --------------------------------------------------------------------------------------------


def _coupling_jacobians(rod: Rod, Q, r):
    r"""$B_s$ (N, 6, 12): the Jacobians of every coupling's strains $(\varphi_s, \tilde g_s)$
    with respect to $(\delta_a, d_a, \delta_b, d_b)$, from 12 Jacobian-vector products (the
    bodies of one parity perturbed together: a coupling joins one even and one odd body)."""
    nb = rod.n_bodies

    def fn(x):
        phi, gap = strains(rod, jnp.einsum("bij,bjk->bik", Q, tensors(x[:, :3])), r + x[:, 3:])
        return jnp.concatenate([phi, gap], axis=1)

    parity = jnp.arange(nb) % 2
    eye = jnp.eye(6, dtype=r.dtype)
    tangents = jnp.where(
        (parity[None, None, :, None] == jnp.arange(2)[:, None, None, None]),
        eye[None, :, None, :],
        0.0,
    ).reshape(12, nb, 6)
    _, lin = jax.linearize(fn, jnp.zeros((nb, 6), r.dtype))
    out = jax.vmap(lin)(tangents).reshape(2, 6, nb - 1, 6)  # [parity, column, s, row]
    s = jnp.arange(nb - 1)
    Ba = jnp.swapaxes(out[s % 2, :, s, :], 1, 2)  # body a = s
    Bb = jnp.swapaxes(out[(s + 1) % 2, :, s, :], 1, 2)  # body b = s + 1
    return jnp.concatenate([Ba, Bb], axis=2)


def _omega_bound(rod: Rod, state: RodState):
    r"""$\bar\omega$ (module docstring): the block Gershgorin bound of the mass-scaled
    stiffness."""
    Q = tensors(jnp.asarray(state.theta))
    B = _coupling_jacobians(rod, Q, jnp.asarray(state.r))
    turn, pos = (jnp.asarray(x, B.dtype) for x in rod.free_masks())
    free = jnp.concatenate(
        [jnp.repeat(turn, 3).reshape(-1, 3), jnp.repeat(pos, 3).reshape(-1, 3)], 1
    )
    free = jnp.concatenate([free[:-1], free[1:]], axis=1)  # (N, 12)
    B = B * free[:, None, :]
    k = jnp.concatenate([jnp.asarray(rod.turn_stiffness), jnp.asarray(rod.gap_stiffness)], 1)
    K = jnp.einsum("sri,sr,srj->sij", B, k, B)  # (N, 12, 12)
    a_min = jnp.linalg.eigvalsh(jnp.asarray(rod.inertia))[:, 0]
    m = jnp.asarray(rod.mass)
    D = jnp.stack([a_min, a_min, a_min, m, m, m], axis=1)  # (N+1, 6)
    D = jnp.concatenate([D[:-1], D[1:]], axis=1)
    S = K / jnp.sqrt(D[:, :, None] * D[:, None, :])  # the couplings' parts of D^-1/2 K D^-1/2
    # block Gershgorin (Feingold & Varga 1962; symmetric diagonal blocks): every eigenvalue is
    # at most lambda_max(S_ii) + sum_j |S_ij|_2 for some body i
    zero = jnp.zeros((rod.n_bodies, 6, 6), B.dtype)
    diag = zero.at[:-1].add(S[:, :6, :6]).at[1:].add(S[:, 6:, 6:])
    off = jnp.linalg.norm(S[:, :6, 6:], ord=2, axis=(1, 2))  # (N,): |S_{s,s+1}|_2
    z1 = jnp.zeros((1,), B.dtype)
    per_body = (
        jnp.linalg.eigvalsh(diag)[:, -1] + jnp.concatenate([off, z1]) + jnp.concatenate([z1, off])
    )
    return jnp.sqrt(jnp.max(per_body))


def step_of(w, eta, safety: float = SAFETY, xp=jnp):
    r"""$s\cdot 2(\sqrt{1 + \eta^2\omega^2} - \eta\omega)/\omega$: the stable step of
    :func:`verlet` (module docstring) for the frequency bound $\omega$ and the Kelvin–Voigt time
    $\eta$, decreasing in $\omega$ (``xp``: ``jnp`` in a program, ``np`` on the host)."""
    return safety * 2.0 * (xp.sqrt(1.0 + (eta * w) ** 2) - eta * w) / w


def stable_step(rod: Rod, state: RodState, safety: float = SAFETY):
    r"""The default step of :func:`verlet` (:func:`step_of` at $\bar\omega$, one compiled
    program)."""
    w = _omega_bound(rod, state)
    eta = jnp.maximum(jnp.max(jnp.asarray(rod.turn_damping)), jnp.max(jnp.asarray(rod.gap_damping)))
    return step_of(w, eta, safety)


# a program that runs once per call, in microseconds: compiled without LLVM's optimisation
# (_programs.fast_compile_options: the same step to the last bit; benchmarks/README.md, History)
stable_step = _programs.jit(stable_step, fast_compile=True)


# --------------------------------------------------------------------------------------------
# The integrator.
# --------------------------------------------------------------------------------------------


def _cayley(q, x):
    r"""$q\otimes(1, x)/\sqrt{1 + x^2}$: $q$ turned by $2\arctan|x|$ about $x$ in its own frame
    (the Cayley map of $2x$), components ``q = (w, q1, q2, q3)``, ``x = (x1, x2, x3)``."""
    w, q1, q2, q3 = q
    x1, x2, x3 = x
    c = lax.rsqrt(1.0 + x1 * x1 + x2 * x2 + x3 * x3)
    return (
        c * (w - q1 * x1 - q2 * x2 - q3 * x3),
        c * (w * x1 + q1 + q2 * x3 - q3 * x2),
        c * (w * x2 + q2 + q3 * x1 - q1 * x3),
        c * (w * x3 + q3 + q1 * x2 - q2 * x1),
    )


def _free_rotation(inertia, q, Pi, h):
    r"""The free rotation of every body over $h$ (module docstring): the turn about $\Pi$ at the
    rate $|\Pi|/a_1$ ($\Pi$ constant in the body frame) between two half turns about the
    principal axes $d_k$, $k = 2, 3$, at the rates $(1/a_k - 1/a_1)\,d_k\cdot\Pi$ ($\Pi$ turned
    back with the body), each by the Cayley map. Components: ``q`` 4, ``Pi`` 3 arrays (B,);
    ``inertia``: ``(a, d, skip)``, ``skip`` the axes whose rate is zero (equal principal
    moments, known before tracing)."""
    a, d, skip = inertia
    order = [k for k in (1, 2) if k not in skip]

    def about_axis(k, q, Pi, tau):
        e = (d[:, 0, k], d[:, 1, k], d[:, 2, k])
        along = e[0] * Pi[0] + e[1] * Pi[1] + e[2] * Pi[2]
        x = (0.5 * tau) * (1.0 / a[:, k] - 1.0 / a[:, 0]) * along
        q = _cayley(q, (x * e[0], x * e[1], x * e[2]))
        # Pi turned by -phi about e: cos phi = (1 - x^2)/(1 + x^2), sin phi = 2x/(1 + x^2)
        den = 1.0 / (1.0 + x * x)
        c, s = (1.0 - x * x) * den, -2.0 * x * den
        exP = (
            e[1] * Pi[2] - e[2] * Pi[1],
            e[2] * Pi[0] - e[0] * Pi[2],
            e[0] * Pi[1] - e[1] * Pi[0],
        )
        Pi = tuple(c * Pi[j] + s * exP[j] + (1.0 - c) * along * e[j] for j in range(3))
        return q, Pi

    for k in order:
        q, Pi = about_axis(k, q, Pi, 0.5 * h)
    f = (0.5 * h) / a[:, 0]
    q = _cayley(q, (f * Pi[0], f * Pi[1], f * Pi[2]))
    for k in reversed(order):
        q, Pi = about_axis(k, q, Pi, 0.5 * h)
    return q, Pi


def _skipped_axes(rod: Rod):
    """The principal axes $k = 2, 3$ whose moments equal the smallest on every body (their
    free rotation is the identity), known before tracing; none where the inertia is traced."""
    A = rod.inertia
    if is_traced(A):
        return ()
    a = np.linalg.eigvalsh(np.asarray(A))
    return tuple(k for k in (1, 2) if np.all(np.abs(a[:, k] - a[:, 0]) <= 1e-12 * a[:, k]))


def _static_zeros(rod: Rod):
    """``rod`` with its attachment offsets ``None`` where they are concrete zeros (a rod's
    segments: the strains skip them in the compiled step) and whether its forces depend on the
    velocities (Kelvin–Voigt damping, friction)."""
    for name in ("attach_a", "attach_b"):
        if not attached(getattr(rod, name)):
            rod = eqx.tree_at(lambda r, name=name: getattr(r, name), rod, None)
    moving = any(load.needs_velocity for load in rod.loads)
    return rod, attached(rod.turn_damping) or attached(rod.gap_damping) or moving


def _run(rod: Rod, state0: RodState, ts, counts, dt_steps, damped: bool, principal, fixed=None):
    """Samples at ``ts`` with ``counts[k]`` equal steps of ``dt_steps[k]`` in interval k;
    ``fixed``: a Python int equal to every count, known before tracing (a loop of fixed length,
    which reverse-mode autodiff can transpose; ``counts`` then only for its shape). ``damped``:
    the forces depend on the velocities (the second kick's are evaluated at velocities predicted
    by the first kick's forces); loads that change with time are evaluated at each kick's
    time."""
    principal = (*jnp.linalg.eigh(jnp.asarray(rod.inertia)), principal)
    A = jnp.asarray(rod.inertia)
    A_inv = jnp.linalg.inv(A)
    m = jnp.asarray(rod.mass)[:, None]
    turn, pos = (jnp.asarray(x, ts.dtype)[:, None] for x in rod.free_masks())

    def omega(Pi):
        return jnp.einsum("bij,bj->bi", A_inv, Pi)

    def forces(q, r, Pi, v, t):
        Q = matrix_of(q[0], jnp.stack(q[1:], axis=-1))
        if damped:
            return forces_tangent(rod, Q, r, omega(Pi), v, t=t)
        return forces_tangent(rod, Q, r, t=t)

    def step(carry, h):
        q, r, Pi, v, M, F, t = carry
        Pi = Pi + (0.5 * h) * M
        v = v + (0.5 * h) * F / m
        r = r + h * v
        q, Pi = _free_rotation(principal, q, (Pi[:, 0], Pi[:, 1], Pi[:, 2]), h)
        Pi = jnp.stack(Pi, axis=-1)
        t = t + h
        if damped:  # the velocities predicted by the first kick's forces
            M, F = forces(q, r, Pi + (0.5 * h) * M, v + (0.5 * h) * F / m, t)
        else:
            M, F = forces(q, r, Pi, v, t)
        return q, r, Pi + (0.5 * h) * M, v + (0.5 * h) * F / m, M, F, t

    theta0 = jnp.asarray(state0.theta)
    w0, u0 = _quaternion_of_vector(theta0)
    q0 = (w0, u0[:, 0], u0[:, 1], u0[:, 2])
    Pi0 = jnp.einsum("bij,bj->bi", A, jnp.asarray(state0.Omega)) * turn
    v0 = jnp.asarray(state0.v) * pos
    r0 = jnp.asarray(state0.r)
    carry0 = (q0, r0, Pi0, v0, *forces(q0, r0, Pi0, v0, ts[0]), ts[0])

    def interval(c, inputs):
        carry, theta = c
        n, h, t_end = inputs
        carry = lax.fori_loop(0, n if fixed is None else fixed, lambda i, x: step(x, h), carry)
        q, r, Pi, v, M, F, _ = carry
        norm = lax.rsqrt(sum(c * c for c in q))
        q = tuple(c * norm for c in q)
        carry = (q, r, Pi, v, M, F, t_end)  # the sample's time, without the steps' rounding
        theta = _log_continued(q[0], jnp.stack(q[1:], axis=-1), theta)
        sample = RodState(theta, r, omega(Pi) * turn, v)
        return (carry, theta), sample

    _, samples = lax.scan(interval, (carry0, theta0), (counts, dt_steps, ts[1:]))
    first = RodState(theta0, r0, jnp.asarray(state0.Omega) * turn, v0)
    states = jax.tree_util.tree_map(lambda x, y: jnp.concatenate([x[None], y]), first, samples)
    finite = jnp.stack(
        [jnp.all(jnp.isfinite(x), axis=(1, 2)) for x in jax.tree_util.tree_leaves(states)]
    ).all(0)
    ok_until = jnp.cumprod(finite.astype(jnp.int32)).astype(bool)
    states = jax.tree_util.tree_map(
        lambda x: jnp.where(ok_until[:, None, None], x, jnp.inf), states
    )
    return states, jnp.all(finite)


# XLA's options for small programs (_programs.small_program_options: a faster first call, and
# no slower run; benchmarks/README.md, History)
_run_jit = _programs.jit(_run, small=True)


def step_counts(span, dt, xp=np):
    r"""The equal steps of each interval between samples: $\max(\lceil \Delta t_k/dt -
    10^{-9}\rceil, 1)$ (``xp``: NumPy on the host, ``jax.numpy`` in a traced program)."""
    return xp.maximum(xp.ceil(span / dt - 1e-9), 1.0)


def host_counts(ts, dt: float, max_steps: int, method: str):
    r"""``(span, counts, total)`` of a fixed-step method with concrete ``ts`` and ``dt``: each
    interval in :func:`step_counts` equal steps; a ``ValueError`` where the total is above
    ``max_steps`` or an interval's count past int32 (the programs count in int32)."""
    span = np.diff(np.asarray(ts, dtype=np.float64))
    counts = step_counts(span, dt)
    total = int(min(np.sum(counts), 2.0**62))
    if total > max_steps:
        raise ValueError(
            f"lattice.simulate: method='{method}' needs {total} steps of dt = {dt:.3g} s for "
            f"ts, more than max_steps = {max_steps}: raise max_steps or dt."
        )
    if np.max(counts) >= 2.0**31:
        raise ValueError(
            f"lattice.simulate: method='{method}' needs {int(np.max(counts))} steps of "
            f"dt = {dt:.3g} s between two samples of ts, more than 2**31 - 1: sample ts more "
            "densely or raise dt."
        )
    return span, counts, total


def verlet(rod: Rod, state0: RodState, ts, dt=None, max_steps: int = 10_000_000):
    r"""``(states, ok, steps, dt)``: the motion of ``rod`` from ``state0`` sampled at ``ts``
    (module docstring) with steps of at most ``dt`` (default :func:`stable_step` at
    ``state0``), every interval between samples in equal steps."""
    given = dt is not None
    dt = float(stable_step(rod, state0)) if dt is None else float(dt)
    if not (math.isfinite(dt) and dt > 0):
        what = "dt" if given else "the default step (from the stiffnesses and masses)"
        raise ValueError(f"lattice.simulate: {what} must be finite and > 0, got {dt}.")
    span, counts, total = host_counts(ts, dt, max_steps, "splitting")
    h = jnp.asarray(span / counts, dtype=ts.dtype)
    counts = counts.astype(np.int32)
    stripped, damped = _static_zeros(rod)
    states, ok = _run_jit(stripped, state0, ts, jnp.asarray(counts), h, damped, _skipped_axes(rod))
    return states, ok, total, dt


# --------------------------------------------------------------------------------------------
# Under a transformation (jax.jit, jax.vmap, jax.grad): no check on the host.
# --------------------------------------------------------------------------------------------


def verlet_traced(rod: Rod, state0: RodState, ts, dt=None, max_steps: int = 10_000_000):
    r"""``(states, ok, steps, dt, too_many, bad_dt)``: :func:`verlet` where a leaf of ``rod``
    or ``state0``, ``ts`` or ``dt`` is traced. The step (``dt`` or :func:`stable_step`), the
    counts $\max(\lceil \Delta t_k/dt - 10^{-9}\rceil, 1)$ and their total are computed in the
    program: ``too_many`` (the total above ``max_steps``, or a count past int32) and ``bad_dt``
    (the step not finite and > 0) are flags, nothing is run then and the samples after the
    first are ``inf``; ``ok``: every sample finite. Each interval's loop runs its own count
    (a ``while`` loop; under ``jax.vmap`` every member keeps its count: the finished ones are
    masked). A concrete ``dt`` outside (0, inf) raises :func:`verlet`'s ``ValueError``; with
    concrete ``ts`` as well the counts are known before tracing, and where they are all equal
    (evenly spaced ``ts``) each interval is a loop of fixed length, which reverse-mode autodiff
    (``jax.grad``) can transpose."""
    fixed = None
    if dt is not None and not is_traced(dt):
        value = float(dt)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"lattice.simulate: dt must be finite and > 0, got {value}.")
        if not is_traced(ts):
            span = np.diff(np.asarray(ts, dtype=np.float64))
            counts = step_counts(span, value)
            if np.sum(counts) <= max_steps and np.all(counts == counts[0]):
                fixed = int(counts[0])
    ts = jnp.asarray(ts)
    if dt is not None:
        dt = jnp.asarray(dt, dtype=ts.dtype)
    stripped, damped = _static_zeros(rod)
    return _verlet_traced(
        rod, stripped, state0, ts, dt, int(max_steps), damped, _skipped_axes(rod), fixed
    )


@eqx.filter_jit
def _verlet_traced(rod, stripped, state0, ts, dt, max_steps, damped, principal, fixed):
    """:func:`verlet_traced` in one program (inlined in the caller's; batched under vmap)."""
    if dt is None:
        dt = stable_step(rod, state0).astype(ts.dtype)
    counts, steps_of, too_many, bad_dt = traced_counts(ts, dt, max_steps)
    states, ok = _run(stripped, state0, ts, counts, steps_of, damped, principal, fixed)
    states = failed_after_first(states, too_many | bad_dt)
    steps = jnp.sum(counts.astype(jnp.result_type(int)))
    return states, ok, steps, dt, too_many, bad_dt


def traced_counts(ts, dt, max_steps):
    r"""``(counts, steps, too_many, bad_dt)`` of a fixed-step method in the program: each
    interval of ``ts`` in $\max(\lceil \Delta t_k/dt - 10^{-9}\rceil, 1)$ equal steps of
    ``steps[k]``; ``bad_dt``: ``dt`` not finite and > 0; ``too_many``: the total above
    ``max_steps`` or a count past int32 (a NaN total, from non-finite ``ts``, counts as too
    many). Where either flag is set every count is 0: nothing is run."""
    span = jnp.diff(ts)
    bad_dt = ~(jnp.isfinite(dt) & (dt > 0))
    n = step_counts(span, jnp.where(bad_dt, 1.0, dt), jnp)
    too_many = ~bad_dt & ~((jnp.sum(n) <= max_steps) & (jnp.max(n) < 2.0**31))
    counts = jnp.where(bad_dt | too_many, 0.0, n).astype(jnp.int32)
    return counts, span / n, too_many, bad_dt


def failed_after_first(states, fail):
    """``states`` (samples along the leading axis) with every sample after the first ``inf``
    where ``fail``."""
    return jax.tree_util.tree_map(
        lambda x: jnp.concatenate([x[:1], jnp.where(fail, jnp.inf, x[1:])]), states
    )


def fixed_step_status(ok, too_many, bad_dt, method: str, max_steps: int, failed: str, what="dt"):
    """``(status, messages)`` of a fixed-step ``method`` whose steps were counted in the program
    (:func:`traced_counts`' flags): ``solver_error`` where not ``ok`` (its message ``failed``),
    ``max_steps_reached``, and ``invalid_parameters`` for the step ``what``."""
    status = SolveStatus.where(ok, SolveStatus.successful, SolveStatus.solver_error)
    status = SolveStatus.where(too_many, SolveStatus.max_steps_reached, status)
    status = SolveStatus.where(bad_dt, SolveStatus.invalid_parameters, status)
    messages = {
        "max_steps_reached": (
            f"method='{method}' needs more steps of dt for ts than max_steps = {max_steps}: "
            "raise max_steps or dt."
        ),
        "solver_error": failed,
        "invalid_parameters": f"{what} must be finite and > 0 (method='{method}').",
    }
    return status, messages
