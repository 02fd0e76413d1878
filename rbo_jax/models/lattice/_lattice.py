r"""A lattice of rigid body oscillators: bodies on the sites, elastic couplings of neighbours.

Bodies $i = 1\dots N$ are rigid body oscillators (:class:`rbo_jax.RigidBodyOscillator`: inertia
$A_i$, foundation $U_i(\theta_i)$, loads). A pair of neighbours $(i, j)$ is coupled through its
**relative turn-vector**, the principal turn-vector of the turn from body $i$ to body $j$ seen
in body $i$'s frame,

$$\varphi_{ij} = \mathrm{turn\_vector}\big(Q^T(\theta_i)\cdot Q(\theta_j)\big), \qquad
\varphi_{ji} = -\varphi_{ij},$$

with an energy $W(\varphi_{ij})$ of any foundation form (a coupling *is* a foundation of the
relative turn: :class:`rbo_jax.QuadraticFoundation` with the bending and torsional stiffnesses
$\kappa_b$, $\kappa_t$, an isotropic or barrier energy, a user's). With the total energy
$U = \sum_i U_i(\theta_i) + \sum_{(i,j)} W(\varphi_{ij})$ every body obeys the right form
(4.55)–(4.56) with $dU/d\theta_i$ in place of its own foundation's gradient:

$$A_i\cdot\dot\Omega_i + \Omega_i\times A_i\cdot\Omega_i + Z(\theta_i)\cdot
  \frac{\partial U}{\partial\theta_i} = P_i^T\cdot M_{ex,i}, \qquad
  \dot\theta_i = Z^T(\theta_i)\cdot\Omega_i.$$

Every edge counts once. Topologies: a chain or a grid (square in 2-D, cubic in 3-D) of
nearest neighbours, periodic or with free ends along each axis (:func:`chain`, :func:`grid`),
whose couplings are stencils (``jnp.roll``), or any list of edges
(:meth:`Lattice.from_edges`), whose forces are segment sums (the transpose of a gather): nothing
dense in $N$.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from ..._validation import checks_status, is_traced
from ...foundations import AbstractFoundation
from ...kinematics import distance_to_singularity
from ...mechanics import AbstractMechanics, EquilibriumStatus
from ..rigid_body import RigidBodyOscillator
from . import _field

__all__ = ["Lattice", "chain", "grid"]


def _check_body(body, shape) -> bool:
    """Whether ``body`` holds per-site parameters (every array leaf with leading axes
    ``shape``), else one body for every site; anything else is refused."""
    if not isinstance(body, RigidBodyOscillator):
        raise TypeError(
            f"lattice: body must be a RigidBodyOscillator (one for every site, or one "
            f"whose parameters carry the lattice's shape {shape} in front, e.g. built "
            f"with jax.vmap), got {type(body).__name__}."
        )
    inertia_shape = tuple(np.shape(body.inertia))
    if inertia_shape == (3, 3):
        return False
    if inertia_shape != tuple(shape) + (3, 3):
        raise ValueError(
            f"lattice: body.inertia must have shape (3, 3) (one body for every "
            f"site) or {tuple(shape) + (3, 3)} (per-site bodies of the lattice's "
            f"shape {tuple(shape)}), got {inertia_shape}."
        )
    for leaf in jax.tree_util.tree_leaves(eqx.filter(body, eqx.is_array)):
        if tuple(np.shape(leaf))[: len(shape)] != tuple(shape):
            raise ValueError(
                f"lattice: per-site bodies need every parameter with leading axes "
                f"{tuple(shape)} (build them with jax.vmap); a leaf has shape "
                f"{tuple(np.shape(leaf))}."
            )
    return True


class Lattice(AbstractMechanics):
    r"""N rigid body oscillators coupled through their relative turns (module docstring).

    Build one with :func:`chain`, :func:`grid` or :meth:`Lattice.from_edges`. Fields: ``body``
    (a :class:`rbo_jax.RigidBodyOscillator` for every site, or per-site parameters: every leaf
    with the lattice's ``shape`` in front), ``coupling`` (an :class:`rbo_jax.AbstractFoundation`
    of the relative turn), ``edges`` (``(E, 2)`` site indices, or ``None`` for a chain or grid),
    ``shape`` and ``periodic`` (static). Every float leaf may be traced: lattices can be built
    inside ``jax.vmap`` and differentiated with respect to their parameters.
    """

    body: RigidBodyOscillator
    coupling: AbstractFoundation
    edges: Int[Array, "E 2"] | None
    shape: tuple[int, ...] = eqx.field(static=True)
    periodic: tuple[bool, ...] = eqx.field(static=True)
    per_site: bool = eqx.field(static=True)

    def __init__(self, body, coupling, shape, periodic, edges=None):
        shape = tuple(int(n) for n in shape)
        if not shape or any(n < 1 for n in shape):
            raise ValueError(f"lattice: the shape must be positive integers, got {shape}.")
        if not isinstance(coupling, AbstractFoundation):
            raise TypeError(
                f"lattice: coupling must be an rbo_jax foundation of the relative "
                f"turn (e.g. QuadraticFoundation(kappa_b, kappa_t, k)), got "
                f"{type(coupling).__name__}."
            )
        self.per_site = _check_body(body, shape)
        self.body = body
        self.coupling = coupling
        self.shape = shape
        self.periodic = tuple(bool(p) for p in periodic)
        if edges is not None:
            edges = _check_edges(edges, math.prod(shape))
        self.edges = edges

    @classmethod
    def from_edges(cls, body, edges, coupling) -> Lattice:
        r"""Bodies ``0 … N−1`` coupled along ``edges``, an ``(E, 2)`` array of site indices (each
        pair once; $\varphi_{ij}$ from the first to the second). ``body`` is one body for every
        site or per-site parameters with a leading axis N; N is that axis, or the largest index
        plus one."""
        e = np.asarray(edges) if not is_traced(edges) else edges
        if is_traced(e):
            raise TypeError("lattice: edges must be concrete (a NumPy or JAX array of indices).")
        n = (
            int(np.shape(body.inertia)[0])
            if np.ndim(body.inertia) == 3
            else (int(np.max(e)) + 1 if np.size(e) else 1)
        )
        return cls(body, coupling, (n,), (False,), edges=e)

    @property
    def size(self) -> int:
        """The number of bodies N."""
        return math.prod(self.shape)

    @property
    def ndim(self) -> int:
        """1 for a chain, 2 or 3 for a grid (an edge list counts as 1)."""
        return len(self.shape)

    @property
    def is_grid(self) -> bool:
        """Whether the couplings are nearest neighbours of a chain or grid (not an edge list)."""
        return self.edges is None

    def site_bodies(self) -> RigidBodyOscillator:
        """The body, per-site leaves flattened to a leading axis N (shared leaves as they are)."""
        if not self.per_site:
            return self.body
        n, k = self.size, len(self.shape)
        return jax.tree_util.tree_map(
            lambda x: jnp.reshape(x, (n,) + jnp.shape(x)[k:]) if eqx.is_array(x) else x, self.body
        )

    def body_axes(self):
        """``in_axes`` of ``jax.vmap`` over the sites for :meth:`site_bodies`."""
        return jax.tree_util.tree_map(
            lambda x: 0 if (self.per_site and eqx.is_array(x)) else None, self.body
        )

    def site(self, i: int = 0) -> RigidBodyOscillator:
        """The body at flat site index ``i`` (a single :class:`RigidBodyOscillator`)."""
        if not self.per_site:
            return self.body
        bodies = self.site_bodies()
        return jax.tree_util.tree_map(lambda x: x[i] if eqx.is_array(x) else x, bodies)

    def with_body(self, body) -> Lattice:
        """The same topology and coupling with another body."""
        return Lattice(body, self.coupling, self.shape, self.periodic, self.edges)

    def with_coupling(self, coupling) -> Lattice:
        """The same topology and bodies with another coupling."""
        return Lattice(self.body, coupling, self.shape, self.periodic, self.edges)

    # ---- the mechanics (rbo_jax.mechanics.AbstractMechanics) ---------------------------------
    # Increments are added to every body's turn-vector (each body's foundation energy U(theta)
    # tells turns by 2*pi apart), one block of three per body; the static residual is every
    # body's angular acceleration at rest, which vanishes with its moment.

    def rest(self):
        """Every turn zero, ``(N, 3)``."""
        return jnp.zeros((self.size, 3), jnp.result_type(float))

    def configuration(self, guess, name: str = "guess"):
        """``guess`` as turn-vectors ``(N, 3)`` (one (3,) vector: every body; ``None``: 0)."""
        if guess is None:
            return self.rest()
        theta = jnp.asarray(guess, dtype=jnp.result_type(float))
        if theta.shape == (3,):
            theta = jnp.broadcast_to(theta, (self.size, 3))
        if theta.shape != (self.size, 3):
            raise ValueError(
                f"{name} must be a turn-vector (3,) or one per body ({self.size}, 3), got shape "
                f"{theta.shape}."
            )
        return theta

    def block_shape(self) -> tuple[int, int]:
        """One block of three turn components per body."""
        return (self.size, 3)

    def retract(self, theta, x):
        r"""$\theta_i + x_i$."""
        return theta + x

    def increment_scale(self, theta):
        r"""$1 + |\theta_{ij}|$."""
        return 1.0 + jnp.abs(theta)

    def static_residual(self, t, theta, x, load_scale=1.0):
        """Every body's angular acceleration at rest, ``(N, 3)``: its moments (foundation,
        couplings, loads times ``load_scale``) through $A_i^{-1}$ (4.55)."""
        th = (theta + x).T
        scale = None if isinstance(load_scale, float) and load_scale == 1.0 else load_scale
        forms = _field.right_forms(self, throw=False)
        _, Omega_dot = _field.rates(self, forms, t, th, jnp.zeros_like(th), load_scale=scale)
        return Omega_dot.T

    def structure(self) -> str:
        """``"tridiagonal"`` for an open chain (each body coupled to the one before and the one
        after), ``"dense"`` otherwise."""
        if self.is_grid and self.ndim == 1 and not self.periodic[0]:
            return "tridiagonal"
        return "dense"

    def configuration_status(self, theta, singular_tol: float = 1e-6):
        """``singular_point`` where a body lies on a singular sphere of $Z$ (4.11),
        ``domain_error`` where one leaves its foundation's domain (4.49)."""
        S = EquilibriumStatus
        margin = jax.vmap(lambda b, th: b.domain_margin(th), in_axes=(self.body_axes(), 0))(
            self.site_bodies(), theta
        )
        status = S.where(jnp.all(margin > 0), S.successful, S.domain_error)
        far = jnp.all(jax.vmap(distance_to_singularity)(theta) > singular_tol)
        return S.where(far, status, S.singular_point)

    def parameter_checks(self) -> list:
        """``(valid, message)`` of every body (each check over all sites) and of the coupling."""
        if self.per_site:
            bodies = self.site_bodies()
            checks = jax.vmap(
                lambda b: [v for v, _ in b.parameter_checks()], in_axes=(self.body_axes(),)
            )(bodies)
            messages = [m for _, m in self.site(0).parameter_checks()]
            own = [(jnp.all(v), f"lattice body: {m}") for v, m in zip(checks, messages)]
        else:
            own = [(v, f"lattice body: {m}") for v, m in self.body.parameter_checks()]
        return own + [(v, f"lattice coupling: {m}") for v, m in self.coupling.parameter_checks()]

    def parameter_status(self):
        """``(ok, which, messages)`` of :meth:`parameter_checks`."""
        return checks_status(self.parameter_checks())

    def free_size(self) -> int:
        """Three turn components per body."""
        return 3 * self.size

    def free_increments(self, q):
        """One block of three per body, ``(N, 3)``."""
        return jnp.reshape(q, (self.size, 3))

    def field(self, t, theta, *, throw: bool = False):
        r"""$x = [q, \Omega]$ (body-major, ``(2 \cdot 3N,)``) $\mapsto$ the rates of
        (4.55)–(4.56) of every body at $\theta_i + q_i$, with the couplings' moments."""
        forms = _field.right_forms(self, throw)
        n = 3 * self.size

        def F(x):
            th = (theta + jnp.reshape(x[:n], (-1, 3))).T
            theta_dot, Omega_dot = _field.rates(self, forms, t, th, jnp.reshape(x[n:], (-1, 3)).T)
            return jnp.concatenate([jnp.ravel(theta_dot.T), jnp.ravel(Omega_dot.T)])

        return F

    def depends_on_velocity(self) -> bool:
        """Whether a body's load depends on its angular velocity (friction (4.84), ...)."""
        return self.body.depends_on_velocity()

    def state_at_rest(self, theta):
        """The turn-vectors ``(N, 3)``."""
        return theta


def _check_edges(edges, n: int):
    e = np.asarray(edges)
    if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):
        raise ValueError(
            f"lattice: edges must be an integer array of shape (E, 2), got {e.dtype} {e.shape}."
        )
    if e.size and (e.min() < 0 or e.max() >= n):
        raise ValueError(
            f"lattice: edges must index the {n} sites 0 … {n - 1}, got indices "
            f"{int(e.min())} … {int(e.max())}."
        )
    if np.any(e[:, 0] == e[:, 1]):
        raise ValueError(
            "lattice: an edge couples a body to itself; every edge needs two different sites."
        )
    return jax.device_put(e.astype(np.int32))


def chain(n: int, body, coupling, *, periodic: bool = True) -> Lattice:
    r"""A chain of ``n`` bodies, each coupled to the next (and the last to the first when
    ``periodic``). ``body``: one :class:`rbo_jax.RigidBodyOscillator` for every site, or per-site
    parameters with a leading axis ``n``."""
    if int(n) < 2:
        raise ValueError(f"lattice.chain: n must be >= 2, got {n}.")
    return Lattice(body, coupling, (int(n),), (periodic,))


def grid(
    shape: Sequence[int], body, coupling, *, periodic: bool | Sequence[bool] = True
) -> Lattice:
    r"""A square (2-D) or cubic (3-D) grid of bodies, each coupled to its nearest neighbour along
    every axis; ``periodic`` for every axis or one flag per axis (free ends otherwise). Sites in
    row-major order (C order: the last axis fastest). ``body``: as :func:`chain`, per-site
    parameters with leading axes ``shape``."""
    shape = tuple(int(n) for n in shape)
    if len(shape) not in (1, 2, 3) or any(n < 2 for n in shape):
        raise ValueError(
            f"lattice.grid: shape must have 1, 2 or 3 axes of at least 2 sites, got {shape}."
        )
    if isinstance(periodic, (bool, np.bool_)):
        periodic = (bool(periodic),) * len(shape)
    periodic = tuple(bool(p) for p in periodic)
    if len(periodic) != len(shape):
        raise ValueError(
            f"lattice.grid: periodic needs one flag per axis ({len(shape)}), got {periodic}."
        )
    return Lattice(body, coupling, shape, periodic)
