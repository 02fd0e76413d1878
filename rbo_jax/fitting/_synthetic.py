r""":func:`synthetic_sensor_data`: what a motion-capture system and an IMU would record of a
model's motion, for planning an experiment and for checking a fit's uncertainty (a
simulation-based calibration: fit many such data sets from known parameters and count how often
the intervals cover them).

**The sensor model** (the one :func:`rbo_jax.fit` assumes, so a calibration tests the inference,
not a mismatch):

- motion capture: the attitude $Q(\theta(t_i))$ turned by a small body-side error,
  $Q_{obs} = Q(\theta)\cdot Q(\eta_i)$, $\eta_i \sim N(0, \sigma_\theta^2 E)$, given as unit
  quaternions (w, x, y, z) of a random sign; times on a regular grid at ``quaternion_rate``
  with a uniform jitter of ±``jitter``/2 periods (the first at t = 0); a fraction ``dropped``
  of the samples missing (NaN);
- gyroscope: the body-frame angular velocity plus a constant ``bias`` and white noise
  $N(0, \sigma_\Omega^2)$ per component, on its own regular clock at ``gyro_rate`` (starting
  half a period after t = 0), NaN inside each interval of ``gaps``.

The two channels are put on one time axis by :meth:`TrajectoryData.merge`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..kinematics import quaternion_of, quaternion_product
from ..simulate import simulate
from ._data import TrajectoryData

__all__ = ["synthetic_sensor_data"]


def _check(duration, quaternion_rate, gyro_rate, sigma_theta, sigma_Omega, jitter, dropped):
    def positive(name, value, allow_none=False):
        if value is None and allow_none:
            return
        if not (np.isscalar(value) and np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}.")

    positive("duration", duration)
    positive("quaternion_rate", quaternion_rate, allow_none=True)
    positive("gyro_rate", gyro_rate, allow_none=True)
    positive("sigma_theta", sigma_theta)
    positive("sigma_Omega", sigma_Omega)
    if quaternion_rate is None and gyro_rate is None:
        raise ValueError("quaternion_rate and gyro_rate are both None: no sensor records.")
    if not 0 <= jitter < 1:
        raise ValueError(f"jitter must be in [0, 1) periods, got {jitter!r}.")
    if not 0 <= dropped < 1:
        raise ValueError(f"dropped must be a fraction in [0, 1), got {dropped!r}.")


def _clock(rate, duration, offset, jitter, rng):
    t = np.arange(offset, duration, 1.0 / rate)
    if jitter:
        t = t + rng.uniform(-0.5 * jitter, 0.5 * jitter, t.size) / rate
        t[0] = offset
    return t


def synthetic_sensor_data(
    model,
    theta0,
    Omega0,
    duration: float,
    *,
    quaternion_rate: float | None = 100.0,
    gyro_rate: float | None = 200.0,
    sigma_theta: float = 0.01,
    sigma_Omega: float = 0.02,
    bias=(0.0, 0.0, 0.0),
    jitter: float = 0.2,
    dropped: float = 0.0,
    gaps=(),
    Omega_bias="fit",
    seed: int = 0,
    rtol: float = 1e-12,
    atol: float = 1e-12,
) -> TrajectoryData:
    r"""Synthetic motion-capture quaternions and gyroscope readings of ``model`` started at
    ``(theta0, Omega0)`` over ``[0, duration]`` (see the module docstring for the sensor model).

    **Arguments:**

    - `model`: the true model (any :class:`rbo_jax.RigidBodyOscillator`); `theta0`, `Omega0`:
      its initial turn-vector and body-frame angular velocity; `duration` (s).
    - `quaternion_rate`, `gyro_rate` (Hz): the two clocks; None leaves that sensor out.
    - `sigma_theta` (rad), `sigma_Omega` (rad/s): the noise levels, also given to the data.
    - `bias` (3,): the gyroscope's true constant bias (rad/s, body frame).
    - `jitter` (periods, in [0, 1)): the motion capture's timing jitter; `dropped`: the fraction
      of its samples lost; `gaps`: ``((t0, t1), ...)`` intervals without gyroscope samples.
    - `Omega_bias`: what the data asks of the fit (``"fit"``, the default where the gyroscope
      records; a known (3,) bias; None).
    - `seed`: of NumPy's generator (noise, signs, jitter, dropped samples).
    - `rtol`, `atol`: of the simulation.

    **Returns** a :class:`TrajectoryData` (the channels merged onto one time axis, NaN where a
    channel has no sample; ``t0`` = 0, where the motion starts) whose ``theta0`` and ``Omega0``
    are not given: a fit finds them
    (``fit_initial_state=True``).
    """
    _check(duration, quaternion_rate, gyro_rate, sigma_theta, sigma_Omega, jitter, dropped)
    bias = np.asarray(bias, dtype=float)
    if bias.shape != (3,) or not np.all(np.isfinite(bias)):
        raise ValueError(f"bias must be a finite (3,) vector, got {bias!r}.")
    rng = np.random.default_rng(seed)
    clocks = {}
    if quaternion_rate is not None:
        clocks["quaternion"] = _clock(quaternion_rate, duration, 0.0, jitter, rng)
    if gyro_rate is not None:
        clocks["Omega"] = _clock(gyro_rate, duration, 0.5 / gyro_rate, 0.0, rng)
    t = np.unique(np.concatenate(list(clocks.values())))
    true = simulate(
        model,
        jnp.asarray(theta0),
        jnp.asarray(Omega0),
        jnp.asarray(t),
        t0=0.0,
        rtol=rtol,
        atol=atol,
    )
    channels = {}
    if "quaternion" in clocks:
        tq = clocks["quaternion"]
        theta = np.asarray(true.theta)[np.searchsorted(t, tq)]
        eta = rng.normal(0.0, sigma_theta, (tq.size, 3))
        w, v = jax.vmap(lambda a, b: quaternion_product(quaternion_of(a), quaternion_of(b)))(
            jnp.asarray(theta), jnp.asarray(eta)
        )
        q = np.concatenate([np.asarray(w)[:, None], np.asarray(v)], axis=1)
        q = q * rng.choice([-1.0, 1.0], size=(tq.size, 1))
        q[1:][rng.uniform(size=tq.size - 1) < dropped] = np.nan  # the first sample is kept
        channels["quaternion"] = (tq, q)
    if "Omega" in clocks:
        tg = clocks["Omega"]
        g = np.asarray(true.Omega)[np.searchsorted(t, tg)] + bias
        g = g + rng.normal(0.0, sigma_Omega, g.shape)
        for t0, t1 in gaps:
            g[(tg > t0) & (tg < t1)] = np.nan
        channels["Omega"] = (tg, g)
    else:
        Omega_bias = None
    return TrajectoryData.merge(
        **channels, sigma_theta=sigma_theta, sigma_Omega=sigma_Omega, Omega_bias=Omega_bias, t0=0.0
    )
