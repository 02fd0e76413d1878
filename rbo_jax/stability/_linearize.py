r"""Linearisation and spectra of any model at an equilibrium: sections 4.2.4, 4.4 and 4.7.

At an equilibrium (zero velocities, zero total force and moment (4.61)) the perturbation method
of 4.2.4, $\theta = \theta_{eq} + \varepsilon\varphi$, $\Omega = \varepsilon\eta$ (4.28), (4.63),
gives the linear system (4.66)–(4.67); here it is the Jacobian, by forward-mode automatic
differentiation, of the model's first-order equations in the chart of its increments at the
equilibrium (:meth:`rbo_jax.mechanics.AbstractMechanics.field`), $x = [q, w]$:

$$\dot q = Z_0\cdot w + O(\varepsilon^2),\qquad \dot w = J_q\cdot q + J_w\cdot w,$$

with $Z_0 = Z^T(\theta_{eq})$ for one body ((4.14); the identity for a rod's composed
increments), $J_q$ the stiffness (non-symmetric under follower loads: the circulatory forces
of the Nikolai paradox and of Beck's column), $J_w$ the damping and gyroscopic terms. Its
eigenvalues $p$ are the exponents of the perturbations $\propto e^{pt}$ ((4.69), (4.72) for the
Nikolai problem). Where no force depends on the velocities, $J_w = 0$ at rest (the gyroscopic
terms are quadratic) and $p = \pm\sqrt{\lambda}$ for the eigenvalues $\lambda$ of the
$m\times m$ matrix $Z_0 J_q$ (:func:`fast_spectrum`, for one body).

For one body, eliminating $\eta = Z^{-T}\dot\varphi$ gives the second-order form

$$\mathsf M\ddot\varphi + \mathsf C\dot\varphi + \mathsf K\varphi = 0,\quad
  \mathsf M = Z^{-1}AZ^{-T},\ \mathsf C = -Z^{-1}AJ_\Omega Z^{-T},\ \mathsf K = -Z^{-1}AJ_\theta$$

(:func:`second_order_form`), in which, for a purely potential problem,
$\mathsf K = \partial^2(U+V)/\partial\theta^2$ is symmetric; follower loads add its
antisymmetric (circulatory) part.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Complex, Float

from .. import _programs
from .._custom_types import Matrix
from ..kinematics import integrating_tensor_inv
from ..mechanics import AbstractMechanics, checked_parameters
from ..models.rigid_body import RigidBodyOscillator
from ._equilibrium import raising_equilibrium

__all__ = [
    "SecondOrderForm",
    "at_equilibrium",
    "eigenvalues",
    "fast_spectrum",
    "linearize",
    "second_order_form",
    "spectrum",
]


def at_equilibrium(model: AbstractMechanics, state, caller: str, theta_eq=None, **kwargs):
    """The configuration of ``state`` (``theta_eq``: the older keyword), or, for ``None``,
    the equilibrium from rest (:func:`solve_equilibrium`, raising where it fails)."""
    if not isinstance(model, AbstractMechanics):
        raise TypeError(
            f"{caller}: expected a RigidBodyOscillator, a Lattice or a Rod, got "
            f"{type(model).__name__}."
        )
    if theta_eq is not None:
        if state is not None:
            raise TypeError(f"{caller}: give the equilibrium once (state or theta_eq).")
        state = theta_eq
    if state is not None:
        return model.configuration(state, "state")
    return raising_equilibrium(model, None, caller, **kwargs)


def _matrix(model: AbstractMechanics, config, t):
    F = model.field(t, config)
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(config))
    return jax.jacfwd(F)(jnp.zeros(2 * model.free_size(), dtype))


def linearize(
    model: AbstractMechanics, state=None, *, t=0.0, theta_eq=None, **equilibrium_kwargs
) -> Float[Array, "n n"]:
    r"""The Jacobian of the first-order equations (module docstring) at the equilibrium
    ``state`` (``None``: solved from rest by :func:`rbo_jax.solve_equilibrium` with
    ``equilibrium_kwargs``), over $[q, w]$ of the free coordinates: for one body the 6×6
    Jacobian of $(\dot\theta, \dot\Omega)$ (4.55)–(4.56) with respect to $[\theta, \Omega]$ at
    $(\theta_{eq}, 0)$, the perturbation equations (4.63)–(4.67); for a lattice of $N$ bodies
    $6N\times 6N$ (body-major); for a rod the matrix over $[\delta, d, \Omega, v]$ of the bodies
    that move (the base's held coordinates left out)."""
    config = at_equilibrium(model, state, "linearize", theta_eq, **equilibrium_kwargs)
    return _matrix(model, config, t)


def _sorted_spectrum(model, config, t):
    """The eigenvalues sorted by real then imaginary part, and whether the model's parameters
    pass their checks (in this program: checked eagerly, op by op, they cost small
    compilations)."""
    p = jnp.linalg.eigvals(_matrix(model, config, t))
    return p[jnp.lexsort((p.imag, p.real))], model.parameter_status()[0]


_spectrum = _programs.jit(_sorted_spectrum, fast_compile=True)


def spectrum(
    model: AbstractMechanics, state=None, *, t=0.0, theta_eq=None, **equilibrium_kwargs
) -> Complex[Array, " n"]:
    r"""The eigenvalues of :func:`linearize` at the equilibrium ``state`` (``None``: solved from
    rest): the exponents $p$ of the perturbations $\propto e^{pt}$ ((4.69), (4.72) for the
    Nikolai problem), six for one body, $2\cdot 3N$ for a lattice, $2\cdot 6N$ for a clamped rod
    of $N$ bodies past the base. Sorted lexicographically (real part, then imaginary part). A
    model whose parameters were traced at construction is checked here: an invalid one raises,
    naming the parameter."""
    return checked_spectrum(model, state, "spectrum", t=t, theta_eq=theta_eq, **equilibrium_kwargs)


def checked_spectrum(model, state, caller: str, *, t=0.0, theta_eq=None, **equilibrium_kwargs):
    """:func:`spectrum`, its messages prefixed by ``caller``."""
    config = at_equilibrium(model, state, caller, theta_eq, **equilibrium_kwargs)
    p, ok = _spectrum(model, config, jnp.asarray(t, jnp.result_type(float)))
    return checked_parameters(model, p, caller, ok)


def fast_spectrum(
    model: AbstractMechanics, state=None, *, t=0.0, theta_eq=None
) -> Complex[Array, " n"]:
    r"""The eigenvalues of :func:`spectrum` from the block structure at rest (module
    docstring). For one body where no force depends on the velocities
    (:meth:`~rbo_jax.mechanics.AbstractMechanics.depends_on_velocity`), $p = \pm\sqrt{\lambda}$
    for the eigenvalues $\lambda$ of $C_\theta = Z^TJ_\theta$ (3×3), at a fraction of the cost
    of the whole eigenproblem, ordered $(p_1, p_2, p_3, -p_1, -p_2, -p_3)$; otherwise the whole
    Jacobian's (a lattice's or a rod's: the reduced $m\times m$ problem would square the
    spread of their spectrum, and with it the rounding of their slow modes). Not sorted (sorting
    costs as much as the rest in a vmapped map: :func:`rbo_jax.stability_map` sorts on the
    host); the same eigenvalues as :func:`spectrum` to rounding."""
    config = at_equilibrium(model, state, "fast_spectrum", theta_eq)
    return eigenvalues(model, config, t, fast=True)


def eigenvalues(model: AbstractMechanics, config, t=0.0, *, fast: bool = False):
    """The eigenvalues at the configuration ``config``, unsorted and unchecked (what a map
    computes at every point): the whole Jacobian's, or with ``fast`` those of
    :func:`fast_spectrum`."""
    # the reduced problem squares the spread of the spectrum: its rounding, eps max|p|^2, is
    # that of a slow mode's p^2 in a stiff medium (a rod's shear modes at 1e7 put a Krein
    # collision's pair off the axis before it collides), so only one body takes it
    if not fast or model.depends_on_velocity() or not isinstance(model, RigidBodyOscillator):
        return jnp.linalg.eigvals(_matrix(model, config, t))
    m = model.free_size()
    F = model.field(t, config)
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(config))
    zero = jnp.zeros(m, dtype)
    J_q = jax.jacfwd(lambda q: F(jnp.concatenate([q, zero]))[m:])(zero)
    Z0 = jax.jacfwd(lambda w: F(jnp.concatenate([zero, w]))[:m])(zero)
    r = jnp.sqrt(jnp.linalg.eigvals(Z0 @ J_q))
    return jnp.concatenate([r, -r])


class SecondOrderForm(eqx.Module):
    r"""$\mathsf M\ddot\varphi + (\mathsf D + \mathsf G)\dot\varphi
    + (\mathsf K_s + \mathsf K_c)\varphi = 0$ at an equilibrium: mass $\mathsf M$ (symmetric),
    damping $\mathsf D$ (symmetric), gyroscopic $\mathsf G$ (antisymmetric), conservative
    stiffness $\mathsf K_s$ (symmetric) and circulatory stiffness $\mathsf K_c$ (antisymmetric,
    zero for potential problems)."""

    mass: Matrix
    damping: Matrix
    gyroscopic: Matrix
    stiffness: Matrix
    circulatory: Matrix

    @property
    def full_stiffness(self) -> Matrix:
        return self.stiffness + self.circulatory


def second_order_form(
    model: RigidBodyOscillator, state=None, *, t=0.0, theta_eq=None
) -> SecondOrderForm:
    r"""The linearized equations of one body at $(\theta_{eq}, 0)$ in second-order form in the
    turn-vector perturbation $\varphi$ (module docstring): $\mathsf M = Z^{-1}AZ^{-T}$,
    $\mathsf C = -Z^{-1}AJ_\Omega Z^{-T}$, $\mathsf K = -Z^{-1}AJ_\theta$, split into symmetric
    and antisymmetric parts. Follower loads (4.57) make $\mathsf K$ non-symmetric: its
    antisymmetric part is the circulatory stiffness behind the Nikolai paradox."""
    if not isinstance(model, RigidBodyOscillator):
        raise TypeError(
            f"second_order_form: expected a RigidBodyOscillator, got {type(model).__name__}."
        )
    theta = at_equilibrium(model, state, "second_order_form", theta_eq)
    J = _matrix(model, theta, t)
    J_theta, J_Omega = J[3:, :3], J[3:, 3:]
    A = model.inertia
    Zinv = integrating_tensor_inv(theta)
    ZinvA = Zinv @ A
    mass = ZinvA @ Zinv.T
    C = -ZinvA @ J_Omega @ Zinv.T
    K = -ZinvA @ J_theta
    return SecondOrderForm(
        mass=0.5 * (mass + mass.T),
        damping=0.5 * (C + C.T),
        gyroscopic=0.5 * (C - C.T),
        stiffness=0.5 * (K + K.T),
        circulatory=0.5 * (K - K.T),
    )
