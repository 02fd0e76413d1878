r"""A batch whose inputs are sharded over several devices, run as each device's share under
``jax.shard_map``: the ``jax.jit(jax.vmap(fast_simulate))`` of a user whose arrays lie on a
:class:`jax.sharding.NamedSharding`.

Left to GSPMD, the batching rule's ``while_loop`` over the refilled lanes was partitioned as
one loop that every device ran on every lane, with an all-reduce in each iteration: slower on
2 devices than on one (benchmarks/README.md, issue 49 G). Here each device runs
:func:`._solve.solve_lanes` on its own share, with no collective inside the loop (STYLE.md 18,
as the batch engine's chunks, :mod:`rbo_jax.batch._program`); the only communication is the
exchange of the inputs and outputs around it.

**Which mesh** (:func:`batch_mesh`). Under ``jax.jit`` an input's abstract value carries the
mesh of its sharding (``jax.typeof(x).sharding.mesh``, an :class:`jax.sharding.AbstractMesh`;
concrete arrays, under a ``vmap`` without ``jit``, carry the mesh itself), and values computed
from it keep it: the batch runs over every device of the first mesh of more than one device
found among the rule's inputs, else over the context mesh (``jax.set_mesh``). Inputs on one
device (or NumPy inputs) and a call inside ``shard_map`` (the batch engine's programs, whose
context mesh has manual axes: already one device's share) run on one device, as before.

**The same bits on any number of devices.** A trajectory's bits do not depend on its lane
(:data:`._solve.VECTOR`), so each device's share gives the bits the whole batch gives on one.
The batch is padded to a multiple of the devices with copies of its last trajectory (at most
one more per device), and dealt to the devices like cards (:func:`rbo_jax._sharding.deal`, as
the batch engine's chunks): neighbouring points of a grid cost alike, and contiguous shares
left one device idle while the other finished the costly region (measured in
benchmarks/README.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from .._sharding import deal, undeal


def _manual(mesh) -> bool:
    return bool(getattr(mesh, "manual_axes", ()))


def _mesh_of(leaf):
    """The mesh of an array's sharding (abstract for a traced value), or ``None``."""
    if isinstance(leaf, jax.Array) and not isinstance(leaf, jax.core.Tracer):
        sharding = leaf.sharding
        return sharding.mesh if isinstance(sharding, NamedSharding) else None
    try:
        return jax.typeof(leaf).sharding.mesh
    except (AttributeError, TypeError):
        return None


def batch_mesh(tree):
    """The mesh whose devices should share a batch of the arrays in ``tree`` (module
    docstring), or ``None``: one device (inputs on one device, or already inside
    ``shard_map``)."""
    context = jax.sharding.get_abstract_mesh()
    if _manual(context):
        return None
    for leaf in jax.tree_util.tree_leaves(tree):
        mesh = _mesh_of(leaf)
        if mesh is not None and not mesh.empty and mesh.size > 1 and not _manual(mesh):
            return mesh
    if not context.empty and context.size > 1:
        return context
    return None


def _spread(x, total: int, n_devices: int):
    """A batched leaf padded to ``total`` rows (copies of its last row), then dealt."""
    x = jnp.asarray(x)
    pad = total - x.shape[0]
    if pad:
        x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad, *x.shape[1:]))])
    return deal(x, n_devices)


def over_mesh(local, mesh, args, batched):
    """``local(*args)`` with every device of ``mesh`` running it on its share of the batch:
    ``batched`` (a tree of bools matching ``args``) says which leaves have the batch on their
    leading axis (padded and dealt, :func:`rbo_jax._sharding.deal`); the others go whole to
    every device. Every output of ``local`` has the batch on its leading axis; they come back
    in the batch's order."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    flags = jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda _, b: bool(b), args, batched))
    n = next(jnp.shape(x)[0] for x, b in zip(leaves, flags) if b)
    devices = mesh.size
    total = -(-n // devices) * devices
    axes = P(tuple(mesh.axis_names))
    leaves = [_spread(x, total, devices) if b else jnp.asarray(x) for x, b in zip(leaves, flags)]

    def share(*local_leaves):  # one device's share: its lanes, no collective
        return local(*jax.tree_util.tree_unflatten(tree, local_leaves))

    specs = tuple(axes if b else P() for b in flags)
    run = jax.shard_map(share, mesh=mesh, in_specs=specs, out_specs=axes, check_vma=False)
    out = jax.jit(run)(*leaves)
    return jax.tree_util.tree_map(lambda y: undeal(y, devices)[:n], out)
