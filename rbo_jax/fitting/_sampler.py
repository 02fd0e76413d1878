r"""The NUTS chains of :func:`rbo_jax.posterior` (BlackJAX): warmup and draws as one scan of one
transition, the chains split over the local devices, the compiled programs cached.

**One program.** Stan's window adaptation (diagonal mass matrix, dual-averaging step size) and
the draws are one ``lax.scan`` of one NUTS transition: the transitions before ``num_warmup``
adapt, the later ones use the adapted step size and mass matrix, so the log density's gradient
is compiled once. The run is cut into ``progress_chunks`` calls of that program (a progress bar
moves between them).

**Chains** are split over the local devices (``shard_map``, each device a ``vmap`` or a
``lax.map`` of its chains) where the device count divides their number, else batched on one
device.

**Cache.** The density is ``density(operands, z)``: the arrays (the model's, the data's, the
whitening) are arguments of the compiled program, not constants in it, and the program is kept
under a key of everything static. A second data set of the same shapes (a new run of the rig, a
calibration over synthetic data sets) compiles nothing.
"""

from __future__ import annotations

import math
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["run_chains"]


def _adaptation():
    """Stan's window adaptation as BlackJAX's ``(init, update, final)`` (diagonal mass matrix,
    target acceptance 0.8) and its schedule."""
    from blackjax.adaptation import window_adaptation

    with warnings.catch_warnings():  # deprecated in BlackJAX 1.7 for its own loop, kept here:
        warnings.simplefilter("ignore", DeprecationWarning)  # that loop compiles twice
        return window_adaptation.base(True, 0.8), window_adaptation.build_schedule


def _chain(density, num_warmup, chunk):
    """One chain's ``start(z0, operands)`` and ``advance(key, carry, first, operands)``:
    ``chunk`` NUTS transitions of ``density(operands, .)`` from the transition ``first`` on. The
    warmup's transitions (index < ``num_warmup``) adapt the step size and diagonal inverse mass
    matrix (Stan's windows); the later ones use the adapted values. Warmup and draws share one
    program, so the gradient is compiled once."""
    import blackjax

    (init, update, final), build_schedule = _adaptation()
    kernel = blackjax.nuts.build_kernel()
    schedule = np.zeros((num_warmup + chunk + 1, 2), dtype=np.int32)
    if num_warmup:
        schedule[:num_warmup] = np.asarray(build_schedule(num_warmup), dtype=np.int32)
    schedule = jnp.asarray(schedule)

    def start(z0, operands):
        return blackjax.nuts.init(z0, lambda z: density(operands, z)), init(z0, 1.0)

    def transition(carry, index, key, log_density):
        state, adaptation = carry
        warm = index < num_warmup
        step_size, imm = final(adaptation)
        step_size = jnp.where(warm, adaptation.step_size, step_size)
        imm = jnp.where(warm, adaptation.inverse_mass_matrix, imm)
        state, info = kernel(jax.random.fold_in(key, index), state, log_density, step_size, imm)
        stage = schedule[jnp.minimum(index, num_warmup)]
        adapted = update(adaptation, (stage[0], stage[1] > 0), state.position, info.acceptance_rate)
        adaptation = jax.tree.map(lambda a, b: jnp.where(warm, a, b), adapted, adaptation)
        stats = {
            "diverging": info.is_divergent,
            "acceptance_rate": info.acceptance_rate,
            "tree_depth": info.num_trajectory_expansions,
            "n_steps": info.num_integration_steps,
            "energy": info.energy,
            "lp": state.logdensity,
            "step_size": step_size,
        }
        return (state, adaptation), (state.position, stats)

    def advance(key, carry, first, operands):
        def body(carry, index):
            return transition(carry, index, key, lambda z: density(operands, z))

        return jax.lax.scan(body, carry, first + jnp.arange(chunk))

    return start, advance


def _uses_devices(chains, chain_method) -> bool:
    n_dev = jax.local_device_count()
    if chain_method == "pmap" and chains % n_dev:
        raise ValueError(f"chain_method='pmap' needs chains divisible by the {n_dev} devices.")
    return n_dev > 1 and (
        chain_method == "pmap" or (chain_method == "auto" and chains % n_dev == 0)
    )


def _over_chains(f, sequential):
    """``f(*xs, shared)`` over the leading axis of ``xs``, ``shared`` whole: ``vmap``, or
    ``lax.map`` (one chain after the other) where batching costs more than it saves
    (fast_simulate's forward-mode Jacobian: measured 30x slower vmapped over 2 chains than one
    chain)."""
    if not sequential:
        return lambda *xs, shared: jax.vmap(lambda *ys: f(*ys, shared))(*xs)
    return lambda *xs, shared: jax.lax.map(lambda t: f(*t, shared), xs)


def _lowered(f, args, shared, use_devices, sequential):
    """``f(*args, shared)`` over the leading (chain) axis of ``args`` (arrays or
    ``jax.ShapeDtypeStruct``s), lowered: ``(lowered, out_shapes, finish)``, ``finish(compiled)``
    giving ``run(args, shared)``; ``shared`` is an argument too (not baked in). Split over the
    local devices (``shard_map`` over a batch of one chain's traced program, ``shared``
    replicated: tracing first keeps equinox's checkpointed loops out of the manual axes) or on
    one device."""
    mapped = _over_chains(f, sequential)
    if not use_devices:
        lowered = jax.jit(lambda args, shared: mapped(*args, shared=shared)).lower(args, shared)
        return lowered, lowered.out_info, lambda compiled: compiled
    from jax.extend.core import jaxpr_as_fun
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    mesh = Mesh(np.asarray(jax.local_devices()), ("chain",))
    split, whole = NamedSharding(mesh, P("chain")), NamedSharding(mesh, P())
    flat, tree = jax.tree.flatten(args)
    sflat, stree = jax.tree.flatten(shared)
    k = len(flat)

    def traced(*xs):
        return f(*jax.tree.unflatten(tree, xs[:k]), jax.tree.unflatten(stree, xs[k:]))

    spec = [jax.ShapeDtypeStruct(np.shape(x)[1:], jnp.result_type(x)) for x in flat]
    spec += [jax.ShapeDtypeStruct(np.shape(x), jnp.result_type(x)) for x in sflat]
    closed, shape = jax.make_jaxpr(traced, return_shape=True)(*spec)

    def one_chain(*xs):  # a chain's arguments, then the shared ones as one tuple
        return tuple(jaxpr_as_fun(closed)(*xs[:-1], *xs[-1]))

    per_chain = _over_chains(one_chain, sequential)
    program = jax.shard_map(
        lambda *xs: per_chain(*xs[:k], shared=xs[k:]),
        mesh=mesh,
        in_specs=(P("chain"),) * k + (P(),) * len(sflat),
        out_specs=P("chain"),
        check_vma=False,
    )

    def put(x, sharding):
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)
        return jax.device_put(x, sharding)

    def place(args, shared):
        return [put(x, split) for x in jax.tree.leaves(args)] + [
            put(x, whole) for x in jax.tree.leaves(shared)
        ]

    lowered = jax.jit(program).lower(*place(args, shared))
    out_tree = jax.tree.structure(shape)

    def finish(compiled):
        return lambda args, shared: jax.tree.unflatten(out_tree, compiled(*place(args, shared)))

    return lowered, jax.tree.unflatten(out_tree, list(lowered.out_info)), finish


def _compile_both(start, advance, z0, keys, first, operands, use_devices, sequential):
    """The chains' two programs (the start, the transitions), lowered one after the other (the
    transitions' from the start's output shapes) and compiled at the same time on two threads:
    each holds the log density's gradient, and XLA compiles without the GIL."""
    from concurrent.futures import ThreadPoolExecutor

    lo_start, carry, fin_start = _lowered(start, (z0,), operands, use_devices, sequential)
    lo_advance, _, fin_advance = _lowered(
        advance, (keys, carry, first), operands, use_devices, sequential
    )
    with ThreadPoolExecutor(2) as pool:
        jobs = [pool.submit(lo.compile) for lo in (lo_start, lo_advance)]
        compiled = [job.result() for job in jobs]
    return fin_start(compiled[0]), fin_advance(compiled[1])


# compiled samplers by the density's static part, the operands' shapes and the run's options:
# a second data set of the same shapes (a calibration, a new run of the rig) compiles nothing
_PROGRAMS: dict = {}
_PROGRAMS_KEPT = 8


def run_chains(density, operands, key, dim, opts, bar):
    """Warmup and ``num_samples`` draws per chain in ``progress_chunks`` calls of one program
    (a progress bar moves between them; the programs are cached under ``key`` when it is not
    None); returns the draws of z (chains, draws, dim), the sampler's statistics and the
    seconds spent compiling and running."""
    chains, num_warmup, num_samples = opts["chains"], opts["num_warmup"], opts["num_samples"]
    total = num_warmup + num_samples
    n_chunks = min(opts["progress_chunks"], total)
    chunk = math.ceil(total / n_chunks)
    use_devices = _uses_devices(chains, opts["chain_method"])
    sequential = opts["sequential"]
    rng = jax.random.PRNGKey(opts["seed"])
    keys = jax.random.split(rng, chains)
    z0 = jax.random.normal(jax.random.fold_in(rng, 1), (chains, dim))
    first = jnp.zeros(chains, dtype=jnp.int32)
    if key is not None:
        key = (key, chains, num_warmup, chunk, use_devices, sequential)
    tic = time.perf_counter()
    cached = _PROGRAMS.get(key) if key is not None else None
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        if cached is None:  # BlackJAX mixes bool and int
            start, advance = _compile_both(
                *_chain(density, num_warmup, chunk), z0, keys, first, operands, use_devices,
                sequential,
            )  # fmt: skip
            if key is not None:
                if len(_PROGRAMS) >= _PROGRAMS_KEPT:
                    _PROGRAMS.pop(next(iter(_PROGRAMS)))
                _PROGRAMS[key] = (start, advance)
        else:
            start, advance = cached
        carry = start((z0,), operands)
    times = {"compile": time.perf_counter() - tic, "reused": cached is not None}
    times["chains"] = ("shard_map + " if use_devices else "") + ("map" if sequential else "vmap")
    tic = time.perf_counter()
    draws, stats = [], []
    for i in range(n_chunks):
        carry, (z, st) = advance((keys, carry, first + i * chunk), operands)
        draws.append(np.asarray(z))
        stats.append(jax.tree.map(np.asarray, st))
        if bar is not None:
            bar.update(min(chunk, total - i * chunk))
    times["sampling"] = time.perf_counter() - tic
    z = np.concatenate(draws, axis=1)[:, num_warmup:total]
    stats = {k: np.concatenate([s[k] for s in stats], 1)[:, num_warmup:total] for k in stats[0]}
    return z, stats, times
