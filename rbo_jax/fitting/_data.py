"""Observed trajectories: :class:`TrajectoryData`, checked on the host before anything is
compiled."""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

from ..kinematics import turn_tensor, turn_vector

__all__ = ["TrajectoryData"]

_OBSERVED = (("theta", (3,)), ("Q", (3, 3)), ("omega", (3,)), ("Omega", (3,)))
_WEIGHTS = (("theta_weight", "theta"), ("omega_weight", "omega"), ("Omega_weight", "Omega"))
_SIGMAS = ("sigma_theta", "sigma_omega", "sigma_Omega")
_CHANNELS = ("quaternion", "theta", "Q", "omega", "Omega")


def _host_array(x, name, shape_tail, n=None):
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of numbers.") from None
    if a.ndim != 1 + len(shape_tail) or tuple(a.shape[1:]) != tuple(shape_tail):
        raise ValueError(
            f"{name} must have shape (n, {', '.join(map(str, shape_tail))}), got {a.shape}."
        )
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} has {a.shape[0]} samples but ts has {n}.")
    return a


def _times(ts) -> np.ndarray:
    try:
        ts = np.asarray(ts, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("ts must be a 1-D array of numbers (the sample times).") from None
    if ts.ndim != 1:
        raise ValueError(f"ts must be a 1-D array of times, got shape {ts.shape}.")
    if ts.size == 0:
        raise ValueError("ts is empty: a trajectory needs at least one sample.")
    bad = np.flatnonzero(~np.isfinite(ts))
    if bad.size:
        raise ValueError(f"ts contains NaN or inf (first at sample {bad[0]}).")
    back = np.flatnonzero(np.diff(ts) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(
            f"ts must be strictly increasing (sort the samples): sample {i} "
            f"(t = {ts[i]:g}) does not come after sample {i - 1} "
            f"(t = {ts[i - 1]:g})."
        )
    return ts


def _quaternions(q, ts) -> np.ndarray:
    """Unit quaternions (n, 4), scalar first (w, x, y, z), either sign, to turn-tensors
    (n, 3, 3); a sample with a NaN stays missing (NaN)."""
    q = _host_array(q, "quaternion", (4,), ts.size)
    present = np.all(_present("quaternion", q, ts), axis=1)
    norm = np.linalg.norm(np.where(present[:, None], q, 1.0), axis=1)
    bad = np.flatnonzero(present & (norm < 1e-6))
    if bad.size:
        raise ValueError(
            f"quaternion has zero norm at sample {bad[0]}: a rotation needs a nonzero "
            "quaternion (mark a missing sample with NaN)."
        )
    w, x, y, z = (q / norm[:, None]).T
    Q = np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)
    return np.where(present[:, None, None], Q, np.nan)


def _present(name, x, ts):
    """Which entries of a channel are observed (finite); NaN is missing, inf is an error, and a
    channel must have at least one observed sample."""
    inf = np.isinf(x)
    if np.any(inf):
        i = int(np.argwhere(inf)[0][0])
        raise ValueError(
            f"{name} contains inf (first at sample {i}, t = {ts[i]}); mark a missing value "
            "with NaN."
        )
    ok = np.isfinite(x)
    if not np.any(ok):
        raise ValueError(f"{name} is all NaN: the channel has no observed sample.")
    return ok


def _observations(ts, given: dict, weights_given: dict):
    """The observed arrays, weights and the attitude's per-sample weight (None: all observed),
    checked. NaN marks a missing value: a vector channel's missing components get weight 0, an
    attitude sample (θ or Q, compared as rotations) with a NaN is missing whole; missing values
    are then zeroed (θ) or set to the identity (Q) so that no NaN enters a program."""
    n = ts.size
    if given["quaternion"] is not None:
        if given["theta"] is not None or given["Q"] is not None:
            raise ValueError("give the attitude once: as quaternion, theta or Q.")
        given = {**given, "Q": _quaternions(given["quaternion"], ts)}
    given.pop("quaternion")
    if given["theta"] is not None and given["Q"] is not None:
        raise ValueError("give the attitude either as theta or as Q, not both.")
    if all(x is None for x in given.values()):
        raise ValueError(
            "nothing observed: give at least one of quaternion, theta, Q, omega, Omega."
        )
    arrays = {
        name: None if given[name] is None else _host_array(given[name], name, tail, n)
        for name, tail in _OBSERVED
    }
    weights = {}
    for name, obs in _WEIGHTS:
        w = weights_given[name]
        if w is not None and arrays[obs] is None:
            raise ValueError(f"{name} given but {obs} is not observed.")
        if w is not None:
            w = _host_array(w, name, (3,), n)
            bad = np.argwhere(~(np.isfinite(w) & (w >= 0)))
            if bad.size:
                raise ValueError(f"{name} must be finite and non-negative (sample {bad[0][0]}).")
        weights[name] = w
    attitude = None
    for name, x in arrays.items():
        if x is None:
            continue
        ok = _present(name, x, ts)
        key = f"{name}_weight"
        if name == "Q" or (name == "theta" and weights["theta_weight"] is None):
            rows = np.all(ok.reshape(n, -1), axis=1)  # compared as rotations: a sample whole
            fill = np.eye(3) if name == "Q" else np.zeros(3)
            arrays[name] = np.where(rows.reshape((n,) + (1,) * (x.ndim - 1)), x, fill)
            attitude = None if rows.all() else rows.astype(np.float64)
            continue
        if not ok.all():
            weights[key] = np.where(ok, 1.0 if weights[key] is None else weights[key], 0.0)
        if weights[key] is not None:
            arrays[name] = np.where(weights[key] > 0, x, 0.0)
    return arrays, weights, attitude


def _bias(Omega_bias, Omega):
    """``(known bias or None, fitted?)`` from ``Omega_bias``: None, ``"fit"`` or a (3,) array."""
    if Omega_bias is None:
        return None, False
    if Omega is None:
        raise ValueError("Omega_bias given but Omega (the gyroscope) is not observed.")
    if isinstance(Omega_bias, str):
        if Omega_bias != "fit":
            raise ValueError(f"Omega_bias must be None, 'fit' or a (3,) array, got {Omega_bias!r}.")
        return None, True
    b = _host_array(np.asarray(Omega_bias)[None], "Omega_bias", (3,))[0]
    if not np.all(np.isfinite(b)):
        raise ValueError("Omega_bias must be finite.")
    return b, False


def _sigma(name, s):
    if s is None:
        return None
    try:
        ok = bool(np.isfinite(s) and s > 0) and np.ndim(s) == 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{name} must be a positive number, got {s!r}.")
    return float(s)


def _first(arrays, weights, attitude, name):
    """``(index, value)`` of the first fully observed sample of a channel, or None."""
    x = arrays[name]
    if x is None:
        return None
    w = weights.get(f"{name}_weight")
    full = np.ones(x.shape[0], bool) if w is None else np.all(w > 0, axis=1)
    if name in ("theta", "Q") and attitude is not None:
        full &= attitude > 0
    i = np.flatnonzero(full)
    return None if i.size == 0 else (int(i[0]), x[i[0]])


def _initial_state(arrays, weights, attitude, theta0, Omega0, bias):
    """``(θ0, Ω0, guessed)``: as given, else from the first fully observed samples (Ω less a known
    bias). ``guessed``: one came from a sample after the first, a starting guess only."""
    guessed = False
    if theta0 is None:
        first = _first(arrays, weights, attitude, "theta")
        if first is None and arrays["Q"] is not None:
            first = _first(arrays, weights, attitude, "Q")
            first = None if first is None else (first[0], np.asarray(turn_vector(first[1])))
        if first is None:
            raise ValueError("theta0 is needed: the attitude is never fully observed.")
        guessed |= first[0] > 0
        theta0 = first[1]
    if Omega0 is None:
        first = _first(arrays, weights, attitude, "Omega")
        if first is not None and bias is not None:
            first = (first[0], first[1] - bias)
        if first is None and arrays["omega"] is not None:
            first = _first(arrays, weights, attitude, "omega")
            if first is not None:
                th0 = np.asarray(theta0, dtype=np.float64)
                first = (first[0], np.asarray(turn_tensor(th0)).T @ first[1])
        if first is None:
            raise ValueError("Omega0 is needed: the angular velocity is never fully observed.")
        guessed |= first[0] > 0
        Omega0 = first[1]
    theta0 = _host_array(np.asarray(theta0)[None], "theta0", (3,))[0]
    Omega0 = _host_array(np.asarray(Omega0)[None], "Omega0", (3,))[0]
    if not (np.all(np.isfinite(theta0)) and np.all(np.isfinite(Omega0))):
        raise ValueError("theta0 and Omega0 must be finite.")
    return theta0, Omega0, guessed


class TrajectoryData(eqx.Module):
    r"""One observed trajectory: sample times ``ts`` and any of the attitude, as ``quaternion``
    (n, 4), ``theta`` (n, 3) or ``Q`` (n, 3, 3), and ``omega`` (n, 3) (left angular velocity,
    world frame) or ``Omega`` (n, 3) (right angular velocity, body frame: a gyroscope).

    - ``quaternion``: unit quaternions scalar first, $(w, x, y, z)$, of $Q(\theta) = \exp(\theta
      \times E)$, body to world (MuJoCo's ``qpos`` and ``framequat``, SciPy's
      ``as_quat(scalar_first=True)``), either sign: the attitude residual is the rotation vector
      of $Q_{obs}^T Q_{model}$, so $q$ and $-q$ are the same sample.
    - **Missing samples**: NaN in a sample, or in one channel of it, means missing; the rest of
      the sample still counts. An attitude sample (compared as a rotation) with a NaN is missing
      whole; a missing component of ω or Ω drops that component only. ``*_weight`` (n, 3) arrays
      of non-negative weights may also weigh the components (θ given with ``theta_weight`` is
      compared component by component).
    - ``ts``: strictly increasing, irregular spacing allowed; ``t0`` (default ``ts[0]``,
      whichever channel is present there) is where the initial state applies. Channels sampled
      on different clocks: :meth:`merge` puts them on one time axis with NaN where a channel has
      no sample.
    - ``Omega_bias``: the gyroscope reads $\Omega + b$ plus noise with a constant bias $b$ (3,)
      (body frame, rad/s). ``"fit"``: fitted with the parameters, one bias shared by every
      experiment that asks for it (:attr:`rbo_jax.FitResult.Omega_bias`); a (3,) array: a known
      bias; None (default): no bias.
    - ``theta0``, ``Omega0``: the initial state at ``t0``; if not given they are taken from the
      first fully observed samples (Ω less a known bias): the starting guess when the initial
      state is fitted (``fit(..., fit_initial_state=True)``; where a sample after the first had
      to serve, :func:`rbo_jax.fit` warns unless the initial state is fitted).
    - ``sigma_*``: the noise standard deviations, per component (``sigma_theta`` in radians);
      None: unknown, estimated from the residuals.

    All checks (shapes, inf, a channel all NaN, quaternions of zero norm, strictly increasing
    times, positive noise levels, at least one observed quantity) happen here, on the host,
    before anything is compiled; the messages name the argument and the first bad sample.
    """

    ts: jax.Array
    theta0: jax.Array
    Omega0: jax.Array
    t0: jax.Array
    theta: jax.Array | None
    Q: jax.Array | None
    omega: jax.Array | None
    Omega: jax.Array | None
    theta_weight: jax.Array | None
    omega_weight: jax.Array | None
    Omega_weight: jax.Array | None
    attitude_weight: jax.Array | None
    Omega_bias: jax.Array | None
    sigma_theta: float | None = eqx.field(static=True)
    sigma_omega: float | None = eqx.field(static=True)
    sigma_Omega: float | None = eqx.field(static=True)
    fit_Omega_bias: bool = eqx.field(static=True)
    initial_state_guessed: bool = eqx.field(static=True)

    def __init__(
        self,
        ts,
        *,
        quaternion=None,
        theta=None,
        Q=None,
        omega=None,
        Omega=None,
        theta0=None,
        Omega0=None,
        t0=None,
        theta_weight=None,
        omega_weight=None,
        Omega_weight=None,
        sigma_theta=None,
        sigma_omega=None,
        sigma_Omega=None,
        Omega_bias=None,
    ):
        ts = _times(ts)
        arrays, weights, attitude = _observations(
            ts,
            {"quaternion": quaternion, "theta": theta, "Q": Q, "omega": omega, "Omega": Omega},
            {
                "theta_weight": theta_weight,
                "omega_weight": omega_weight,
                "Omega_weight": Omega_weight,
            },
        )
        sigmas = {
            name: _sigma(name, s)
            for name, s in zip(_SIGMAS, (sigma_theta, sigma_omega, sigma_Omega))
        }
        bias, fit_bias = _bias(Omega_bias, arrays["Omega"])
        theta0, Omega0, guessed = _initial_state(arrays, weights, attitude, theta0, Omega0, bias)
        if t0 is None:
            t0 = ts[0]
        elif not np.isfinite(t0):
            raise ValueError(f"t0 must be finite, got {t0!r}.")
        if float(t0) > ts[0]:
            raise ValueError(f"t0 = {t0} is after the first sample ts[0] = {ts[0]}.")

        def j(x):  # a checked NumPy array to the device: a transfer (jnp.asarray would compile
            # a small XLA program per shape)
            return None if x is None else jax.device_put(x)

        self.ts, self.theta0, self.Omega0 = j(ts), j(theta0), j(Omega0)
        self.t0 = j(np.asarray(float(t0)))
        self.theta, self.Q, self.omega, self.Omega = (
            j(arrays[k]) for k in ("theta", "Q", "omega", "Omega")
        )
        self.theta_weight, self.omega_weight, self.Omega_weight = (
            j(weights[k]) for k in ("theta_weight", "omega_weight", "Omega_weight")
        )
        self.attitude_weight, self.Omega_bias = j(attitude), j(bias)
        self.sigma_theta, self.sigma_omega, self.sigma_Omega = (sigmas[k] for k in _SIGMAS)
        self.fit_Omega_bias, self.initial_state_guessed = fit_bias, bool(guessed)

    @property
    def num_samples(self) -> int:
        return int(self.ts.shape[0])

    @classmethod
    def merge(cls, **channels) -> TrajectoryData:
        """Channels sampled on different clocks, on one time axis: each channel given as
        ``name=(ts, values)`` (``quaternion``, ``theta``, ``Q``, ``omega``, ``Omega``); the
        samples of all channels are placed on the union of their times, with NaN where a channel
        has no sample (a missing value). Other keywords (``sigma_*``,
        ``Omega_bias``, ``theta0``, ``Omega0``, ``t0``) are passed on.

        ``TrajectoryData.merge(quaternion=(t_mocap, q), Omega=(t_gyro, gyro), sigma_theta=1e-3,
        sigma_Omega=0.01, Omega_bias="fit")``.
        """
        streams = {k: v for k, v in channels.items() if k in _CHANNELS}
        rest = {k: v for k, v in channels.items() if k not in _CHANNELS}
        if not streams:
            raise ValueError(f"merge needs at least one channel: {', '.join(_CHANNELS)}.")
        times = {}
        for name, stream in streams.items():
            try:
                t, x = stream
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a pair (ts, values).") from None
            times[name] = _times(t)
            streams[name] = np.asarray(x, dtype=np.float64)
            if streams[name].shape[:1] != times[name].shape:
                raise ValueError(
                    f"{name} has {streams[name].shape[:1]} samples for {times[name].size} times."
                )
        ts = np.unique(np.concatenate(list(times.values())))
        out = {}
        for name, x in streams.items():
            full = np.full((ts.size,) + x.shape[1:], np.nan)
            full[np.searchsorted(ts, times[name])] = x
            out[name] = full
        return cls(ts, **out, **rest)

    def truncate(self, t_end) -> TrajectoryData:
        """The samples with t ≤ t_end (for staged horizons)."""
        keep = np.asarray(self.ts) <= t_end
        keep[0] = True

        def cut(x):
            return None if x is None else np.asarray(x)[keep]

        per_sample = {name: cut(getattr(self, name)) for name, _ in _OBSERVED + _WEIGHTS}
        if self.attitude_weight is not None:  # missing attitude samples back to NaN
            missing = cut(self.attitude_weight) == 0
            for name in ("theta", "Q"):
                if per_sample[name] is not None and self.theta_weight is None:
                    per_sample[name] = per_sample[name].copy()
                    per_sample[name][missing] = np.nan
        if not self.fit_Omega_bias and self.Omega_bias is None:
            bias = None
        else:
            bias = "fit" if self.fit_Omega_bias else np.asarray(self.Omega_bias)
        return TrajectoryData(
            np.asarray(self.ts)[keep],
            **per_sample,
            **{name: getattr(self, name) for name in ("theta0", "Omega0", "t0", *_SIGMAS)},
            Omega_bias=bias,
        )
