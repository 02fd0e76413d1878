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
method (optimistix). Its solution is a regular point of the system at a generic Hopf point, so
the implicit function theorem gives the derivatives of $\alpha$ with respect to every other
parameter: optimistix's implicit adjoint, i.e. ``jax.grad`` and ``jax.jacfwd`` work through
:func:`hopf_point`.

**First Lyapunov coefficient** (Kuznetsov, *Elements of Applied Bifurcation Theory*, 3rd ed.,
eq. (3.20)): with $Jq = i\omega q$, $J^Tp = -i\omega p$, $\langle q, q\rangle = 1$,
$\langle p, q\rangle = \bar p^Tq = 1$, and the multilinear forms $B = D^2F$, $C = D^3F$ at the
Hopf point (nested forward-mode derivatives),

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

from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Complex, Float, Int

from ..kinematics import _as_vector, distance_to_singularity
from ..model import RigidBodyOscillator
from ..stability import solve_equilibrium
from ._field import complex_form, flat_field, multilinear

__all__ = ["HopfStatus", "HopfPoint", "hopf_point", "first_lyapunov_coefficient"]


class HopfStatus(eqx.Enumeration):
    """Outcome of :func:`hopf_point`."""

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


class HopfPoint(eqx.Module):
    r"""A Hopf point (module docstring): the critical ``value`` of the parameter, the
    ``frequency`` $\omega > 0$ of the eigenvalue pair $\pm i\omega$, the equilibrium ``theta``,
    the critical ``eigenvector`` $q$ ($Jq = i\omega q$, $|q| = 1$) and adjoint ``adjoint``
    ($\bar p^Tq = 1$) of the flat state $[\theta, \Omega]$, the ``transversality``
    $d\,\mathrm{Re}\lambda/d\alpha$, the ``first_lyapunov`` coefficient $\ell_1$, the Newton
    ``residual`` (max norm) and ``num_steps``, and the ``status`` (:class:`HopfStatus`)."""

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
    def ok(self):
        return self.status == HopfStatus.successful

    @property
    def supercritical(self):
        r"""$\ell_1 < 0$: a stable limit cycle is born on the unstable side (soft flutter)."""
        return self.first_lyapunov < 0

    @property
    def period(self):
        return 2 * jnp.pi / self.frequency


def first_lyapunov_coefficient(F: Callable, x0, omega, q, p) -> Float[Array, ""]:
    r"""Kuznetsov's first Lyapunov coefficient $\ell_1$ (eq. (3.20) of his book; module
    docstring) of the vector field ``F`` at the Hopf point ``x0``, with $Jq = i\omega q$,
    $\langle q, q\rangle = 1$ and $J^Tp = -i\omega p$, $\langle p, q\rangle = 1$. Second and
    third derivatives of ``F`` by nested forward-mode autodiff."""
    J = jax.jacfwd(F)(x0)
    form = multilinear(F, x0)
    qb = jnp.conj(q)
    n = x0.shape[0]
    # two batched calls of B (the second needs the first's solves) and one of C
    B_qqb, B_qq = _pairs(form, [(q, qb), (q, q)])
    h11 = jnp.linalg.solve(J, jnp.real(B_qqb))
    h20 = jnp.linalg.solve(jax.lax.complex(-J, 2 * omega * jnp.eye(n)), B_qq)
    B_qh11, B_qbh20 = _pairs(form, [(q, jax.lax.complex(h11, jnp.zeros_like(h11))), (qb, h20)])
    total = (jnp.vdot(p, complex_form(form, q, q, qb)) - 2 * jnp.vdot(p, B_qh11)
             + jnp.vdot(p, B_qbh20))
    return jnp.real(total) / (2 * omega)


def _pairs(form, pairs):
    """Complex B(u, v) for several pairs (u, v) in one batched call of the real form."""
    real = [(jnp.real(u), jnp.imag(u), jnp.real(v), jnp.imag(v)) for u, v in pairs]
    U = jnp.stack([w for ur, ui, _, _ in real for w in (ur, ur, ui, ui)])
    V = jnp.stack([w for _, _, vr, vi in real for w in (vr, vi, vr, vi)])
    values = form(U, V).reshape(len(pairs), 4, -1)
    # B(ur + i ui, vr + i vi) = B(ur, vr) - B(ui, vi) + i[B(ur, vi) + B(ui, vr)]
    return [jax.lax.complex(v[0] - v[3], v[1] + v[2]) for v in values]


def _point(others: dict, parameter: str, value) -> dict:
    return {**others, parameter: value}


def _build(model_fn, point) -> RigidBodyOscillator:
    model = model_fn(**point)
    if not isinstance(model, RigidBodyOscillator):
        raise TypeError(f"model_fn must return a RigidBodyOscillator, got {type(model).__name__}.")
    return model


def _start(model_fn, theta_eq_fn, parameter, others, alpha0, theta_guess, t):
    """Equilibrium, critical eigenvalue and eigenvector at the guess."""
    point = _point(others, parameter, alpha0)
    model = _build(model_fn, point)
    if theta_eq_fn is not None:
        theta = _as_vector(theta_eq_fn(**point), "theta_eq_fn(...)")
        eq_ok = jnp.all(jnp.isfinite(theta))
    else:
        sol = solve_equilibrium(model, theta_guess, t=t)
        theta, eq_ok = sol.theta, sol.ok
    theta = jnp.where(eq_ok, theta, 0.0)
    J = jax.jacfwd(flat_field(model, t))(jnp.concatenate([theta, jnp.zeros(3)]))
    lam, V = jnp.linalg.eig(J)
    tol = 1e-8 * jnp.maximum(jnp.max(jnp.abs(lam)), 1.0)
    score = jnp.where(jnp.imag(lam) > tol, jnp.real(lam), -jnp.inf)
    i = jnp.argmax(score)
    return theta, eq_ok, jnp.isfinite(score[i]), jnp.imag(lam[i]), V[:, i]


def _residual(model_fn, parameter, t):
    def fn(u, args):
        others, w = args
        theta, alpha, omega, vr, vi = u[:3], u[3], u[4], u[5:11], u[11:17]
        F = flat_field(_build(model_fn, _point(others, parameter, alpha)), t)
        x = jnp.concatenate([theta, jnp.zeros_like(theta)])
        Fx, Jvr = jax.jvp(F, (x,), (vr,))
        Jvi = jax.jvp(F, (x,), (vi,))[1]
        wr, wi = jnp.real(w), jnp.imag(w)
        norm = jnp.stack([wr @ vr + wi @ vi - 1.0, wr @ vi - wi @ vr])
        return jnp.concatenate([Fx[3:], Jvr + omega * vi, Jvi - omega * vr, norm])

    return fn


def _adjoint_vector(J, omega, q):
    r"""$p$ with $J^Tp = -i\omega p$ and $\bar p^Tq = 1$."""
    mu, V = jnp.linalg.eig(J.T)
    p = V[:, jnp.argmin(jnp.abs(mu - jax.lax.complex(jnp.zeros_like(omega), -omega)))]
    return p / jnp.conj(jnp.vdot(p, q))


def _transversality(model_fn, parameter, others, alpha, theta, t, q, p):
    r"""$d\,\mathrm{Re}\lambda/d\alpha$ along the branch of equilibria (module docstring)."""

    def J_of(theta, alpha):
        F = flat_field(_build(model_fn, _point(others, parameter, alpha)), t)
        return jax.jacfwd(F)(jnp.concatenate([theta, jnp.zeros_like(theta)]))

    def G(theta, alpha):
        F = flat_field(_build(model_fn, _point(others, parameter, alpha)), t)
        return F(jnp.concatenate([theta, jnp.zeros_like(theta)]))[3:]

    G_theta = jax.jacfwd(G, argnums=0)(theta, alpha)
    G_alpha = jax.jacfwd(G, argnums=1)(theta, alpha)
    dtheta = -jnp.linalg.solve(G_theta, G_alpha)
    dJ = jax.jvp(J_of, (theta, alpha), (dtheta, jnp.ones_like(alpha)))[1]
    return jnp.real(jnp.vdot(p, dJ.astype(q.dtype) @ q))


def _solve(model_fn, parameter, t, others, u0, w, rtol, atol, max_steps):
    """Newton on the Hopf system from the unknowns ``u0`` with normalisation vector ``w``;
    returns the :class:`HopfPoint` (status from the solve only) and the raw solution."""
    fn = _residual(model_fn, parameter, t)
    sol = optx.root_find(fn, optx.Newton(rtol=rtol, atol=atol), u0, args=(others, w),
                         max_steps=max_steps, throw=False)
    u = sol.value
    theta, alpha, omega = u[:3], u[3], u[4]
    q = jax.lax.complex(u[5:11], u[11:17])
    q = jnp.where(omega < 0, jnp.conj(q), q)
    omega = jnp.abs(omega)
    q = q / jnp.linalg.norm(q).astype(q.dtype)
    residual = jnp.max(jnp.abs(fn(u, (others, w))))

    point = _point(others, parameter, alpha)
    model = _build(model_fn, point)
    x = jnp.concatenate([theta, jnp.zeros(3)])
    J = jax.jacfwd(flat_field(model, t))(x)
    # l1 and the transversality are not differentiated (their derivatives would need fourth
    # derivatives of the vector field): computed from stopped values, documented.
    sg = jax.lax.stop_gradient
    p = _adjoint_vector(sg(J), sg(omega), sg(q))
    F_sg = flat_field(_build(model_fn, sg(point)), t)
    l1 = first_lyapunov_coefficient(F_sg, sg(x), sg(omega), sg(q), p)
    trans = _transversality(model_fn, parameter, sg(others), sg(alpha), sg(theta), t, sg(q), p)

    S = HopfStatus
    finite = jnp.all(jnp.isfinite(u)) & jnp.isfinite(residual)
    status = S.where(sol.result == optx.RESULTS.successful, S.successful, S.not_converged)
    status = S.where(finite, status, S.not_converged)
    scale = jnp.maximum(jnp.max(jnp.abs(J)), 1.0)
    status = S.where(omega > 1e-6 * scale, status, S.zero_frequency)
    status = S.where(distance_to_singularity(theta) > 1e-6, status, S.singular_point)
    ok, _, _ = model.parameter_status()
    status = S.where(ok, status, S.invalid_parameters)
    point = HopfPoint(
        value=alpha, frequency=omega, theta=theta, eigenvector=q, adjoint=p,
        transversality=trans, first_lyapunov=l1, residual=residual,
        num_steps=sol.stats["num_steps"], status=status)
    return point, u


def _nan_unless(good, x):
    return jnp.where(good, x, jnp.full_like(x, jnp.nan))


def _masked(point: HopfPoint) -> HopfPoint:
    """NaN values where the status is not successful."""
    good = point.status == HopfStatus.successful
    names = ("value", "frequency", "theta", "eigenvector", "adjoint", "transversality",
             "first_lyapunov")
    return eqx.tree_at(lambda h: [getattr(h, n) for n in names], point,
                       [_nan_unless(good, getattr(point, n)) for n in names])


def _initial_unknowns(model_fn, theta_eq_fn, parameter, others, alpha0, theta_guess, t):
    sg = jax.lax.stop_gradient
    alpha0 = sg(alpha0)
    theta0, eq_ok, has_pair, omega0, v0 = sg(
        _start(model_fn, theta_eq_fn, parameter, sg(others), alpha0, theta_guess, t))
    u0 = jnp.concatenate([theta0, jnp.stack([alpha0, omega0]), jnp.real(v0), jnp.imag(v0)])
    return u0, v0, eq_ok, has_pair


@eqx.filter_jit
def _hopf_point(model_fn, theta_eq_fn, parameter, others, alpha0, theta_guess, t, rtol, atol,
                max_steps):
    u0, v0, eq_ok, has_pair = _initial_unknowns(model_fn, theta_eq_fn, parameter, others, alpha0,
                                                theta_guess, t)
    point, _ = _solve(model_fn, parameter, t, others, u0, v0, rtol, atol, max_steps)
    S = HopfStatus
    status = S.where(has_pair, point.status, S.no_oscillatory_pair)
    status = S.where(eq_ok, status, S.equilibrium_failed)
    return _masked(eqx.tree_at(lambda h: h.status, point, status))


def hopf_point(
    model_fn: Callable[..., RigidBodyOscillator],
    params: Mapping[str, object],
    parameter: str,
    guess,
    *,
    theta_eq_fn: Callable[..., object] | None = None,
    theta_guess=None,
    t=0.0,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int = 64,
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
      is ``theta_eq_fn(**params)`` if given (a closed form such as (4.62)), else Newton from
      ``theta_guess`` (default 0); the complex eigenvalue pair with the largest real part is
      followed.
    - `rtol`, `atol`, `max_steps`: Newton's (optimistix) tolerances and budget.

    **Returns** a :class:`HopfPoint` (module docstring for the system, $\ell_1$ and the
    transversality). Never raises for a failed solve: ``status`` says why, and the values are
    NaN. ``jax.grad``/``jax.jacfwd`` of ``value`` (and ``frequency``, ``theta``,
    ``eigenvector``) with respect to the other entries of ``params`` work by the implicit
    function theorem; ``jax.vmap`` over them works too. ``first_lyapunov``, ``transversality``
    and ``adjoint`` are computed from stopped values (their derivatives would need fourth
    derivatives of the vector field): their derivatives come out zero, differentiate them by
    finite differences. Compiled once per ``model_fn`` and structure of ``params``.

    Example: the Nikolai problem with friction (4.84), ``hopf_point(lambda M, b:
    nikolai_model(M, friction=b), {"b": 0.1}, "M", 0.1)`` gives the critical follower moment
    $M_{cr} = 2b\sqrt{K(M_{cr})/A_1}$ and $\omega = \sqrt{K/A_1}$.
    """
    if not callable(model_fn):
        raise TypeError("model_fn must be a callable model_fn(**params) -> RigidBodyOscillator.")
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping {{name: value}}, got {type(params).__name__}.")
    if not isinstance(parameter, str):
        raise TypeError(f"parameter must be the name of an entry of params, got {parameter!r}.")
    others = {str(k): jnp.asarray(v, dtype=jnp.result_type(float))
              for k, v in params.items() if k != parameter}
    guess = jnp.asarray(guess, dtype=jnp.result_type(float))
    if guess.shape != ():
        raise ValueError(f"guess must be a scalar value of {parameter!r}, got shape {guess.shape}.")
    theta_guess = jnp.zeros(3) if theta_guess is None else _as_vector(theta_guess, "theta_guess")
    return _hopf_point(model_fn, theta_eq_fn, parameter, others, guess, theta_guess, t,
                       float(rtol), float(atol), int(max_steps))
