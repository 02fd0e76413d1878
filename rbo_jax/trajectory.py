r"""What every solver of the equations of motion returns, and the checks around it.

:class:`SolveStatus` is the outcome of every solve; :class:`AbstractTrajectory` what every
trajectory says about it (``ok``, ``message``, ``status_name``): :class:`Trajectory` (the rigid
body: :func:`rbo_jax.simulate`, :func:`rbo_jax.fast_simulate`),
:class:`rbo_jax.lattice.LatticeTrajectory` and :class:`rbo_jax.lattice.RodTrajectory`.

A trajectory holds samples $(t_i, \theta(t_i), \Omega(t_i))$ of the right form (4.55)–(4.56)
and derives the left angular velocity $\omega = P\cdot\Omega$, the turn-tensor $P = Q(\theta)$
(4.3), the kinetic moment (4.44) and the energies on access. Samples after a failure are ``inf``.

Shared by every solver: the checks of the sample times (:func:`check_times`) and of the
precision (:func:`warn_if_float32`), the checked inputs of a rigid body (:func:`prepare_inputs`),
the statuses of bad input (:func:`flag`) and ``throw`` (:func:`raise_failure`).
"""

from __future__ import annotations

import functools
import math
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from . import _enumeration
from ._validation import array_namespace, common_float_dtype, is_traced
from ._validation import tree_finite as all_finite  # simulate's name for it
from .kinematics import as_vector, safe_norm, turn_tensor
from .models.rigid_body import RigidBodyOscillator

__all__ = ["AbstractTrajectory", "SolveStatus", "Trajectory"]


class SolveStatus(eqx.Enumeration):
    """Outcome of a solve; ``SolveStatus[status]`` gives the message."""

    successful = ""
    max_steps_reached = (
        "The maximum number of solver steps was reached before the final time: increase "
        "`max_steps`, or loosen rtol/atol."
    )
    step_size_collapse = (
        "The step size collapsed below `dtmin`: the vector field became non-finite or the "
        "solution blew up (check the parameters and the initial state)."
    )
    singular_point = (
        "The turn-vector reached a singular point |theta| = 2*pi*k of the integrating tensor Z "
        "(eq. 4.11) with theta x Omega != 0, where det Z is infinite and the equations "
        "(4.54)/(4.56) break down."
    )
    domain_error = (
        "The turn-vector left the domain of the foundation energy (e.g. a barrier of eq. 4.49 "
        "was crossed)."
    )
    nonfinite_input = (
        "The initial state (theta0, Omega0) is not finite (or, in a sweep, a parameter of the "
        "point)."
    )
    solver_error = "The differential equation solver failed (see diffrax.RESULTS)."
    invalid_parameters = (
        "A model parameter is invalid (e.g. a negative stiffness, a non-positive definite "
        "inertia tensor, a NaN): the model was built from traced values that its constructors "
        "could not check; RigidBodyOscillator.parameter_status() names the parameter."
    )
    nonfinite_state = (
        "The state or the vector field became non-finite (NaN or inf) during the solve: the "
        "solution blew up."
    )
    invalid_times = (
        "The sample times ts are not finite or not strictly increasing (traced times with "
        "throw=False; concrete ones raise a ValueError)."
    )


@functools.cache
def status_code(name: str) -> int:
    """The integer code of the :class:`SolveStatus` item ``name`` (a Python int: a constant in
    the integrators' programs)."""
    return _enumeration.names(SolveStatus).index(name)


@eqx.filter_jit
def per_sample(f, *samples):
    """``f`` (a function, a bound method of the model or a ``jax.tree_util.Partial``) mapped
    over the samples, as one compiled program per quantity and model structure: run eagerly,
    each operation of ``f`` would compile a small XLA program of its own. Inside a
    transformation it is inlined."""
    return jax.vmap(f)(*samples)


class AbstractTrajectory(eqx.Module):
    """What every trajectory's ``status`` (a :class:`SolveStatus`) says: ``ok``, ``message``,
    ``status_name`` (of :class:`Trajectory`, :class:`rbo_jax.lattice.LatticeTrajectory` and
    :class:`rbo_jax.lattice.RodTrajectory`). The fields ``ts``, ``status`` and ``num_steps``
    are the subclass's own, not ``eqx.AbstractVar``s here, which would move them to the front
    of the fields."""

    @property
    def ok(self):
        """Whether the solve reached the final time (for a concrete status a NumPy boolean,
        compared on the host: no small eager program)."""
        code = _enumeration.code(self.status)
        if is_traced(code):
            return self.status == SolveStatus.successful
        return np.asarray(code) == np.asarray(_enumeration.code(SolveStatus.successful))

    @property
    def message(self) -> str:
        """The status message (for a concrete, unbatched trajectory)."""
        return SolveStatus[self.status] or "successful"

    @property
    def status_name(self) -> str:
        """The status as a name, e.g. ``"singular_point"`` (for a concrete, unbatched
        trajectory; the names are the fields of :class:`SolveStatus`)."""
        return _enumeration.name(self.status)

    def _dataset(self, data, coords, **attrs):
        """An :class:`xarray.Dataset` of ``data`` over the times ``t`` and ``coords``, with the
        attributes ``status``, ``message``, ``num_steps`` and ``attrs``."""
        import xarray as xr

        ds = xr.Dataset(data, coords={"t": ("t", np.asarray(self.ts), {"units": "s"}), **coords})
        ds.attrs.update(
            status=self.status_name, message=self.message, num_steps=int(self.num_steps), **attrs
        )
        return ds


# the variables theta and Omega of a trajectory's dataset: their attributes
THETA_ATTRS = {"long_name": "turn-vector theta (4.1)", "units": "rad"}
OMEGA_ATTRS = {"long_name": "right (body-frame) angular velocity Omega", "units": "rad s-1"}


class Trajectory(AbstractTrajectory):
    r"""Samples of a solution of the rigid body oscillator.

    Fields: ``ts`` (n,), ``theta`` (n, 3) the turn-vector, ``Omega`` (n, 3) the right angular
    velocity, ``model`` the :class:`RigidBodyOscillator`, ``status`` a :class:`SolveStatus`,
    ``num_steps`` the number of accepted solver steps. Samples after a failure are ``inf``.

    Derived (computed on access): ``omega`` = P·Ω (left angular velocity), ``turn_tensor`` P(t),
    ``kinetic_moment`` L (4.44), ``kinetic_energy``, ``potential_energy``, ``energy`` = K + U + V.
    """

    ts: Float[Array, " n"]
    theta: Float[Array, "n 3"]
    Omega: Float[Array, "n 3"]
    model: RigidBodyOscillator
    status: SolveStatus
    num_steps: Int[Array, ""]

    def _map(self, f):
        return per_sample(f, self.theta, self.Omega)

    @property
    def omega(self) -> Float[Array, "n 3"]:
        return self._map(self.model.omega)

    @property
    def turn_tensor(self) -> Float[Array, "n 3 3"]:
        return per_sample(turn_tensor, self.theta)

    @property
    def kinetic_moment(self) -> Float[Array, "n 3"]:
        return self._map(self.model.kinetic_moment)

    @property
    def kinetic_energy(self) -> Float[Array, " n"]:
        return per_sample(self.model.kinetic_energy, self.Omega)

    @property
    def potential_energy(self) -> Float[Array, " n"]:
        return per_sample(self.model.potential_energy, self.theta)

    @property
    def energy(self) -> Float[Array, " n"]:
        return self._map(self.model.energy)

    def to_xarray(self, **attrs):
        """The samples as an :class:`xarray.Dataset` (for a concrete, unbatched trajectory).

        Dimensions ``t`` and ``component`` (x, y, z of the reference basis); variables
        ``theta`` (the turn-vector, rad), ``Omega`` and ``omega`` (right and left angular
        velocities), ``energy`` (K + U + V) and ``reached`` (whether the solver reached the
        sample). Attributes: ``status`` (a :class:`SolveStatus` name), ``message``,
        ``num_steps``, plus ``attrs``. Units are those of the model's parameters (any
        consistent set; the labels name SI units).
        """
        theta, Omega = np.asarray(self.theta), np.asarray(self.Omega)
        reached = np.all(np.isfinite(theta), axis=1) & np.all(np.isfinite(Omega), axis=1)
        vec = ("t", "component")
        data = {
            "theta": (vec, theta, THETA_ATTRS),
            "Omega": (vec, Omega, OMEGA_ATTRS),
            "omega": (
                vec,
                np.asarray(self.omega),
                {
                    "long_name": "left (world-frame) angular velocity omega = P.Omega",
                    "units": "rad s-1",
                },
            ),
            "energy": (
                "t",
                np.asarray(self.energy),
                {"long_name": "mechanical energy K + U + V", "units": "J"},
            ),
            "reached": ("t", reached, {"long_name": "the solver reached this sample"}),
        }
        return self._dataset(data, {"component": ["x", "y", "z"]}, **attrs)


# ------------------------------------------------------------------------------------------
# Helpers shared by the solvers.
# ------------------------------------------------------------------------------------------

# |θ×Ω| / (|θ||Ω|) below this counts as plane motion, which crosses the singular spheres
# |θ| = 2πk of Z harmlessly.
TRANSVERSE_TOL = 1e-6


def transverse_fraction(theta, Omega):
    """|θ×Ω| / (|θ||Ω|): 0 for plane motion, where the singular spheres are harmless."""
    return safe_norm(jnp.cross(theta, Omega)) / (safe_norm(theta) * safe_norm(Omega) + 1e-300)


def crossed_sphere(n, n_old):
    """Whether a step from a turn-vector of norm ``n_old`` to one of norm ``n`` crossed a
    singular sphere |θ| = 2πk (k ≥ 1) of Z (4.11)."""
    two_pi = 2.0 * math.pi
    return (jnp.floor(n / two_pi) != jnp.floor(n_old / two_pi)) & (jnp.maximum(n, n_old) >= math.pi)


def is_transverse(theta, Omega):
    """Whether the motion is off the plane (θ×Ω ≠ 0 beyond :data:`TRANSVERSE_TOL`): where the
    singular spheres |θ| = 2πk of Z stop a solve."""
    return transverse_fraction(theta, Omega) > TRANSVERSE_TOL


def check_times(ts, throw: bool = True):
    """``ts`` as a strictly increasing, finite, non-empty 1-D float array: concrete values are
    checked now (``ValueError``); traced ones with :func:`equinox.error_if` when ``throw``, and
    not here otherwise (:func:`prepare_inputs` folds them into the status
    ``invalid_times``, so that ``throw=False`` programs hold no host callback)."""
    traced = any(is_traced(t) for t in jax.tree_util.tree_leaves(ts))
    # concrete times are checked in NumPy and then moved to the device (a transfer):
    # jnp.asarray of a NumPy array compiles a small XLA program per shape
    given = ts
    ts = jnp.asarray(ts) if traced else np.asarray(ts)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"ts must be a non-empty 1-D array of times, got shape {ts.shape}.")
    if not jnp.issubdtype(ts.dtype, jnp.floating):
        ts = ts.astype(jnp.result_type(float))
    if traced:
        if throw:
            ts = eqx.error_if(ts, ~times_ok(ts), "ts must be finite and strictly increasing.")
        return ts
    ts = ts.astype(jax.dtypes.canonicalize_dtype(ts.dtype))  # checked in the solve's precision
    if not np.all(np.isfinite(ts)):
        raise ValueError("ts must be finite.")
    if ts.shape[0] > 1 and not np.all(np.diff(ts) > 0):
        raise ValueError("ts must be strictly increasing.")
    if isinstance(given, jax.Array) and given.dtype == ts.dtype:
        return given
    return jax.device_put(ts)


def times_ok(ts):
    """Whether the (traced) times ``ts`` are finite and strictly increasing."""
    return jnp.all(jnp.isfinite(ts)) & jnp.all(jnp.diff(ts) > 0)


def warn_if_float32(dtype, rtol, atol):
    """Warn when a solve in ``dtype`` is asked for tolerances below its resolution."""
    eps = float(jnp.finfo(dtype).eps)
    try:
        tol = min(float(rtol), float(atol))
    except (TypeError, jax.errors.ConcretizationTypeError):
        return
    if tol < 10 * eps:
        warnings.warn(
            f"rbo_jax: integrating in {jnp.dtype(dtype).name} with tolerance {tol:g}, below what "
            f"its precision (eps = {eps:.1e}) can deliver. Enable float64 (import rbo_jax before "
            "creating arrays, and do not set JAX_ENABLE_X64=0), or loosen rtol/atol.",
            RuntimeWarning,
            stacklevel=3,
        )


class Inputs(NamedTuple):
    """The checked input of a solve (:func:`prepare_inputs`): ``theta0``, ``Omega0`` and ``ts``
    to integrate (zeros in place of bad input), ``dtype``, the flags ``bad_input``,
    ``invalid`` (parameters) and ``bad_times``, and ``ts_given``, the times as given (what the
    :class:`Trajectory` reports)."""

    theta0: Array
    Omega0: Array
    ts: Array
    dtype: np.dtype
    bad_input: Array
    invalid: Array
    bad_times: Array
    ts_given: Array


def prepare_inputs(model, theta0, Omega0, ts, rtol, atol, throw) -> Inputs:
    """Checked initial state and sample times in the solve's precision, and the flags of bad
    input.

    The state takes the precision of the model too: float32 initial values with a float64 model
    (the default) are integrated in float64. A non-finite initial state (``bad_input``), invalid
    parameters (``invalid``: :meth:`RigidBodyOscillator.parameter_status`) or, with traced
    ``ts``, times that are not finite and strictly increasing (``bad_times``) replace the state
    (and the times) by zeros, so that the solve runs harmlessly, and are flagged by
    :func:`finish`. With ``throw`` the last two raise their message here instead; without, no
    check is a host callback (JAX's persistent compilation cache keeps only programs without
    them). Infinite parameters can be legitimate (``BarrierFoundation(alpha=inf)`` switches a
    barrier off), NaN ones never are.
    """
    theta0 = as_vector(theta0, "theta0")
    Omega0 = as_vector(Omega0, "Omega0")
    ts = check_times(ts, throw)
    params = jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_inexact_array))
    dtype = common_float_dtype(theta0, Omega0, ts, *params)
    theta0, Omega0, ts = theta0.astype(dtype), Omega0.astype(dtype), ts.astype(dtype)
    warn_if_float32(dtype, rtol, atol)
    ok, which, messages = model.parameter_status()
    if array_namespace(theta0, Omega0, ts, ok) is np:
        # everything concrete: the flags in NumPy (no small eager programs); the state is
        # replaced only when a flag is set
        ok = bool(ok)
        if throw and not ok:
            theta0 = eqx.branched_error_if(theta0, jnp.asarray(True), int(which), messages)
        bad_input = not (
            np.all(np.isfinite(np.asarray(theta0))) and np.all(np.isfinite(np.asarray(Omega0)))
        )
        if bad_input or not ok:
            zeros = jax.device_put(np.zeros(3, dtype))
            theta0, Omega0 = zeros, zeros
        return Inputs(
            theta0=theta0,
            Omega0=Omega0,
            ts=ts,
            dtype=dtype,
            bad_input=np.bool_(bad_input),
            invalid=np.bool_(not ok),
            bad_times=np.bool_(False),
            ts_given=ts,
        )
    if throw:
        theta0 = eqx.branched_error_if(theta0, ~ok, which, messages)
    bad_times = (
        ~times_ok(ts) if isinstance(ts, jax.core.Tracer) and not throw else jnp.asarray(False)
    )
    bad_input = ~all_finite((theta0, Omega0))
    zeros = jnp.zeros_like(theta0)
    stop = bad_input | ~ok | bad_times
    return Inputs(
        theta0=jnp.where(stop, zeros, theta0),
        Omega0=jnp.where(stop, zeros, Omega0),
        ts=jnp.where(bad_times, jnp.zeros_like(ts), ts),
        dtype=dtype,
        bad_input=bad_input,
        invalid=~ok,
        bad_times=bad_times,
        ts_given=ts,
    )


def flag(status, tree, cond, name: str, fill):
    """``(status, tree)`` with the status ``name`` (a :class:`SolveStatus` field) and every leaf
    of ``tree`` ``fill`` (``inf`` for samples not reached, NaN for no result) where ``cond``."""
    status = SolveStatus.where(cond, getattr(SolveStatus, name), status)
    return status, jax.tree_util.tree_map(lambda x: jnp.where(cond, fill, x), tree)


def raise_failure(x, status, throw: bool, messages=None):
    """``x``, raising the message of a failed ``status`` with ``throw``
    (:func:`equinox.error_if`, inside a program too): the status's own, or ``messages[code]``
    (:func:`equinox.branched_error_if`). A concrete success runs nothing (no small eager
    program)."""
    code = _enumeration.code(status)
    if not throw or (not is_traced(code) and _enumeration.name(status) == "successful"):
        return x
    failed = status != SolveStatus.successful
    if messages is None:
        return status.error_if(x, failed)
    return eqx.branched_error_if(x, failed, code, messages)


def finish(model, inputs: Inputs, theta, Omega, status, num_steps, throw) -> Trajectory:
    """The :class:`Trajectory` of a solve: samples of a non-finite input are ``inf``, those of
    invalid parameters or times NaN (none of them is a result); with ``throw`` a failure raises
    its status message."""
    flags = (inputs.bad_input, inputs.invalid, inputs.bad_times)
    # concrete and nothing flagged: no replacement (no small eager programs)
    if not (array_namespace(flags) is np and not any(bool(f) for f in flags)):
        status = SolveStatus.where(inputs.bad_input, SolveStatus.nonfinite_input, status)
        status = SolveStatus.where(inputs.invalid, SolveStatus.invalid_parameters, status)
        status = SolveStatus.where(inputs.bad_times, SolveStatus.invalid_times, status)
        nan = inputs.invalid | inputs.bad_times
        fill = jnp.where(nan, jnp.nan, jnp.inf)
        theta = jnp.where(inputs.bad_input | nan, fill, theta)
        Omega = jnp.where(inputs.bad_input | nan, fill, Omega)
    theta = raise_failure(theta, status, throw)
    return Trajectory(inputs.ts_given, theta, Omega, model, status, num_steps)
