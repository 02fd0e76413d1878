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


def _observations(ts, given: dict, weights_given: dict):
    """The observed arrays and weights, checked; unobserved values (weight 0) zeroed."""
    n = ts.size
    if given["theta"] is not None and given["Q"] is not None:
        raise ValueError("give the attitude either as theta or as Q, not both.")
    if all(x is None for x in given.values()):
        raise ValueError("nothing observed: give at least one of theta, Q, omega, Omega.")
    arrays = {
        name: None if given[name] is None else _host_array(given[name], name, tail, n)
        for name, tail in _OBSERVED
    }
    weights = {}
    for name, obs in _WEIGHTS:
        w = weights_given[name]
        if w is None:
            weights[name] = None
            continue
        if arrays[obs] is None:
            raise ValueError(f"{name} given but {obs} is not observed.")
        w = _host_array(w, name, (3,), n)
        bad = np.argwhere(~(np.isfinite(w) & (w >= 0)))
        if bad.size:
            raise ValueError(f"{name} must be finite and non-negative (sample {bad[0][0]}).")
        weights[name] = w
    for name, x in arrays.items():
        if x is None:
            continue
        w = weights.get(f"{name}_weight")
        bad = ~np.isfinite(x)
        if w is not None:
            bad = bad & (w > 0)
        if np.any(bad):
            i = int(np.argwhere(bad)[0][0])
            raise ValueError(
                f"{name} contains NaN or inf (first at sample {i}, t = {ts[i]}); mark missing "
                f"values with {name}_weight = 0 and any finite value."
            )
        if w is not None:
            arrays[name] = np.where(w > 0, x, 0.0)
    return arrays, weights


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


def _initial_state(arrays, weights, theta0, Omega0):
    """(θ0, Ω0): as given, else from the first samples when they are fully observed."""

    def first(name):
        x, w = arrays[name], weights.get(f"{name}_weight")
        return None if x is None or (w is not None and not np.all(w[0] > 0)) else x[0]

    if theta0 is None:
        theta0 = first("theta")
        if theta0 is None and arrays["Q"] is not None:
            theta0 = np.asarray(turn_vector(arrays["Q"][0]))
        if theta0 is None:
            raise ValueError("theta0 is needed: the attitude at t0 is not fully observed.")
    if Omega0 is None:
        Omega0 = first("Omega")
        if Omega0 is None and first("omega") is not None:
            th0 = np.asarray(theta0, dtype=np.float64)
            Omega0 = np.asarray(turn_tensor(th0)).T @ arrays["omega"][0]
        if Omega0 is None:
            raise ValueError("Omega0 is needed: the angular velocity at t0 is not observed.")
    theta0 = _host_array(np.asarray(theta0)[None], "theta0", (3,))[0]
    Omega0 = _host_array(np.asarray(Omega0)[None], "Omega0", (3,))[0]
    if not (np.all(np.isfinite(theta0)) and np.all(np.isfinite(Omega0))):
        raise ValueError("theta0 and Omega0 must be finite.")
    return theta0, Omega0


class TrajectoryData(eqx.Module):
    r"""One observed trajectory: sample times ``ts`` and any of ``theta`` (n, 3), ``Q`` (n, 3, 3),
    ``omega`` (n, 3) (left angular velocity), ``Omega`` (n, 3) (right angular velocity).

    ``theta0``, ``Omega0``: the initial state at ``t0`` (default ``ts[0]``); if not given they
    are taken from the first samples (θ or Q, and Ω or ω) — they are the starting guess when the
    initial state is fitted. ``*_weight`` (n, 3) arrays of non-negative weights mark missing or
    unobserved components with 0 (NaN values are refused: give them weight 0 and any finite
    value). ``sigma_*`` are the noise standard deviations (None: unknown, estimated from the
    residuals).

    All checks (shapes, NaN or inf samples, strictly increasing times, positive noise levels, at
    least one observed quantity) happen here, on the host, before anything is compiled; the
    messages name the field and the first bad sample.
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
    sigma_theta: float | None = eqx.field(static=True)
    sigma_omega: float | None = eqx.field(static=True)
    sigma_Omega: float | None = eqx.field(static=True)

    def __init__(
        self,
        ts,
        *,
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
    ):
        ts = _times(ts)
        arrays, weights = _observations(
            ts,
            {"theta": theta, "Q": Q, "omega": omega, "Omega": Omega},
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
        theta0, Omega0 = _initial_state(arrays, weights, theta0, Omega0)
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
        self.sigma_theta, self.sigma_omega, self.sigma_Omega = (sigmas[k] for k in _SIGMAS)

    @property
    def num_samples(self) -> int:
        return int(self.ts.shape[0])

    def truncate(self, t_end) -> TrajectoryData:
        """The samples with t ≤ t_end (for staged horizons)."""
        keep = np.asarray(self.ts) <= t_end
        keep[0] = True

        def cut(x):
            return None if x is None else np.asarray(x)[keep]

        per_sample = [name for name, _ in _OBSERVED + _WEIGHTS]
        return TrajectoryData(
            np.asarray(self.ts)[keep],
            **{name: cut(getattr(self, name)) for name in per_sample},
            **{name: getattr(self, name) for name in ("theta0", "Omega0", "t0", *_SIGMAS)},
        )
