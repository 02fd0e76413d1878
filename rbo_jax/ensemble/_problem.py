r"""What the integrator needs from a model, for one trajectory or a structure of arrays of them.

:class:`Problem` wraps the model's right form (4.55)–(4.56) (:meth:`RigidBodyOscillator.right_form`,
with $A^{-1}$ computed once) as a function of the six state components, and the per-step checks:
the singular spheres $|\theta| = 2\pi k$ of $Z$ (4.11) and the domain of the foundation energy.

For B trajectories at once the problem's leaves carry the batch on their **last** axis
(component-major: a vector parameter is ``(3, B)``), and :func:`lanes` evaluates the per-trajectory
code with ``jax.vmap`` over that axis: every component is then a contiguous ``(B,)`` array, and
the vector field becomes element-wise code over the lanes.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..integrate.dop853 import Store
from ..kinematics import distance_to_singularity, dot3, storing
from ..models.rigid_body import RightForm
from ..trajectory import crossed_sphere, is_transverse
from ..trajectory import status_code as code


def _norm(v):
    return jnp.sqrt(dot3(v, v))


class Problem(eqx.Module):
    """One trajectory's equations of motion and checks, on state tuples (θ0, θ1, θ2, Ω0, Ω1, Ω2)."""

    rhs: RightForm

    def f(self, t, y):
        theta_dot, Omega_dot = self.rhs(t, (jnp.stack(y[:3]), jnp.stack(y[3:])))
        return (theta_dot[0], theta_dot[1], theta_dot[2], Omega_dot[0], Omega_dot[1], Omega_dot[2])

    def failure(self, y_old, y_new, singular_tol):
        """The status code of an accepted step that must stop the solve, else ``successful``:
        a non-finite state, the turn within ``singular_tol`` of a sphere |θ| = 2πk (k ≥ 1) or
        across one while θ×Ω ≠ 0 (plane motion crosses them harmlessly), or θ outside the domain
        of the foundation energy. The same tests as :func:`rbo_jax.simulate`'s events
        (:func:`rbo_jax.distance_to_singularity`, ``transverse_fraction``), made once per step."""
        y_old, y_new = jax.lax.stop_gradient((tuple(y_old), tuple(y_new)))  # a status only
        theta, Omega = jnp.stack(y_new[:3]), jnp.stack(y_new[3:])
        near = distance_to_singularity(theta) < singular_tol
        n, n_old = _norm(theta), _norm(jnp.stack(y_old[:3]))
        crossed = crossed_sphere(n, n_old)
        transverse = is_transverse(theta, Omega)
        finite = jnp.all(jnp.isfinite(jnp.stack(y_new)))
        outside = ~(self.rhs.model.domain_margin(theta) > 0)
        status = jnp.where(outside, code("domain_error"), code("successful"))
        status = jnp.where((near | crossed) & transverse, code("singular_point"), status)
        return jnp.where(finite, status, code("nonfinite_state"))


@jax.jit
def _f_once(problem: Problem, t, y, one):
    with storing(Store(one)):
        return problem.f(t, y)


def traced_once(problem: Problem, store: Store):
    """``problem.f`` for a loop body, as calls of one jitted function: JAX traces the vector
    field once per signature (not once per stage: a DOP853 step with its dense output and
    initial step holds ~17 of them), and differentiates and batches that one trace, cached,
    however often it is called; XLA inlines the calls, so the compiled program is unchanged."""
    return lambda t, y: _f_once(problem, t, y, store.one)


def to_lanes(tree, batched):
    """Leaves with the batch axis moved last; ``batched`` (a matching tree of bools, or one bool)
    says which leaves have a leading batch axis (the others are shared and keep their shape)."""
    if isinstance(batched, bool):
        batched = jax.tree_util.tree_map(lambda _: batched, tree)
    return jax.tree_util.tree_map(lambda x, b: jnp.moveaxis(x, 0, -1) if b else x, tree, batched)


def lane_axes(tree, batched):
    """The ``in_axes`` of :func:`lanes` for a tree laid out by :func:`to_lanes`."""
    if isinstance(batched, bool):
        batched = jax.tree_util.tree_map(lambda _: batched, tree)
    return jax.tree_util.tree_map(lambda x, b: x.ndim - 1 if b else None, tree, batched)


def lanes(method: str, problem: Problem, axes, *args):
    """``problem.<method>(*args)`` for every lane: a vmap over the last axis of the problem's
    batched leaves and the leading axis of the ``(B,)`` components in ``args``."""
    fn = getattr(Problem, method)
    arg_axes = jax.tree_util.tree_map(lambda x: 0 if jnp.ndim(x) else None, args)
    return jax.vmap(fn, in_axes=(axes, *arg_axes))(problem, *args)
