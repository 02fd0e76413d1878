r"""Linear waves: the Bloch matrix of a lattice linearized about a uniform equilibrium.

At a uniform equilibrium (every body at rest at the same $\theta_{eq}$, all relative turns
zero) the couplings exert no moment, so $\theta_{eq}$ is an equilibrium of one body (4.61). A
small motion $\delta y_n = (\delta\theta_n, \delta\Omega_n)$ of the bodies of a chain or grid
obeys $\dot{\delta y}_n = \sum_m J_{m-n}\,\delta y_m$ with $6\times6$ blocks that depend only on
the offset $d = m - n$ (the lattice is invariant under translations), non-zero for the body
itself and its nearest neighbours. A Bloch wave $\delta y_n = \hat y\,e^{i q\cdot n}$ then solves
$\dot{\hat y} = B(q)\,\hat y$ with the Bloch matrix

$$B(q) = \sum_d J_d\,e^{i q\cdot d},$$

whose eigenvalues $\lambda(q)$ give the frequencies ($\mathrm{Im}\,\lambda$) and growth rates
($\mathrm{Re}\,\lambda$) of the waves of wavevector $q$ (radians per site along each axis).
The blocks come from automatic differentiation of the lattice's equations of motion on a
periodic cell of $3^{dim}$ bodies (each body's neighbours then distinct), once; $B(q)$ for
any $q$ is a sum, vmappable and differentiable in $q$ (group velocities
$\partial\,\mathrm{Im}\,\lambda/\partial q$) and in the parameters.

At $q = 0$, $B$ is the linearization of one body (:func:`rbo_jax.linearize`): the couplings of
a uniform motion vanish. For a chain at rest with the quadratic foundation (4.50) and a
quadratic coupling, $\omega^2 = (c + 4\kappa_b\sin^2\frac q2)/A_1$ (bending, double) and
$\omega^2 = (d + 4\kappa_t\sin^2\frac q2)/A_3$ (torsion).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._validation import is_traced
from ..kinematics import as_vector
from ..models.lattice import Lattice, rates, right_forms
from ..stability import solve_equilibrium

__all__ = ["bloch_blocks", "bloch_matrix", "dispersion", "group_velocity", "uniform_equilibrium"]


def _require_grid(lattice: Lattice, what: str):
    if not isinstance(lattice, Lattice):
        raise TypeError(
            f"lattice.{what}: expected a rbo_jax.lattice.Lattice, got {type(lattice).__name__}."
        )
    if not lattice.is_grid:
        raise ValueError(
            f"lattice.{what}: Bloch waves need a chain or grid (translation "
            "invariance); a lattice from an edge list has none."
        )
    if lattice.per_site:
        raise ValueError(
            f"lattice.{what}: Bloch waves need the same body on every site; this "
            "lattice has per-site parameters."
        )


def uniform_equilibrium(lattice: Lattice, theta_guess=None):
    r"""$\theta_{eq}$ of one body (Newton, :func:`rbo_jax.solve_equilibrium`, from
    ``theta_guess``, default 0): with every body there, the lattice is at rest.
    Differentiable with respect to the parameters by the implicit function theorem
    (:func:`rbo_jax.solve_equilibrium`'s)."""
    _require_grid(lattice, "uniform_equilibrium")
    return solve_equilibrium(lattice.body, theta_guess).theta


def _cell(lattice: Lattice) -> Lattice:
    """The same bodies and coupling on a periodic cell of 3 sites per axis."""
    return Lattice(lattice.body, lattice.coupling, (3,) * lattice.ndim, (True,) * lattice.ndim)


def _offsets(ndim: int) -> np.ndarray:
    """The offset of every site of the 3-per-axis cell from site 0: -1, 0, 1 per axis
    (``(3**ndim, ndim)``, row-major like the sites)."""
    return np.array(
        [[(i + 1) % 3 - 1 for i in idx] for idx in itertools.product(range(3), repeat=ndim)]
    )


def bloch_blocks(lattice: Lattice, theta_eq=None):
    r"""The blocks $J_d$ (``(3**dim, 6, 6)``) and offsets $d$ (``(3**dim, dim)``) of the
    linearized lattice about the uniform equilibrium ``theta_eq`` (default
    :func:`uniform_equilibrium`): $J_d = \partial\dot y_0/\partial y_d$, the state ordered
    $[\theta, \Omega]$ as in :func:`rbo_jax.linearize`."""
    _require_grid(lattice, "bloch_blocks")
    theta_eq = uniform_equilibrium(lattice) if theta_eq is None else as_vector(theta_eq)
    cell = _cell(lattice)
    n = cell.size
    forms = right_forms(cell)

    def field0(y):  # y (6, n): the rates of body 0
        th_dot, Om_dot = rates(cell, forms, 0.0, y[:3], y[3:])
        return jnp.concatenate([th_dot[:, 0], Om_dot[:, 0]])

    y_eq = jnp.concatenate(
        [jnp.broadcast_to(theta_eq[:, None], (3, n)), jnp.zeros((3, n), theta_eq.dtype)]
    )
    J = jax.jacfwd(field0)(y_eq)  # (6, 6, n)
    return jnp.moveaxis(J, -1, 0), jnp.asarray(_offsets(lattice.ndim))


def bloch_matrix(lattice: Lattice, q, theta_eq=None, blocks=None):
    r"""$B(q) = \sum_d J_d\,e^{i q\cdot d}$ (module docstring), ``(6, 6)`` complex; ``q`` a
    number (chain) or one wavenumber per axis; ``blocks`` from :func:`bloch_blocks` to reuse
    them."""
    J, d = bloch_blocks(lattice, theta_eq) if blocks is None else blocks
    q = jnp.atleast_1d(jnp.asarray(q)).astype(J.dtype)
    if q.shape != (d.shape[1],):
        raise ValueError(
            f"lattice.bloch_matrix: q needs one wavenumber per axis "
            f"({d.shape[1]}), got shape {q.shape}."
        )
    phase = jnp.exp(lax.complex(jnp.zeros((), q.dtype), d.astype(q.dtype) @ q))
    return jnp.einsum("k,kij->ij", phase, lax.complex(J, jnp.zeros_like(J)))


def dispersion(lattice: Lattice, q, theta_eq=None, blocks=None):
    r"""The six eigenvalues $\lambda(q)$ of the Bloch matrix (:func:`bloch_matrix`), sorted by
    frequency $\mathrm{Im}\,\lambda$ (then growth rate): for a stable lattice at rest
    $\pm i\omega_k(q)$, the three branches' frequencies the last three. vmappable over ``q``
    (pass ``blocks`` from :func:`bloch_blocks` to differentiate once) and differentiable."""
    lam = jnp.linalg.eigvals(bloch_matrix(lattice, q, theta_eq, blocks))
    order = jnp.lexsort((jnp.real(lam), jnp.imag(lam)))
    return lam[order]


def group_velocity(lattice: Lattice, q, theta_eq=None, blocks=None):
    r"""$\partial\omega_k/\partial q$ of the six branches of :func:`dispersion` (``(6, dim)``;
    ``(6,)`` for a number ``q``), by forward-mode differentiation of the eigenvalues."""
    blocks = bloch_blocks(lattice, theta_eq) if blocks is None else blocks
    scalar = not is_traced(q) and np.ndim(q) == 0
    q = jnp.atleast_1d(jnp.asarray(q, dtype=blocks[0].dtype))
    v = jax.jacfwd(lambda k: jnp.imag(dispersion(lattice, k, blocks=blocks)))(q)
    return v[:, 0] if scalar else v
