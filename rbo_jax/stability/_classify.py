r"""Stability from a spectrum: Lyapunov's first method, with one test for every model.

An equilibrium is unstable when an eigenvalue $p$ of its linearisation has $\mathrm{Re}\,p > 0$,
asymptotically stable when every $\mathrm{Re}\,p < 0$. In floating point "zero" needs a
tolerance, and one that does not depend on the units: each eigenvalue is measured against its
own modulus,

$$\mathrm{Re}\,p_i > \mathrm{rtol}\,|p_i| + \min(c\,\epsilon, \mathrm{rtol})\max_j|p_j| ,$$

with a floor of $c = 1000$ machine epsilons of the largest modulus for the roots near zero (a
free body's rigid modes, a double root at a divergence point), whose rounding is that of the
whole eigenproblem; an ``rtol`` below $c\,\epsilon$ lowers the floor to itself (the caller
vouches for the rounding: a slow flutter onset under stiff modes $10^6$ times faster, the
hinge-damped Ziegler pendulum of translating bodies, is found to $10^{-5}$ with
``rtol = 1e-14``).

A spectrum without velocity-dependent forces (``reversible``: no friction, no Kelvin–Voigt
damping; :meth:`rbo_jax.mechanics.AbstractMechanics.depends_on_velocity`) is symmetric under
$p \to -p$: its roots leave the imaginary axis only by colliding (a Krein collision, or at zero:
divergence), where $\mathrm{Re}\,p$ grows like the square root of the distance to the
collision, and the rounding of the nearly defective pair grows like its inverse. No fixed
multiple of $\epsilon$ holds it: Pflüger's column, whose shear modes are $10^6$ times faster
than its flutter pair, shows $\mathrm{Re}\,p$ of the stable pair up to $4000\,\epsilon\max|p|$
at $2\cdot10^{-6}$ below the collision and $10^4\,\epsilon\max|p|$ at $2\cdot10^{-7}$. There
the floor is $\mathrm{rtol}\max_j|p_j|$: an instability is found past the collision by the
square of the floor over the growth (Pflüger's column, $n = 8$: $1.0$–$1.3\cdot10^{-6}$ of
the load past the collision), never before it.

Scaling time or masses multiplies every $p$ by one factor and leaves the
test unchanged. A test scaled by the largest $|p|$ alone would lose a slow mode under the
rounding threshold of a stiff one: the flutter mode of a lightly damped rod whose stiff shear
modes are $10^4$ times faster rises past $10^{-9}\max|p|$ only well past its onset.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _enumeration as enum
from .._custom_types import Scalar
from .._validation import array_namespace

ROUNDING = 1000  # machine epsilons of max |p|: the floor of the test (module docstring)


class StabilityKind(eqx.Enumeration):
    """Classification of an equilibrium from its spectrum (Lyapunov's first method)."""

    asymptotically_stable = "asymptotically stable: every Re p < 0"
    marginally_stable = (
        "marginally stable in the linear approximation: every Re p = 0 within tolerance (the "
        "conservative case; nonlinear terms or a Jordan block decide)"
    )
    divergence = "unstable by divergence: a real root p > 0 (static buckling)"
    flutter = "unstable by flutter: a complex pair with Re p > 0 (growing oscillation)"
    undefined = "undefined: the spectrum is not finite (the equilibrium could not be computed)"


def spectral_abscissa(eigenvalues) -> Scalar:
    """max Re p."""
    return jnp.max(jnp.real(eigenvalues))


def _tolerances(p, rtol, reversible=False, xp=jnp):
    """The tolerance of every root (module docstring), in the namespace ``xp``."""
    dtype = xp.real(p).dtype
    # a tighter rtol than the floor lowers the floor too: the caller vouches for the rounding
    floor = rtol if reversible else xp.minimum(ROUNDING * xp.finfo(dtype).eps, rtol)
    return rtol * xp.abs(p) + floor * xp.max(xp.abs(p))


def unstable_roots(eigenvalues, *, rtol: float = 1e-9, reversible: bool = False):
    r"""Which roots have
    $\mathrm{Re}\,p > \mathrm{rtol}\,|p| + \min(c\epsilon, \mathrm{rtol})\max|p|$ (module
    docstring; the floor $\mathrm{rtol}\max|p|$ for a ``reversible`` spectrum). NumPy for
    concrete eigenvalues (a host loop compiles nothing), JAX for traced ones."""
    xp = array_namespace(eigenvalues, rtol)
    p = xp.asarray(eigenvalues)
    return xp.real(p) > _tolerances(p, rtol, reversible, xp)


def unstable_oscillatory(eigenvalues, *, rtol: float = 1e-9, reversible: bool = False):
    """Which roots are unstable (:func:`unstable_roots`) with an imaginary part beyond the same
    tolerance: the roots of a flutter instability."""
    xp = array_namespace(eigenvalues, rtol)
    p = xp.asarray(eigenvalues)
    tol = _tolerances(p, rtol, reversible, xp)
    return (xp.real(p) > tol) & (xp.abs(xp.imag(p)) > tol)


def classify(eigenvalues, *, rtol: float = 1e-9, reversible: bool = False):
    r"""Classify an equilibrium from its eigenvalues; returns ``(kind, abscissa)``.

    A root is unstable where
    $\mathrm{Re}\,p > \mathrm{rtol}\,|p| + \min(1000\,\epsilon, \mathrm{rtol})\max|p|$ and
    stable where $\mathrm{Re}\,p < -(\dots)$ (module docstring: each root against its own
    modulus, whatever the units). No unstable root and every root stable:
    ``asymptotically_stable``; no unstable root otherwise: ``marginally_stable`` (conservative
    spectra, on the imaginary axis up to rounding). Of the unstable roots, the one with the
    largest real part decides between ``divergence`` (its imaginary part within the same
    tolerance of zero) and ``flutter``. ``undefined`` where a root is not finite. Growth rates
    below ``rtol`` of their frequency are not resolved: the Nikolai roots have
    Re p ≈ |M|/(4√(A1 c)) for small M against |p| ≈ √(c/A1), so at |M| ≲ 1e-9 c the default calls
    the equilibrium marginal; pass a smaller ``rtol`` (e.g. 1e-12) to resolve them. A
    ``reversible`` spectrum (no velocity-dependent force, module docstring) takes the floor
    $\mathrm{rtol}\max|p|$: the rounding of a pair about to collide is not bounded by a multiple
    of $\epsilon$. One compiled program (concrete eigenvalues: no dispatch per operation)."""
    return _classified(eigenvalues, rtol, reversible)


@functools.partial(jax.jit, static_argnums=2)
def _classified(eigenvalues, rtol, reversible: bool):
    """:func:`classify`'s body."""
    p = jnp.asarray(eigenvalues)
    tol = _tolerances(p, rtol, reversible)
    re = jnp.real(p)
    unstable = re > tol
    a = jnp.max(re)
    i_max = jnp.argmax(jnp.where(unstable, re, -jnp.inf))
    K = StabilityKind
    kind = K.where(jnp.all(re < -tol), K.asymptotically_stable, K.marginally_stable)
    oscillating = jnp.abs(jnp.imag(p[i_max])) > tol[i_max]
    kind = K.where(jnp.any(unstable), K.where(oscillating, K.flutter, K.divergence), kind)
    kind = K.where(jnp.all(jnp.isfinite(p)), kind, K.undefined)
    return kind, a


def is_unstable(kind):
    """Whether a classification is divergence or flutter (a traced boolean)."""
    code = enum.code(kind)
    return (code == enum.code(StabilityKind.flutter)) | (
        code == enum.code(StabilityKind.divergence)
    )
