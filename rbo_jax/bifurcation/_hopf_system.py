r"""The extended system of a flutter point, for any model, and its solve as one program.

With $F(x; \alpha)$ the model's first-order equations in the chart of its increments at a
configuration (:meth:`rbo_jax.mechanics.AbstractMechanics.field`, $x = [q, w]$, $m$ free
coordinates, $n = 2m$) and $\alpha$ the free parameter, an equilibrium is $G(q, \alpha) =
F([q, 0]; \alpha)_w = 0$ (the moment balance (4.61) for one body) and its linearisation is
$J = \partial F/\partial x$ ((4.63)–(4.67)). Two kinds of flutter point are solved for:

**Hopf** (``kind="hopf"``): a pair $\pm i\omega$ crosses the imaginary axis. Unknowns
$(q, \alpha, \omega, v)$, $v \in \mathbb C^n$:

$$G(q, \alpha) = 0,\qquad (J - i\omega)\,v = 0,\qquad C^Hv = e_1 .$$

**Krein collision** (``kind="collision"``: undamped systems under follower loads, Beck's,
Pflüger's and Ziegler's columns, whose eigenvalues stay on the axis below the flutter load):
two pairs $i\omega_1$, $i\omega_2$ merge into a double eigenvalue $i\omega$ with a Jordan chain,
past which they leave the axis as $\pm a + i\omega$. Unknowns $(q, \alpha, \omega, v, u)$:

$$G = 0,\qquad (J - i\omega)\,v = 0,\qquad (J - i\omega)\,u = v,\qquad C^Hv = e_1,\qquad
C^Hu = 0 .$$

$C$ ($n\times k$, orthonormal) spans the eigenvectors of the followed eigenvalue at the start:
$k$ is its multiplicity there (2 for a rod bending alike in two planes, 1 for a simple pair,
where $C^Hv = 1$ is the normalisation of Kuznetsov's Hopf system). The real and imaginary
parts make a consistent system of real equations, over-determined where $k > 1$ or for a
collision, with a Jacobian of full column rank at a generic flutter point: Newton's method
(:func:`rbo_jax.solvers.newton_step`, the one loop :func:`rbo_jax.solvers.iterate`) takes the
least-squares step, rows equilibrated first (a rod's stiff shear and stretch rows are $10^{12}$
times its bending rows). The Jacobian is the forward-mode one of the residual, whose
$\partial_q(Jv)$ are second directional derivatives of $F$.

The start from the eigenvalues at the guess is :mod:`._hopf_start`'s, the solve and the
solution's chart :mod:`._hopf_program`'s.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _enumeration as enum
from ..mechanics import AbstractMechanics

__all__ = [
    "KINDS",
    "adjoint_vector",
    "HopfStatus",
    "Layout",
    "Raw",
    "Spec",
    "evaluate",
    "model_at",
    "oriented",
    "residual",
    "unpack_parameters",
]

KINDS = ("auto", "hopf", "collision")
ROUNDING = 64  # machine epsilons: an equilibrated residual at the rounding level has converged
ZERO_FREQUENCY = 1e-9  # |omega| at most this times max |p| at the solution: not a Hopf point
# free coordinates of the models whose Newton differences come from their linearisation
# (evaluate): one body's 3, a chain of two's 6
SHARED_UP_TO = 6


class HopfStatus(eqx.Enumeration):
    """Outcome of :func:`rbo_jax.hopf_point`."""

    successful = ""
    equilibrium_failed = (
        "The equilibrium at the guess could not be computed (Newton on the balance of forces "
        "and moments (4.61) failed, or theta_eq_fn gave non-finite values): try another guess "
        "of the equilibrium or more load steps."
    )
    no_oscillatory_pair = (
        "At the guess the linearization (4.63)-(4.67) has no complex pair of eigenvalues to "
        "follow to the imaginary axis (or, for a collision, no two distinct frequencies)."
    )
    not_converged = (
        "Newton's method on the flutter system (equilibrium, eigenvalue pair on the imaginary "
        "axis) did not converge: start from a guess closer to the stability boundary (or the "
        "followed eigenvalue has more eigenvectors than multiplicity allows)."
    )
    zero_frequency = (
        "The solve reached a zero frequency: a double zero eigenvalue (Bogdanov-Takens point) "
        "or a real pair, not a Hopf point."
    )
    singular_point = "The equilibrium lies on a singular sphere |theta| = 2*pi*k of Z (4.11)."
    invalid_parameters = (
        "A model parameter is invalid (built from traced values its constructors could not "
        "check); the model's parameter_status() names it."
    )


def code_of(item) -> int:
    """The integer code of a status item."""
    return int(np.asarray(enum.code(item)))


class Spec(NamedTuple):
    """What a flutter program is compiled for (hashable)."""

    model_fn: Callable
    state_fn: Callable | None  # the equilibrium's closed form at the guess (theta_eq_fn)
    parameter: str
    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    kind: str
    rtol: float
    atol: float
    max_steps: int
    cluster: float
    by_frequency: bool  # the start follows the pair nearest a given frequency (a traced value)
    multiplicity: int
    steps: int
    lyapunov: bool = True  # the first Lyapunov coefficient at a simple Hopf pair


class Raw(NamedTuple):
    r"""The program's outputs: the critical configuration, the unknowns ``u`` (their $q$ zero,
    in the chart at ``config``), the normalisation basis ``C``, the system's Jacobian there, the
    equilibrated residual, Newton's steps, the status code, the adjoint, $\\ell_1$, the
    transversality and the multiplicity found at the start."""

    config: object
    u: jax.Array
    C: jax.Array
    jacobian: jax.Array  # the model's linearisation J at the solution
    residual: jax.Array
    num_steps: jax.Array
    status: jax.Array
    adjoint: jax.Array
    first_lyapunov: jax.Array
    transversality: jax.Array


def unpack_parameters(names, shapes, p) -> dict:
    """``{name: value}`` from the flat vector ``p`` (NumPy or JAX) of the parameters
    ``names``."""
    out, i = {}, 0
    for name, shape in zip(names, shapes):
        size = int(np.prod(shape, dtype=int))
        out[name] = p[i : i + size].reshape(shape)
        i += size
    return out


def model_at(spec: Spec, alpha, p) -> AbstractMechanics:
    """``model_fn`` at the parameter ``alpha`` and the flat others ``p``."""
    model = spec.model_fn(
        **{**unpack_parameters(spec.names, spec.shapes, p), spec.parameter: alpha}
    )
    if not isinstance(model, AbstractMechanics):
        raise TypeError(
            "model_fn must return a RigidBodyOscillator, a Lattice or a Rod, got "
            f"{type(model).__name__}."
        )
    return model


def _split(z):
    return jnp.concatenate([jnp.real(z), jnp.imag(z)])


def _times_i(z):
    return jax.lax.complex(-jnp.imag(z), jnp.real(z))


class Layout(NamedTuple):
    r"""Where the unknowns sit in ``u``: $[q\\ (m), \\alpha, \\omega, v_r, v_i, (u_r, u_i)]$."""

    m: int
    kind: str

    @property
    def n(self) -> int:
        return 2 * self.m

    @property
    def size(self) -> int:
        return self.m + 2 + (4 if self.kind == "collision" else 2) * self.n

    def rows(self, k: int) -> int:
        r"""The real equations of :func:`equations` with a basis $C$ of ``k`` columns: $G$ ($m$),
        $(J - i\omega)v$ ($2n$), $C^Hv$ ($2k$), and for a collision the chain's $2n + 2k$."""
        return self.m + (2 if self.kind == "collision" else 1) * (2 * self.n + 2 * k)

    def unpack(self, u):
        m, n = self.m, self.n
        u, tail = u[: m + 1], u[m + 1 :]
        q, alpha, omega = u[:m], u[m], tail[0]
        v = jax.lax.complex(tail[1 : 1 + n], tail[1 + n : 1 + 2 * n])
        chain = None
        if self.kind == "collision":
            o = 1 + 2 * n
            chain = jax.lax.complex(tail[o : o + n], tail[o + n : o + 2 * n])
        return q, alpha, omega, v, chain

    def pack(self, q, alpha, omega, v, chain=None):
        parts = [q, alpha[None], omega[None], jnp.real(v), jnp.imag(v)]
        if self.kind == "collision":
            parts += [jnp.real(chain), jnp.imag(chain)]
        return jnp.concatenate(parts)


def equations(layout: Layout, f0, products, omega, v, chain, C):
    """The flutter system (module docstring) from the field $F$ at $[q, 0]$ (``f0``) and its
    Jacobian's products with $[v_r, v_i, u_r, u_i]$ (``products``), real."""
    e1 = jnp.zeros(C.shape[1], C.dtype).at[0].set(1.0)
    Ch = jnp.conj(C).T
    Jv = jax.lax.complex(products[0], products[1])
    parts = [f0[layout.m :], _split(Jv - _times_i(omega) * v), _split(Ch @ v - e1)]
    if chain is not None:
        Ju = jax.lax.complex(products[2], products[3])
        parts += [_split(Ju - _times_i(omega) * chain - v), _split(Ch @ chain)]
    return jnp.concatenate(parts)


def _vectors(v, chain):
    vectors = [jnp.real(v), jnp.imag(v)]
    if chain is not None:
        vectors += [jnp.real(chain), jnp.imag(chain)]
    return jnp.stack(vectors)


def residual(spec: Spec, layout: Layout, u, config, C, p, t):
    """The flutter system (module docstring) at the unknowns ``u`` in the chart at
    ``config``, real."""
    q, alpha, omega, v, chain = layout.unpack(u)
    F = model_at(spec, alpha, p).field(t, config)
    x0 = jnp.concatenate([q, jnp.zeros_like(q)])
    jvp = lambda d: jax.jvp(F, (x0,), (d,))  # noqa: E731
    f0, products = jax.vmap(jvp, out_axes=(None, 0))(_vectors(v, chain))
    return equations(layout, f0, products, omega, v, chain, C)


def evaluate(spec: Spec, layout: Layout, u, config, C, p, t, central=True):
    r"""The system, its Jacobian in the unknowns and the model's linearisation $J$ at ``u``:
    exact in the unknowns the system is linear in, $\omega$, $v$ (and $u$), from $J$ (forward
    mode, first derivatives of the model); by central differences in $q$ and $\alpha$ where
    ``central`` (zero columns otherwise: the phases that do not need them). Second derivatives
    of the model there would cost a larger program; they only steer Newton's iteration: the
    residual, hence the solution, is exact, and the implicit derivative takes the exact
    Jacobian (:mod:`._hopf`). A model of at most :data:`SHARED_UP_TO` free coordinates takes
    its differences from the linearisation at the shifted points too (one vmapped copy of
    $F$'s Jacobian in the program: it compiles faster than a second copy for the residual, and
    runs as fast at that size); a larger one from the residual's own products."""
    k = layout.m + 1
    _, alpha, _, _, _ = layout.unpack(u)
    scale = jnp.ones(k, u.dtype).at[-1].set(jnp.maximum(jnp.abs(alpha), 1.0))
    h = jnp.finfo(u.dtype).eps ** (1 / 3) * jnp.maximum(jnp.abs(u[:k]), scale)
    shifts = jnp.concatenate([jnp.diag(h), -jnp.diag(h)])  # (2k, k): q and alpha moved

    def linearised(head):  # (F([q, 0]), J) at (q, alpha) = head
        F = model_at(spec, head[-1], p).field(t, config)
        x0 = jnp.concatenate([head[:-1], jnp.zeros_like(head[:-1])])
        J, f0 = jax.jacfwd(lambda x: (F(x),) * 2, has_aux=True)(x0)
        return f0, J

    def of_tail(w, f0, J):
        _, _, omega, v, chain = layout.unpack(jnp.concatenate([u[:k], w]))
        r = equations(layout, f0, _vectors(v, chain) @ J.T, omega, v, chain, C)
        return r, r

    shared = layout.m <= SHARED_UP_TO
    if shared:  # at u and at the 2k shifted points
        heads = u[None, :k] + jnp.concatenate([jnp.zeros((1, k), u.dtype), shifts])
        f0s, Js = jax.vmap(linearised)(heads)
        f0, J = f0s[0], Js[0]
    else:
        f0, J = linearised(u[:k])
    linear, r = jax.jacfwd(of_tail, has_aux=True)(u[k:], f0, J)
    if shared:
        sides = jax.vmap(lambda f, M: of_tail(u[k:], f, M)[0])(f0s[1:], Js[1:])
        columns = jnp.where(central, ((sides[:k] - sides[k:]) / (2 * h[:, None])).T, 0.0)
    else:

        def differences():
            fn = lambda d: residual(spec, layout, u.at[:k].add(d), config, C, p, t)  # noqa: E731
            sides = jax.vmap(fn)(shifts)
            return ((sides[:k] - sides[k:]) / (2 * h[:, None])).T

        zeros = lambda: jnp.zeros((r.shape[0], k), u.dtype)  # noqa: E731
        columns = jax.lax.cond(central, differences, zeros)
    return r, jnp.concatenate([columns, linear], axis=1), J


def oriented(layout: Layout, u):
    r"""$(|\omega|, q)$: $q$ the unit eigenvector of $+i|\omega|$ (conjugated where Newton
    found $-\omega$)."""
    _, _, omega, v, _ = layout.unpack(u)
    q = v / jnp.linalg.norm(v).astype(v.dtype)
    return jnp.abs(omega), jnp.where(omega < 0, jnp.conj(q), q)


def adjoint_vector(J, omega, q):
    r"""$p$ with $J^Tp = -i\omega p$ and $\bar p^Tq = 1$: the bordered system
    $\begin{pmatrix}J^T + i\omega E & q\\ q^H & 0\end{pmatrix}\begin{pmatrix}p\\ s\end{pmatrix}
    = \begin{pmatrix}0\\ 1\end{pmatrix}$, regular at a simple pair ($s = 0$)."""
    n = J.shape[0]
    A = jax.lax.complex(J.T, omega * jnp.eye(n, dtype=J.dtype))
    top = jnp.concatenate([A, q[:, None]], axis=1)
    bottom = jnp.concatenate([jnp.conj(q), jnp.zeros(1, q.dtype)])[None, :]
    rhs = jnp.zeros(n + 1, q.dtype).at[n].set(1.0)
    return jnp.linalg.solve(jnp.concatenate([top, bottom]), rhs)[:n]
