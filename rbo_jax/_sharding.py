"""Work spread over the local devices: one program per chunk of points, each device computing its
share with no communication (``jit(shard_map(vmap(...)))`` of one point's jaxpr).

The machinery of the batch engine (:mod:`rbo_jax.batch._program`, whose docstring explains the
choices), kept at the bottom of the package so that lower layers batch over every device too
(:func:`map_points`: the vmapped curves of :func:`rbo_jax.continue_hopf`).

- :func:`block_size` and :func:`lapack_in_blocks`: LAPACK calls in blocks that jaxlib never
  splits over XLA's intra-op pool (a split blocks a pool thread until tasks on the same pool
  finish; with one device per core that waited forever, issue 31);
- :class:`Layout`: a device's share is a multiple of :data:`VECTOR` points, so that a point's
  bits do not depend on the number of devices;
- :func:`point_program`: one point's function, traced once, batched and sharded.
"""

from __future__ import annotations

import contextlib
import math
import threading

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax._src import core as jax_core
from jax._src.interpreters import batching
from jax.extend.core import jaxpr_as_fun, jaxprs_in_params
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

BATCH_AXIS = "batch"
# A device's share of a chunk is a multiple of this many points: no
# point in the scalar remainder of a vectorised loop (16 doubles: two AVX-512 vectors).
VECTOR = 16
# jaxlib splits a batched LAPACK call over the intra-op pool from this much work (flop) on
# (GetLapackBatchChunkSize, kMinWorkPerTask).
SPLIT_WORK = 200_000
# jaxlib's cost per matrix of each LAPACK kernel a primitive lowers to (``cost_per_matrix`` in
# jaxlib/cpu/lapack_kernels.cc), bounded by a multiple of n³, n the largest matrix dimension of
# the call's operands: trsm m·k·m, getrf m·n·min, potrf n³/3, geqrf and geqp3 ≤ 2mn·min,
# orgqr ≤ 4mnk + 4k³/3 (``qr`` runs geqrf and orgqr), ormqr ≤ 4k·m·n, gesdd/gesvd 10mn·min,
# syevd 5n³ (heevd 4n³ × 3), real geev 10n³, gees 5n³, gehrd 2n³, sytrd 4n³/3, gtsv 5·m·k;
# complex types × 3 (KERNEL_COMPLEX). A primitive not listed (``cholesky_update``) takes
# COST_PER_N3, a bound of every kernel. Each call's blocks follow its own kernel's estimate,
# not a bound of every kernel, so that cheap kernels run in few large blocks
# (benchmarks/README.md, History).
KERNEL_COST = {
    "triangular_solve": 1,
    "lu": 1,
    "cholesky": 1,
    "geqrf": 2,
    "geqp3": 2,
    "householder_product": 6,
    "qr": 6,
    "ormqr": 4,
    "svd": 10,
    "eigh": 5,
    "eig": 10,
    "schur": 5,
    "hessenberg": 2,
    "tridiagonal": 2,
    "tridiagonal_solve": 5,
}
KERNEL_COMPLEX = 3
COST_PER_N3 = 30
# The primitives that lower to LAPACK on CPU (jax._src.lax.linalg), and the FFT (ducc, which
# also runs on the intra-op pool).
LINALG = frozenset(
    {
        "cholesky",
        "cholesky_update",
        "eig",
        "eigh",
        "geqp3",
        "geqrf",
        "hessenberg",
        "householder_product",
        "lu",
        "ormqr",
        "qr",
        "schur",
        "svd",
        "triangular_solve",
        "tridiagonal",
        "tridiagonal_solve",
    }
)


def _equations(jaxpr):
    for eqn in jaxpr.eqns:
        yield eqn
        for sub in jaxprs_in_params(eqn.params):
            yield from _equations(sub)


def _call_work(name, shapes, dtypes) -> int:
    """A bound of jaxlib's work estimate for one element of a call of primitive ``name`` whose
    operands have ``shapes`` (without the batch axis) and ``dtypes``: :data:`KERNEL_COST` · n³
    per matrix (n the largest of the operands' matrix dimensions) × the matrices per element."""
    n = max((max(s[-2:]) for s in shapes if len(s) >= 1), default=1)
    first = shapes[0] if shapes else ()
    matrices = math.prod(first[:-2]) if len(first) >= 2 else 1
    cost = KERNEL_COST.get(name, COST_PER_N3)
    if any(jnp.issubdtype(d, jnp.complexfloating) for d in dtypes):
        cost *= KERNEL_COMPLEX
    return cost * int(n) ** 3 * int(matrices)


def _lapack_work(eqn) -> int:
    """:func:`_call_work` of one point's call ``eqn``."""
    avals = [v.aval for v in eqn.invars if hasattr(v.aval, "shape")]
    return _call_work(eqn.primitive.name, [a.shape for a in avals], [a.dtype for a in avals])


def block_size(jaxpr) -> int:
    """The smallest block of a quantity whose one-point ``jaxpr`` calls LAPACK (or an FFT): the
    most points whose batched costliest call jaxlib never splits over the intra-op pool (each
    call is run in blocks of its own, :func:`lapack_in_blocks`); 0 when the quantity calls
    neither (nothing is run in blocks)."""
    work, fft = 0, False
    for eqn in _equations(jaxpr):
        name = eqn.primitive.name
        if name == "fft":
            fft = True
        elif name in LINALG:
            work = max(work, _lapack_work(eqn))
    if fft:
        return 1  # ducc splits a transform by the number of transforms: one point at a time
    if work == 0:
        return 0
    return max(1, (SPLIT_WORK - 1) // work)


def local_function(closed, out_tree):
    """The per-device function ``(points, n) -> outputs`` of one point's jaxpr (``vmap``)."""
    fn = jaxpr_as_fun(closed)
    batched = jax.vmap(lambda x: fn(x))

    def chunk_program(xs):  # the name in JAX's logs and persistent cache
        return jax.tree_util.tree_unflatten(out_tree, batched(xs))

    return chunk_program


def _element_block(prim, vals, dims) -> int:
    """The most elements of this batched call that jaxlib never splits: :func:`block_size` of
    one element (its operands without the batch axis; a batch nested inside the element, e.g.
    a ``vmap`` inside the point function, counts as its matrices)."""
    if prim.name == "fft":
        return 1
    shapes = [
        tuple(s for k, s in enumerate(jnp.shape(v)) if k != d)
        for v, d in zip(vals, dims)
        if jnp.ndim(v) >= 1
    ]
    dtypes = [jnp.result_type(v) for v in vals if jnp.ndim(v) >= 1]
    return max(1, (SPLIT_WORK - 1) // _call_work(prim.name, shapes, dtypes))


# LU factorisations and triangular solves of matrices up to this order run in XLA, not LAPACK,
# inside a chunk program (:func:`_small_rule`). jaxlib calls LAPACK once per matrix, and
# OpenBLAS's getrf and trsm take its buffer (``blas_memory_alloc``, behind a process-wide lock)
# around every call: with one device per core, the devices' threads queued on that lock. A
# batched loop over the rows has no lock and no call per matrix (figures: benchmarks/README.md,
# History).
SMALL_MATRIX = 4


def _batched(vals, dims, size):
    """The operands with their batch axis first (an unbatched one broadcast to ``size``)."""
    return [
        jnp.broadcast_to(v, (size, *jnp.shape(v))) if d is None else jnp.moveaxis(v, d, 0)
        for v, d in zip(vals, dims)
    ]


def _lu_rows(a):
    """LAPACK's ``getrf`` (partial pivoting, the row of the largest magnitude) on a batch
    ``a`` (B, m, n): ``(lu, pivots, permutation)`` as :func:`jax.lax.linalg.lu` returns them.
    JAX's own loop for platforms without LAPACK (``_lu_unblocked``), batched: a ``fori_loop``
    over the columns, every step on all the matrices at once."""
    B, m, n = a.shape
    rows = jnp.arange(m, dtype=jnp.int32)[None, :]  # (1, m)
    take = jax.vmap(lambda x, i: x[i])

    def column(k, state):
        pivots, perm, a = state
        ak = lax.dynamic_index_in_dim(a, k, axis=2, keepdims=False)  # (B, m)
        size = jnp.abs(ak.real) + jnp.abs(ak.imag) if jnp.iscomplexobj(ak) else jnp.abs(ak)
        i = jnp.argmax(jnp.where(rows >= k, size, -jnp.inf), axis=1).astype(jnp.int32)[:, None]
        pivots = lax.dynamic_update_index_in_dim(pivots, i, k, axis=1)
        swap = jnp.where(rows == k, i, jnp.where(rows == i, k, rows))  # (B, m)
        a, perm = take(a, swap), take(perm, swap)
        ak = lax.dynamic_index_in_dim(a, k, axis=2, keepdims=False)
        x = lax.dynamic_index_in_dim(ak, k, axis=1)  # the pivots (B, 1)
        scaled = ak / jnp.where(x != 0, x, jnp.ones_like(x))
        ak = jnp.where((rows > k) & (x != 0), scaled, ak)
        a = lax.dynamic_update_index_in_dim(a, ak, k, axis=2)
        ark = lax.dynamic_index_in_dim(a, k, axis=1)  # row k (B, 1, n)
        cols = jnp.arange(n, dtype=jnp.int32)[None, None, :]
        update = (rows[:, :, None] > k) & (cols > k)
        return pivots, perm, a - jnp.where(update, ak[:, :, None] * ark, jnp.zeros_like(a))

    pivots = jnp.zeros((B, min(m, n)), jnp.int32)
    perm = jnp.broadcast_to(jnp.arange(m, dtype=jnp.int32)[None, :], (B, m))
    pivots, perm, a = lax.fori_loop(0, min(m, n), column, (pivots, perm, a))
    return a, pivots, perm


def _triangular_rows(a, b, *, left_side, lower, transpose_a, conjugate_a, unit_diagonal):
    """``op(a) x = b`` (``left_side``) on batches ``a`` (B, m, m), ``b`` (B, m, k) by
    substitution, a ``fori_loop`` over the rows (``op``: transposed and/or conjugated)."""
    del left_side
    A = jnp.conj(a) if conjugate_a else a
    A = jnp.swapaxes(A, 1, 2) if transpose_a else A
    low = lower != transpose_a
    m = A.shape[-1]
    eye = jnp.eye(m, dtype=A.dtype)[None]
    A = jnp.tril(A) if low else jnp.triu(A)
    if unit_diagonal:
        A = A * (1 - eye) + eye

    def row(k, x):
        i = k if low else m - 1 - k
        Ai = lax.dynamic_index_in_dim(A, i, axis=1, keepdims=False)  # (B, m)
        bi = lax.dynamic_index_in_dim(b, i, axis=1, keepdims=False)  # (B, k)
        d = lax.dynamic_index_in_dim(Ai, i, axis=1, keepdims=False)  # (B,)
        xi = (bi - jnp.einsum("bj,bjk->bk", Ai, x)) / d[:, None]
        return lax.dynamic_update_index_in_dim(x, xi, i, axis=1)

    return lax.fori_loop(0, m, row, jnp.zeros(b.shape, jnp.result_type(A, b)))


def _small_rule(prim, axis_data, vals, dims, params):
    """The batched ``lu`` or left-side ``triangular_solve`` of matrices up to
    :data:`SMALL_MATRIX` rows in XLA (:func:`_lu_rows`, :func:`_triangular_rows`), or ``None``
    for any other call."""
    if prim.name not in ("lu", "triangular_solve") or all(d is None for d in dims):
        return None
    if prim.name == "triangular_solve" and not params["left_side"]:
        return None
    # each operand of one element a matrix, the first at most SMALL_MATRIX in both dimensions
    shapes = [[n for k, n in enumerate(jnp.shape(v)) if k != d] for v, d in zip(vals, dims)]
    if any(len(s) != 2 for s in shapes) or max(shapes[0]) > SMALL_MATRIX:
        return None
    ops = _batched(vals, dims, int(axis_data.size))
    if prim.name == "lu":
        return _lu_rows(ops[0]), (0, 0, 0)
    return _triangular_rows(*ops, **params), 0


def _chunked_rule(prim, original):
    """A batching rule of ``prim`` that runs a batch larger than jaxlib would run unsplit (from
    the operands' shapes, :func:`_element_block`) as ``lax.map`` over blocks (each block by the
    original rule); small LU factorisations and triangular solves in XLA (:func:`_small_rule`)."""

    def rule(axis_data, vals, dims, **params):
        small = _small_rule(prim, axis_data, vals, dims, params)
        if small is not None:
            return small
        limit = _element_block(prim, vals, dims)
        if axis_data.size <= limit or all(d is None for d in dims):
            return original(axis_data, vals, dims, **params)
        which = [i for i, d in enumerate(dims) if d is not None]
        moved = tuple(jnp.moveaxis(vals[i], dims[i], 0) for i in which)

        def one(xs):
            args = list(vals)
            for i, x in zip(which, xs):
                args[i] = x
            return prim.bind(*args, **params)

        # the largest block that divides the batch: no second copy of the call for a remainder
        size = int(axis_data.size)
        even = next(b for b in range(limit, 0, -1) if size % b == 0)
        out = lax.map(one, moved, batch_size=even)
        return out, ([0] * len(out) if prim.multiple_results else 0)

    return rule


@contextlib.contextmanager
def lapack_in_blocks(block: int | None):
    """While a chunk program is traced: every LAPACK primitive batched over more matrices than
    jaxlib would run unsplit (each call's own limit, from its shapes and kernel: one block size
    for all, the smallest, ran cheap 3 × 3 solves in needlessly small blocks) runs in blocks
    (:func:`_chunked_rule`), so that jaxlib never splits a call over the intra-op pool; the
    rest of the quantity stays one ``vmap`` over the device's points (the refilled lanes of
    :func:`rbo_jax.fast_simulate` keep all of them). ``block``: ``0``, nothing to do (the
    quantity calls no LAPACK, :func:`block_size`); else any. JAX's caches of batched
    sub-jaxprs are cleared around it, so that no program traced before or after takes the
    other's. One trace at a time (a lock): the rules are global."""
    if block == 0:
        yield
        return
    rules = batching.fancy_primitive_batchers
    with _RULES_LOCK:
        saved = {p: rules[p] for p in _lapack_primitives() if p in rules}
        _clear_batching_caches()
        try:
            for p, original in saved.items():
                rules[p] = _chunked_rule(p, original)
            yield
        finally:
            rules.update(saved)
            _clear_batching_caches()


_RULES_LOCK = threading.RLock()


def _lapack_primitives():
    from jax._src.lax import fft as fft_module
    from jax._src.lax import linalg

    found = [v for v in vars(linalg).values() if isinstance(v, jax_core.Primitive)]
    return [p for p in found if p.name in LINALG] + [fft_module.fft_p]


def _clear_batching_caches():
    for name in ("_batch_jaxpr2", "_batch_jaxpr_axes"):
        cached = getattr(batching, name, None)
        if cached is not None and hasattr(cached, "cache_clear"):
            cached.cache_clear()


def sharded(local, mesh):
    # check_vma=False: the body has no collectives, and user quantities may hold callbacks or
    # custom rules that the varying-manual-axes checker does not know.
    return jax.jit(
        jax.shard_map(
            local, mesh=mesh, in_specs=P(BATCH_AXIS), out_specs=P(BATCH_AXIS), check_vma=False
        )
    )


class Layout:
    """How a chunk is laid out on the devices: ``devices``, ``block`` (LAPACK calls in blocks of
    this many points; 0: no LAPACK call), ``batch`` (the padded chunk: a multiple of the devices
    × :data:`VECTOR`, so that every device's share is a multiple of VECTOR)."""

    def __init__(self, devices, block: int, chunk_points: int):
        self.devices = tuple(devices)
        # jaxlib splits LAPACK batches on a CPU only; a GPU's solvers run whole batches
        cpu = all(d.platform == "cpu" for d in self.devices)
        self.block = int(block) if cpu else 0
        unit = VECTOR * len(self.devices)
        self.batch = -(-int(chunk_points) // unit) * unit
        self.mesh = jax.sharding.Mesh(np.array(self.devices, dtype=object), (BATCH_AXIS,))
        self.sharding = NamedSharding(self.mesh, P(BATCH_AXIS))

    def x(self, n_names: int):
        """The argument: the chunk's points, sharded over the devices."""
        dtype = jnp.result_type(float)
        return jax.ShapeDtypeStruct((self.batch, n_names), dtype, sharding=self.sharding)

    def local_x(self, n_names: int):
        """One device's share of the argument (what a stored program takes)."""
        dtype = jnp.result_type(float)
        return jax.ShapeDtypeStruct((self.batch // len(self.devices), n_names), dtype)


# XLA:CPU's pass that cuts a program's large loops into tasks for its intra-op threads
# (``outer_dimension_partitions`` on the fusions; its name in ``xla_disable_hlo_passes``).
PARTITION_PASS = "cpu-parallel-task-assigner"


def compile_options(devices) -> dict | None:
    """XLA's options for a chunk program over ``devices``: for several CPU devices, no loop cut
    into tasks (:data:`PARTITION_PASS` off); ``None`` (XLA's defaults) otherwise.

    XLA:CPU cuts every large loop of a program (a fusion over a device's lanes, in every step of
    a solve) into as many tasks as its intra-op pool has threads, and that pool has at least
    one thread per device (``max(cores, devices)`` in ``PjRtCpuClient``), whatever the CPU
    affinity. With one device per core every core already runs a device's share, and the tasks
    can only queue behind the other devices' work. Pinning the compiling threads to one core
    does not remove the cuts (``outer_dimension_partitions`` of 2 in the 2-device programs,
    pinned or not); it only makes XLA compile on one thread. The cuts are left out so that a
    machine of many cores does not cut every fusion of every device in as many tasks as it has
    cores; on 2 cores the run times were the same without them (benchmarks/README.md,
    History). One device keeps the cuts: there they are XLA's way of using the cores."""
    cpu = all(d.platform == "cpu" for d in devices)
    if len(devices) < 2 or not cpu:
        return None
    return {"xla_disable_hlo_passes": PARTITION_PASS}


def compile_program(traced, layout: Layout, options: dict | None = None):
    """Lower and compile a traced chunk program of ``layout``: lowered with LAPACK in blocks
    too, compiled with :func:`compile_options` and ``options``.

    Some primitives trace their batched implementation only when they are lowered: lineax's
    linear solve keeps the solver's ``lu_solve`` inside its primitive until then, so that the
    program's jaxpr holds no ``triangular_solve`` and the batching of tracing time never saw
    it. Lowered outside :func:`lapack_in_blocks`, a Newton stability map's chunk of 65,536 points
    on 2 devices held two ``lapack_dtrsm_ffi`` calls of 32,768 matrices each, which jaxlib split
    over the intra-op pool: both devices' threads waited there for good (issue 31; 16,384-point
    chunks stayed just below jaxlib's split). One device did not wait so (that chunk on one
    device ended, pinned to one core and on two), and lowering under the rules slowed its warm
    first answer (the Newton map of ``latency.py``: benchmarks/README.md, History), so a
    program for one device is lowered as it is."""
    block = layout.block if len(layout.devices) > 1 else 0
    with lapack_in_blocks(block):
        lowered = traced.lower()
    return lowered.compile({**(compile_options(layout.devices) or {}), **(options or {})} or None)


def deal(block: np.ndarray, n_devices: int) -> np.ndarray:
    """The rows of ``block`` dealt to the devices like cards: device d's share (rows d·s … (d+1)·s
    of the result, s = rows / devices) holds rows d, d + D, d + 2D, … of ``block``. Neighbouring
    points of a grid cost alike (a region of unstable motion takes many more steps), so
    contiguous shares left one device waiting for the other at every chunk; dealt shares cost
    the same on average. :func:`undeal` puts the outputs back in order."""
    if n_devices == 1:
        return block
    rows = block.shape[0]
    return (
        block.reshape(rows // n_devices, n_devices, *block.shape[1:])
        .swapaxes(0, 1)
        .reshape(block.shape)
    )


def undeal(values: np.ndarray, n_devices: int) -> np.ndarray:
    """The inverse of :func:`deal` on an output with the points first."""
    if n_devices == 1:
        return values
    rows = values.shape[0]
    return (
        values.reshape(n_devices, rows // n_devices, *values.shape[1:])
        .swapaxes(0, 1)
        .reshape(values.shape)
    )


def undeal_shards(x, n_devices: int) -> np.ndarray:
    """``undeal(np.asarray(x), n_devices)`` of a program's output ``x`` sharded by rows over
    the devices (:func:`deal`'s shares), read from each device's shard: one copy into the
    host array instead of two (``np.asarray`` of a sharded array concatenates the shards,
    then :func:`undeal` reorders them)."""
    shards = sorted(x.addressable_shards, key=lambda s: s.index[0].start or 0)
    if n_devices == 1 or len(shards) != n_devices:
        return undeal(np.asarray(x), n_devices)
    parts = [np.asarray(s.data) for s in shards]
    rows = parts[0].shape[0]
    out = np.empty((rows * n_devices, *parts[0].shape[1:]), parts[0].dtype)
    dealt = out.reshape(rows, n_devices, *parts[0].shape[1:])  # a view: out is contiguous
    for d, part in enumerate(parts):
        dealt[:, d] = part
    return out


def trace_point(point, n: int):
    """One point's closed jaxpr and output tree: ``point(x)`` of a ``(n,)`` vector. Traced with
    LAPACK in blocks too: a ``vmap`` inside the point (e.g. the spectra of a scan of loads in
    :func:`rbo_jax.lattice.critical_load`) would otherwise hold a batched call that jaxlib
    splits over the intra-op pool, which waits forever when every pool thread is a device."""
    dtype = jnp.result_type(float)
    with lapack_in_blocks(None):
        closed, shape = jax.make_jaxpr(point, return_shape=True)(jax.ShapeDtypeStruct((n,), dtype))
    return closed, jax.tree_util.tree_structure(shape)


def point_layout(point, n: int, devices, points: int):
    """``(local, layout)``: ``point`` traced once (:func:`trace_point`), as the per-device function
    (:func:`local_function`) of a chunk of at least ``points`` points laid out on ``devices``."""
    closed, out_tree = trace_point(point, n)
    return local_function(closed, out_tree), Layout(devices, block_size(closed.jaxpr), points)


def point_program(point, n: int, devices, points: int):
    """``(traced program, layout)``: ``point`` over a ``(layout.batch, n)`` array of at least
    ``points`` points, sharded over ``devices``."""
    local, layout = point_layout(point, n, devices, points)
    with lapack_in_blocks(layout.block):
        return sharded(local, layout.mesh).trace(layout.x(n)), layout


def map_points(fn, points: dict, devices=None):
    """``fn(**point)`` at every point of ``points`` (``{name: 1-D array}``, equal lengths),
    spread over the local devices (all by default): its outputs as NumPy arrays with the
    points first. For concrete inputs; under a transformation use ``jax.vmap``."""
    names = tuple(points)
    x = np.stack([np.asarray(points[k], float) for k in names], axis=1)
    devices = tuple(jax.local_devices()) if devices is None else tuple(devices)

    def point(v):
        return fn(**{k: v[i] for i, k in enumerate(names)})

    traced, layout = point_program(point, len(names), devices, len(x))
    block = np.empty((layout.batch, len(names)))
    block[:] = x[0]
    block[: len(x)] = x
    compiled = compile_program(traced, layout)
    n_dev = len(layout.devices)
    out = compiled(jax.device_put(deal(block, n_dev), layout.sharding))
    return jax.tree_util.tree_map(lambda a: undeal(np.asarray(a), n_dev)[: len(x)], out)
