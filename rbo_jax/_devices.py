"""Every core by default: one XLA CPU device per core this process may use.

JAX gives a CPU one device, and XLA spreads a program over the cores with its intra-op threads.
For the batch work of this package (sweeps, stability maps, vmapped continuation, large
lattices: many independent lanes in adaptive ``while_loop``\\ s) that is the slowest way to use a
multi-core machine, slower than one pinned core (issue 31; benchmarks/README.md, the "cores"
rows; jax-ml/jax#29499 reports the same). One device per core, each running its share of a
chunk under ``shard_map`` (:mod:`rbo_jax.batch._program`), uses them all.

So ``import rbo_jax`` asks JAX for one CPU device per core in the process's CPU affinity
(``os.sched_getaffinity``: ``taskset -c 0`` gives one), before JAX's backend starts, unless

- the user chose already: ``JAX_NUM_CPU_DEVICES``, ``jax.config.update("jax_num_cpu_devices",
  n)`` before the import, or ``--xla_force_host_platform_device_count`` in ``XLA_FLAGS``;
- ``RBO_JAX_CPU_DEVICES`` says otherwise: ``off`` (or ``0``) leaves JAX's default, a number ``n``
  asks for ``n`` devices;
- JAX's backend has started already (a computation before ``import rbo_jax``): then nothing can
  change it, and the first sweep on fewer devices than cores says so once
  (:func:`warn_if_few_devices`).

Nothing else changes: a plain ``jax.jit`` call runs on the first device with XLA's threads as
before; only the batch engine, the sharded lattice and a ``jax.vmap`` of
:func:`rbo_jax.fast_simulate` whose inputs the user placed on a ``NamedSharding`` over the
devices spread work over them. On a GPU
machine the accelerators are the devices and this setting does not matter. ``devices=`` (and
``--devices``) still chooses fewer.
"""

from __future__ import annotations

import os
import warnings

import jax

ENV = "RBO_JAX_CPU_DEVICES"
_OFF = {"off", "0", "no", "false"}
_chosen: int | None = None  # the count this module asked for, if any
_warned = False


def cores() -> int:
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` where the
    system has no affinity)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this private function: assume
        # it has started, and change nothing
        return True


def user_choice() -> str | None:
    """How the user chose the number of CPU devices, or ``None`` if they did not."""
    if os.environ.get("JAX_NUM_CPU_DEVICES"):
        return "JAX_NUM_CPU_DEVICES"
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return "XLA_FLAGS"
    if getattr(jax.config, "jax_num_cpu_devices", -1) not in (-1, None) and _chosen is None:
        return "jax_num_cpu_devices"
    return None


def requested() -> int | None:
    """The device count ``RBO_JAX_CPU_DEVICES`` asks for: ``None`` for off, else a number
    (every core when unset). Raises ``ValueError`` naming the variable for anything else."""
    value = os.environ.get(ENV, "").strip().lower()
    if value in _OFF:
        return None
    if not value:
        return cores()
    try:
        n = int(value)
    except ValueError:
        raise ValueError(
            f"{ENV}={value!r}: expected a number of CPU devices, or 'off' (JAX's default)."
        ) from None
    if n < 0:
        raise ValueError(f"{ENV}={value!r}: the number of CPU devices must be >= 0.")
    return n or None


def use_every_core() -> int | None:
    """At ``import rbo_jax``: ask JAX for one CPU device per core (see the module docstring).
    Returns the count asked for, ``None`` if nothing was set."""
    global _chosen
    n = requested()
    if n is None or user_choice() is not None or _backend_started():
        return None
    if getattr(jax.config, "jax_num_cpu_devices", None) is None:  # a JAX without the option
        return None
    jax.config.update("jax_num_cpu_devices", n)
    _chosen = n
    return n


def warn_if_few_devices(devices) -> None:
    """Once per process: a sweep over fewer CPU devices than cores, although the user asked for
    neither (JAX started before ``import rbo_jax``), says what to do. Fewer devices that the user
    asked for (``RBO_JAX_CPU_DEVICES=n``, JAX's own settings) are not warned about."""
    global _warned
    if _warned or devices is not None:
        return
    local = jax.local_devices()
    n = cores()
    if local[0].platform != "cpu" or user_choice() is not None:
        return
    want = requested()  # RBO_JAX_CPU_DEVICES's count (every core when unset)
    if want is None or len(local) >= min(n, want):
        return
    _warned = True
    warnings.warn(
        f"rbo_jax: JAX's CPU backend started with {len(local)} device(s) before rbo_jax was "
        f"imported, so this batch runs on {len(local)} of the {n} cores it may use. Import "
        f"rbo_jax before the first JAX computation, or call "
        f"jax.config.update('jax_num_cpu_devices', {n}) before it ({ENV}=off silences this).",
        RuntimeWarning,
        stacklevel=3,
    )
