r"""Actuation of a rod and a ground to move on: muscle torques (a travelling wave of internal
moments), a rest curvature that changes with time, and a plane with contact and anisotropic
friction (:mod:`._loads`'s interface: forces and moments at the bodies' motion and time).

**Muscle torques** (:class:`MuscleTorques`, PyElastica's ``MuscleTorques``; Gazzola, Dudte,
McCormick & Mahadevan 2018, R. Soc. open sci. 5, 171628, eq. 4.6). An active bending moment
travels along the rod,

$$\tau(s, t) = \min(1, t/t_r)\;\beta(s)\,\sin(\omega t - k s + \phi), \qquad
  \omega = 2\pi/T,$$

about a fixed world ``direction`` $d$ (the plane's normal for a snake on the ground). $s$ is
the fraction of the rest length counted as PyElastica counts it for its snake, **from the tip**
($s = 1 - \xi$, $\xi$ the fraction from the base). Each coupling $c$ (at $\xi_c$, the middle of
the segment) carries the couple $+\tau(s_c, t)\,d$ on its outer body and $-\tau(s_c, t)\,d$ on
its inner one (PyElastica puts the same couples at its inner nodes). The envelope $\beta$ is a
constant, or a clamped cubic B-spline of the given coefficients with equally spaced knots on
$[0, 1]$ (PyElastica's ``_bspline``: ``amplitude=b_coeff`` is its ``with_spline=True``;
its ``with_spline=False`` is ``amplitude=1``). Every parameter may be traced (``jax.grad``
with respect to the coefficients, the period, the wave number).

**Rest curvature** (:class:`RestCurvature`): the couplings' rest relative turn becomes
$h_c\,\kappa^0(t, \xi_c)$, so that the bending energy is
$\tfrac12(\varphi_c - h_c\kappa^0)\cdot K^\varphi_c(\varphi_c - h_c\kappa^0)$ (the curvature
$\kappa^0$ in the coupling's mid-frame, 1/length; $\xi$ from the base). A snake or a swimmer
driven by its preferred shape; statics at $t = 0$ see the rest shape.

**A frictional plane** (:class:`FrictionalPlane`, PyElastica's ``AnisotropicFrictionalPlane``
smoothed so that every derivative exists). With $g_i = n\cdot(r_i - o) - a$ the height of body
$i$ above the plane (less the contact radius $a$) and $\ell_i$ its share of the length:

- the normal force is $\ell_i\,[k\,\delta\,\mathrm{softplus}(-g_i/\delta) - c\,(n\cdot v_i)\,
  \sigma(-g_i/\delta)]\,n$: a spring of stiffness $k$ per unit length into the plane, a
  damper $c$, their onset smoothed over the length $\delta$ (``smoothing``; $\delta \to 0$:
  $k\max(-g, 0)$);
- friction acts in the plane with the elastic part $N_i = \ell_i k\delta\,\mathrm{softplus}
  (-g_i/\delta)$, along the body's axis $a_i$ (its third axis projected on the plane) and across
  it, $l_i = a_i\times n$:

  $$F_i = -N_i\,\frac{\mu_a(u_a)\,u_a\,a_i + \mu_l\,u_l\,l_i}{\sqrt{u_a^2 + u_l^2 + \varepsilon^2}},
    \qquad \mu_a(u) = \mu_b + (\mu_f - \mu_b)\,\tfrac12\,(1 + \tanh(u/\varepsilon)),$$

  $u_a = v_i\cdot a_i$, $u_l = v_i\cdot l_i$: Coulomb's kinetic friction (forward $\mu_f$,
  backward $\mu_b$, lateral $\mu_l$) whose direction and forward/backward switch are smoothed
  over the slip velocity $\varepsilon$ (``slip_velocity``). Below $\varepsilon$ it acts as a
  viscous drag of coefficient $N\mu/\varepsilon$: a body held by friction creeps at speeds of
  order $\varepsilon$; PyElastica's kinetic friction switches within $10^{-8}$ m/s of rest
  (its ``slip_velocity_tol``) and adds a static friction (zero in its snake). Rolling friction
  (a moment from the contact point's lever arm) is left out: the body's spin about its axis
  does not enter.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._validation import is_traced
from ._loads import AbstractRodLoad, real_array

__all__ = [
    "FrictionalPlane",
    "MuscleTorques",
    "RestCurvature",
    "bspline_basis",
    "coupling_fractions",
]


def bspline_basis(s, n_coeff: int):
    r"""The clamped cubic B-spline basis of ``n_coeff`` (≥ 4) coefficients with equally spaced
    knots on $[0, 1]$ (PyElastica's ``_bspline``), at the points ``s`` in $[0, 1)$:
    ``(len(s), n_coeff)``, by the Cox–de Boor recursion (knots concrete, ``s`` may be traced)."""
    degree = 3
    inner = np.linspace(0.0, 1.0, n_coeff - 2)
    knots = np.concatenate([np.zeros(degree), inner, np.ones(degree)])
    s = jnp.asarray(s)[:, None]
    lo, hi = knots[:-1][None], knots[1:][None]
    B = ((s >= lo) & (s < hi)).astype(s.dtype)  # degree 0: (len(s), len(knots) - 1)
    for p in range(1, degree + 1):
        m = len(knots) - 1 - p
        left_den = knots[p : p + m] - knots[:m]
        right_den = knots[p + 1 : p + 1 + m] - knots[1 : 1 + m]
        left = np.where(left_den > 0, 1.0 / np.where(left_den > 0, left_den, 1.0), 0.0)
        right = np.where(right_den > 0, 1.0 / np.where(right_den > 0, right_den, 1.0), 0.0)
        B = (s - knots[:m][None]) * left[None] * B[:, :m] + (
            knots[p + 1 : p + 1 + m][None] - s
        ) * right[None] * B[:, 1 : 1 + m]
    return B


def coupling_fractions(rod):
    r"""$\xi_c$ ``(N,)``: the middle of every coupling as a fraction of the rest length from the
    base, from the rest gaps' lengths."""
    h = jnp.sqrt(jnp.sum(jnp.asarray(rod.rest_gap) ** 2, axis=-1))
    return (jnp.cumsum(h) - 0.5 * h) / jnp.sum(h)


def _needs_length(rod, owner: str) -> None:
    gaps = rod.rest_gap
    if not is_traced(gaps) and np.any(np.linalg.norm(np.asarray(gaps), axis=-1) <= 0):
        raise ValueError(
            f"{owner}: every coupling needs a rest length (a rod from lattice.rod or "
            "circular_rod); a chain of links with zero rest gaps (lattice.pendulum) has none."
        )


def _scalar(x, name: str, owner: str, *, positive: bool = False, nonnegative: bool = False):
    x = real_array(x, name, owner)
    if np.shape(x) != ():
        raise ValueError(f"{owner}: {name} must be a scalar, got shape {np.shape(x)}.")
    if not is_traced(x):
        v = float(x)
        if not np.isfinite(v) or (positive and v <= 0) or (nonnegative and v < 0):
            need = "> 0" if positive else ">= 0" if nonnegative else "finite"
            raise ValueError(f"{owner}: {name} must be finite and {need}, got {v}.")
    return x


def _vector(x, name: str, owner: str, *, unit: bool = False):
    x = real_array(x, name, owner)
    if tuple(np.shape(x)) != (3,):
        raise ValueError(f"{owner}: {name} must be a 3-vector, got shape {np.shape(x)}.")
    if not is_traced(x):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{owner}: {name} must be finite, got {np.asarray(x).tolist()}.")
        if unit:
            size = float(np.linalg.norm(x))
            if size == 0:
                raise ValueError(f"{owner}: {name} must not be zero.")
            x = x / size
    elif unit:
        x = x / jnp.linalg.norm(x)
    return x


def _to_bodies(rod, at, world_couples):
    """Body-frame moments ``(N+1, 3)`` of couples ``(N, 3)`` (world) at the couplings: plus on
    each coupling's outer body, minus on its inner one."""
    z = jnp.zeros((1, 3), world_couples.dtype)
    world = jnp.concatenate([z, world_couples]) - jnp.concatenate([world_couples, z])
    return jnp.einsum("bji,bj->bi", at.Q, world)


class MuscleTorques(AbstractRodLoad):
    r"""A travelling wave of active bending moments (module docstring; PyElastica's
    ``MuscleTorques``): ``amplitude`` a scalar or ≥ 4 B-spline coefficients (its ``b_coeff``),
    ``period`` $T$, ``wave_number`` $k$ ($2\pi$ over the wave length as a fraction of the
    rest length), ``phase_shift`` $\phi$, ``direction`` (world, unit), ``ramp_up_time``
    $t_r > 0$. Zero in the statics ($t = 0$)."""

    amplitude: Float[Array, "..."]
    period: Float[Array, ""]
    wave_number: Float[Array, ""]
    phase_shift: Float[Array, ""]
    direction: Float[Array, "3"]
    ramp_up_time: Float[Array, ""]

    def __init__(
        self,
        amplitude,
        period,
        wave_number,
        *,
        phase_shift=0.0,
        direction=(0.0, 1.0, 0.0),
        ramp_up_time=None,
    ):
        owner = "MuscleTorques"
        a = real_array(amplitude, "amplitude", owner)
        if np.ndim(a) > 1 or (np.ndim(a) == 1 and np.shape(a)[0] < 4):
            raise ValueError(
                f"{owner}: amplitude must be a scalar or >= 4 B-spline coefficients, got "
                f"shape {np.shape(a)}."
            )
        if not is_traced(a) and not np.all(np.isfinite(a)):
            raise ValueError(f"{owner}: amplitude must be finite.")
        self.amplitude = a
        self.period = _scalar(period, "period", owner, positive=True)
        self.wave_number = _scalar(wave_number, "wave_number", owner)
        self.phase_shift = _scalar(phase_shift, "phase_shift", owner)
        self.direction = _vector(direction, "direction", owner, unit=True)
        ramp = self.period if ramp_up_time is None else ramp_up_time
        self.ramp_up_time = _scalar(ramp, "ramp_up_time", owner, positive=True)

    def check(self, rod) -> None:
        _needs_length(rod, "MuscleTorques")

    def envelope(self, s):
        r"""$\beta(s)$ at the fractions ``s`` (from the tip)."""
        a = jnp.asarray(self.amplitude)
        if a.ndim == 0:
            return a * jnp.ones_like(s)
        return bspline_basis(s, a.shape[0]) @ a

    def torques(self, rod, t):
        r"""$\tau(s_c, t)$ ``(N,)`` at the couplings (module docstring)."""
        s = 1.0 - coupling_fractions(rod)
        ramp = jnp.clip(t / self.ramp_up_time, 0.0, 1.0)
        omega = 2.0 * np.pi / self.period
        return (
            ramp * self.envelope(s) * jnp.sin(omega * t - self.wave_number * s + self.phase_shift)
        )

    def forces(self, rod, rotate, scale, at):
        tau = scale * self.torques(rod, at.t)
        M = _to_bodies(rod, at, tau[:, None] * jnp.asarray(self.direction)[None])
        return jnp.zeros_like(M), M


class RestCurvature(AbstractRodLoad):
    r"""A rest curvature $\kappa^0(t, \xi)$ (1/length, in each coupling's mid-frame;
    $\xi \in (0, 1)$ the fraction of the rest length from the base): ``curvature`` an array
    ``(3,)`` or ``(N, 3)`` (constant), or a function ``curvature(t, xi, params) -> (N, 3)``
    of the time, the couplings' fractions ``(N,)`` and ``params`` (any pytree: traced,
    differentiated). Its couplings' rest relative turns are $h_c\,\kappa^0$ (module
    docstring)."""

    curvature: Any
    params: Any
    function: Callable | None = eqx.field(static=True)

    def __init__(self, curvature, params=None):
        owner = "RestCurvature"
        if callable(curvature):
            self.function, self.curvature, self.params = curvature, None, params
            return
        k = real_array(curvature, "curvature", owner)
        if np.shape(k)[-1:] != (3,) or np.ndim(k) > 2:
            raise ValueError(
                f"{owner}: curvature must be a function, a 3-vector or one per coupling "
                f"(N, 3), got shape {np.shape(k)}."
            )
        if not is_traced(k) and not np.all(np.isfinite(k)):
            raise ValueError(f"{owner}: curvature must be finite.")
        self.function, self.curvature, self.params = None, k, params

    def check(self, rod) -> None:
        _needs_length(rod, "RestCurvature")
        if self.function is None and np.ndim(self.curvature) == 2:
            if np.shape(self.curvature)[0] != rod.n:
                raise ValueError(
                    f"RestCurvature: curvature has {np.shape(self.curvature)[0]} rows, the rod "
                    f"{rod.n} couplings."
                )
        if self.function is not None:
            out = jax.eval_shape(
                self.function,
                jax.ShapeDtypeStruct((), jnp.result_type(float)),
                jax.ShapeDtypeStruct((rod.n,), jnp.result_type(float)),
                self.params,
            )
            if tuple(out.shape) != (rod.n, 3):
                raise ValueError(
                    f"RestCurvature: curvature(t, xi, params) must return ({rod.n}, 3), got "
                    f"{tuple(out.shape)}."
                )

    def rest_turns(self, rod, t):
        h = jnp.sqrt(jnp.sum(jnp.asarray(rod.rest_gap) ** 2, axis=-1))
        if self.function is None:
            kappa = jnp.broadcast_to(jnp.asarray(self.curvature), (rod.n, 3))
        else:
            kappa = self.function(t, coupling_fractions(rod), self.params)
        return h[:, None] * kappa

    def forces(self, rod, rotate, scale, at):
        z = jnp.zeros((rod.n_bodies, 3), at.r.dtype)
        return z, z


class FrictionalPlane(AbstractRodLoad):
    r"""A plane through ``origin`` with unit ``normal`` that the bodies rest on (module
    docstring): contact ``stiffness`` $k$ and ``damping`` $c$ per unit length, kinetic friction
    ``mu = (forward, backward, lateral)`` (forward along each body's third axis), the contact
    ``radius`` $a$ (the rod's), ``slip_velocity`` $\varepsilon$ and ``smoothing`` $\delta$
    of the module docstring."""

    origin: Float[Array, "3"]
    normal: Float[Array, "3"]
    stiffness: Float[Array, ""]
    damping: Float[Array, ""]
    mu: Float[Array, "3"]
    radius: Float[Array, ""]
    slip_velocity: Float[Array, ""]
    smoothing: Float[Array, ""]
    needs_velocity = True

    def __init__(
        self,
        *,
        mu,
        stiffness,
        damping=0.0,
        origin=(0.0, 0.0, 0.0),
        normal=(0.0, 1.0, 0.0),
        radius=0.0,
        slip_velocity=1e-4,
        smoothing=1e-4,
    ):
        owner = "FrictionalPlane"
        self.origin = _vector(origin, "origin", owner)
        self.normal = _vector(normal, "normal", owner, unit=True)
        self.stiffness = _scalar(stiffness, "stiffness", owner, positive=True)
        self.damping = _scalar(damping, "damping", owner, nonnegative=True)
        mu = real_array(mu, "mu", owner)
        if tuple(np.shape(mu)) != (3,):
            raise ValueError(
                f"{owner}: mu must be (forward, backward, lateral), got shape {np.shape(mu)}."
            )
        if not is_traced(mu) and not (np.all(np.isfinite(mu)) and np.all(mu >= 0)):
            raise ValueError(f"{owner}: mu must be finite and >= 0, got {mu.tolist()}.")
        self.mu = mu
        self.radius = _scalar(radius, "radius", owner, nonnegative=True)
        self.slip_velocity = _scalar(slip_velocity, "slip_velocity", owner, positive=True)
        self.smoothing = _scalar(smoothing, "smoothing", owner, positive=True)

    def forces(self, rod, rotate, scale, at):
        n = jnp.asarray(self.normal)
        delta = self.smoothing
        gap = (at.r - jnp.asarray(self.origin)[None]) @ n - self.radius
        depth = delta * jax.nn.softplus(-gap / delta)
        share = jnp.asarray(rod.share)
        N = share * self.stiffness * depth  # the elastic part, >= 0
        F = N[:, None] * n[None]
        if at.v is None:  # at rest: no damping, no friction
            return scale * F, jnp.zeros_like(F)
        vn = at.v @ n
        F = F - (share * self.damping * vn * jax.nn.sigmoid(-gap / delta))[:, None] * n[None]
        axis = at.Q[:, :, 2]
        a = axis - (axis @ n)[:, None] * n[None]
        a = a / jnp.sqrt(jnp.sum(a * a, axis=-1, keepdims=True) + 1e-30)
        lat = jnp.cross(a, n[None])
        ua = jnp.sum(at.v * a, axis=-1)
        ul = jnp.sum(at.v * lat, axis=-1)
        eps = self.slip_velocity
        speed = jnp.sqrt(ua * ua + ul * ul + eps * eps)
        mu_f, mu_b, mu_l = (jnp.asarray(self.mu)[i] for i in range(3))
        mu_a = mu_b + (mu_f - mu_b) * 0.5 * (1.0 + jnp.tanh(ua / eps))
        drag = (mu_a * ua)[:, None] * a + (mu_l * ul)[:, None] * lat
        F = F - (N / speed)[:, None] * drag
        return scale * F, jnp.zeros_like(F)
