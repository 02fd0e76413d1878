r"""Gradient-based fitting of model parameters (foundation stiffness, damping, inertia, initial
state) to observed trajectories, with Gauss–Newton standard errors.

The residuals of one observed trajectory, whitened by the noise level $\sigma$, are

- attitude (full turn-vector θ or turn-tensor Q observed): the rotation distance
  $r = \mathrm{turn\_vector}(Q_{obs}^T\cdot Q(\theta_{model}))/\sigma_\theta$, a proper metric on
  rotations (its norm is the angle between the two attitudes), so data that wraps through
  $|\theta| = \pi$ (principal turn-vectors) is fitted correctly;
- attitude with only some components of θ observed (``theta_weight`` with zeros): the
  component differences $w\,(\theta_{model} - \theta_{obs})/\sigma_\theta$;
- angular velocities ω (left, world frame) or Ω (right, body frame): $w\,(\cdot_{model} -
  \cdot_{obs})/\sigma$.

The loss is $\frac12\sum r^2$. Parameters are chosen with an equinox-style selector
``params=lambda m: (m.foundation.c, m.foundation.d)`` and are optimised in an unconstrained
reparametrisation (log for positive parameters by default; softplus or identity on request), never
by clipping. The least-squares solvers (Levenberg–Marquardt, default; damped Gauss–Newton) use
forward-mode Jacobians through the ODE solve — by default :func:`rbo_jax.fast_simulate`'s, every
fitted scalar a tangent direction of one loop (``integrator="simulate"``: diffrax's
``ForwardMode``); memory independent of the number of steps either way — and iterate on the host
around one compiled program (:func:`rbo_jax.solvers.run_least_squares`, which the lattice's and
rod's fits share). That program holds no host callback, so the command line's persistent
compilation cache keeps it. The first-order optimisers (Adam, L-BFGS) come from optax with
reverse-mode gradients through :func:`rbo_jax.simulate`
(``diffrax.RecursiveCheckpointAdjoint``: memory logarithmic in the number of steps).

Standard errors use the Gauss–Newton approximation of the Hessian at the optimum,
$\mathrm{Cov} = s^2 (J^TJ)^{-1}$ with $J$ the Jacobian of the whitened residuals with respect to
the natural parameters; $s^2 = 1$ when the noise levels are given (``sigma_*``), otherwise the
residual variance $\sum r^2/(n - p)$.

**When to use staged horizons.** For long records, or motions that look chaotic (large
amplitudes, follower loads), a fit started far from the truth can lock onto a wrong local minimum:
the simulated and observed attitudes drift apart by more than a period and the loss landscape
becomes rugged. ``horizons=(0.25, 0.5, 1.0)`` fits the first quarter of each record, then half,
then all, each stage starting from the previous estimate (one compilation per stage).

Modules: ``_data`` (:class:`TrajectoryData`), ``_synthetic`` (:func:`synthetic_sensor_data`),
``_residuals`` (residuals, reparametrisation, the compiled programs), ``_optax`` (Adam,
L-BFGS), ``_fit`` (:func:`fit`, :class:`FitResult`), ``_profile`` (:func:`profile_likelihood`),
``_posterior`` (:func:`posterior`) and ``_sampler`` (its NUTS chains); ``constants``, the fits of
a model function's named constants that the lattices' and rods' fits build on
(:mod:`rbo_jax.fitting.constants`); the least-squares solvers and the covariance live in
:mod:`rbo_jax.solvers`.
"""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._data": ("TrajectoryData",),
        "._fit": ("FitResult", "fit"),
        "._posterior": ("posterior",),
        "._profile": ("profile_likelihood",),
        "._residuals": ("residuals",),
        "._synthetic": ("synthetic_sensor_data",),
    },
)
