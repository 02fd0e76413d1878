"""Processes of a multi-host sweep (:func:`jax.distributed`): barriers, failure votes and the
gathering of an in-memory result.

After ``jax.distributed.initialize(...)`` every process takes chunks (to a store: one at a time
from a shared counter, so that no process idles while chunks remain; in memory: round robin,
the layout of the gathering), computes them on its local devices independently (no lock-step
between hosts) and writes them to its own chunks of the store (which must then be on a file
system all hosts see); without
a store the results are gathered with :func:`jax.experimental.multihost_utils.process_allgather`
(on CPU through the gloo collectives). Process 0 creates the store.

**A lost process** (killed, its host gone) does not stop a sweep to a store: after their shares
the processes meet at :meth:`Hosts.live` — the coordination service's ``get_live_nodes``, a
barrier that returns when every process still sending heartbeats has arrived (a process
silent for the heartbeat timeout of ``jax.distributed.initialize`` counts as lost) — and
process 0 computes the chunks of the lost processes that the store is still missing, then
finalizes it. That needs the coordination service to survive the loss of a task:
``jax.config.update("jax_enable_recoverability", True)`` before ``jax.distributed.initialize``
(``rbo-jax sweep --coordinator`` sets it); without it JAX's service ends every process when one
is lost. The loss of process 0, which runs the service, ends the others in any case: what they
wrote is kept, and ``resume=True`` finishes the sweep. Failures (an exception in a process) are
reported through the service's key-value store, not a collective, so that a lost process does
not turn them into a second error.

**Said in words.** Each process puts its pid and host name in the key-value store when a sweep
starts and logs those of the others (logger ``rbo_jax.sweep``, level INFO: the CLI reads process
0's there when process 0 is lost). Process 0 prints one line on stderr when it takes over, e.g.
``rbo_jax.sweep: process 1 of 2 (pid 5374 on host node02) was lost (no heartbeat); process 0
computes the 3 chunks it left: 4, 7-8`` (:func:`lost_line`).
"""

from __future__ import annotations

import itertools
import logging
import os
import socket

import jax
import numpy as np

from ._output import OutputSpec
from ._space import Space
from .progress import chunk_ranges

log = logging.getLogger("rbo_jax.sweep")

#: The key of a process's "pid host" in the coordination service's key-value store.
_WHO = "rbo_jax/process/{}"


def lost_line(lost: list[int], count: int, left: list[int], who: dict[int, str]) -> str:
    """The one line that process 0 prints when it takes over the chunks of lost processes."""
    named = [f"{i}" + (f" ({who[i]})" if i in who else "") for i in lost]
    one = len(lost) == 1
    what = (
        f"process {lost[0]} of {count}" + (f" ({who[lost[0]]})" if lost[0] in who else "") + " was"
        if one
        else f"processes {', '.join(named)} of {count} were"
    )
    its = "it" if one else "they"
    took = (
        f"process 0 computes the {len(left)} chunk{'s' if len(left) != 1 else ''} {its} "
        f"left: {chunk_ranges(left)}"
        if left
        else f"{its} left no chunk to compute"
    )
    return f"rbo_jax.sweep: {what} lost (no heartbeat); {took}"


class Hosts:
    """This process's index and the process count, with the meeting points of a sweep."""

    _sweeps = itertools.count()  # a sweep's number: the same on every process (same calls)

    def __init__(self):
        self.index, self.count = jax.process_index(), jax.process_count()
        self.prefix = f"rbo_jax/sweep/{next(Hosts._sweeps)}" if self.count > 1 else ""
        self.who: dict[int, str] = {}  # "pid N on host H" of the processes, by index
        client = self._client() if self.count > 1 else None
        if client is not None:
            client.key_value_set(
                _WHO.format(self.index),
                f"{os.getpid()} {socket.gethostname()}",
                allow_overwrite=True,
            )

    @staticmethod
    def _client():
        """JAX's coordination-service client of this process (None: not distributed)."""
        from jax._src import distributed

        return distributed.global_state.client

    def introduce(self):
        """Read (and log) the pid and host of every process: after a meeting of all of them,
        each having put its own in the key-value store on creating its :class:`Hosts`."""
        client = self._client() if self.count > 1 else None
        if client is None:
            return
        for i in range(self.count):
            try:
                pid, host = client.key_value_try_get(_WHO.format(i)).split(" ", 1)
            except (jax.errors.JaxRuntimeError, ValueError):  # NOT_FOUND: not said
                continue
            self.who[i] = f"pid {pid} on host {host}"
            log.info("process %d of %d is pid %s on host %s", i, self.count, pid, host)

    def live(self, name: str) -> list[int]:
        """Meet the other processes; the indices of the processes that are alive. Returns when
        every live process has arrived; a process that stopped sending heartbeats (lost) is
        not waited for (it is detected after the service's heartbeat timeout)."""
        if self.count == 1:
            return [0]
        client = self._client()
        if client is None or not hasattr(client, "get_live_nodes"):  # an older jaxlib
            self.barrier(name)
            return list(range(self.count))
        return sorted(int(i) for i in client.get_live_nodes(list(range(self.count))))

    def report(self, failed: bool):
        """Tell process 0, through the key-value store, whether this process's share failed."""
        if self.count > 1:
            self._client().key_value_set(
                f"{self.prefix}/failed/{self.index}", str(int(failed)), allow_overwrite=True
            )

    def failed(self, alive: list[int]) -> list[int]:
        """The live processes that reported a failure (after :meth:`report` and :meth:`live`)."""
        if self.count == 1:
            return []
        client = self._client()
        out = []
        for i in alive:
            try:
                if client.key_value_try_get(f"{self.prefix}/failed/{i}") == "1":
                    out.append(i)
            except jax.errors.JaxRuntimeError:  # NOT_FOUND: it failed before it could report
                out.append(i)
        return out

    def barrier(self, name: str):
        if self.count > 1:
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices(f"rbo_jax.sweep:{name}")

    def any_failed(self, failed: bool) -> list[int]:
        """All processes meet here; the indices of those that report a failure."""
        if self.count == 1:
            return [0] if failed else []
        from jax.experimental import multihost_utils

        flags = np.asarray(multihost_utils.process_allgather(np.int32(failed)))
        return [int(i) for i in np.flatnonzero(flags)]

    def share(self, chunk_ids: list[int]) -> list[int]:
        """This process's chunks (round robin)."""
        return chunk_ids[self.index :: self.count]

    def take(self, chunk_ids: list[int]):
        """This process's chunks of a sweep to a store, taken one at a time from a counter
        that the processes share (the coordination service's ``key_value_increment``): a
        process that is faster, or has less to compile, takes more, and none idles while
        chunks remain (round robin left one host idle while the other had half its share to
        go). Without the service's client: round robin."""
        client = self._client() if self.count > 1 else None
        if client is None or not hasattr(client, "key_value_increment"):
            yield from self.share(chunk_ids)
            return
        while (i := client.key_value_increment(f"{self.prefix}/next", 1) - 1) < len(chunk_ids):
            yield chunk_ids[i]

    def gather(self, arrays: dict, kept: dict, missing: list[int], space: Space, spec: OutputSpec):
        """Assemble into ``arrays`` the chunks computed by every process (``kept`` holds this
        process's results by chunk id)."""
        from jax.experimental import multihost_utils

        per_process = -(-len(missing) // self.count)
        names = [v.name for v in spec.variables] + ["status"]
        shapes = {v.name: v.shape for v in spec.variables} | {"status": ()}
        dtypes = {v.name: v.dtype for v in spec.variables} | {"status": "int8"}
        local = {}
        for name in names:
            buf = np.zeros((per_process,) + space.chunk_shape + shapes[name], dtypes[name])
            for j, cid in enumerate(self.share(missing)):
                r = kept[cid][name]
                buf[(j,) + tuple(slice(0, s) for s in r.shape)] = r
            local[name] = buf
        everyone = multihost_utils.process_allgather(local)
        for p in range(self.count):
            for j, cid in enumerate(missing[p :: self.count]):
                slices = space.slices(cid)
                block = tuple(slice(0, sl.stop - sl.start) for sl in slices)
                for name in names:
                    arrays[name][slices] = np.asarray(everyone[name])[(p, j) + block]
