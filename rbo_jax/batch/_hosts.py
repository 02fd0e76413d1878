"""Processes of a multi-host sweep (:func:`jax.distributed`): barriers, failure votes and the
gathering of an in-memory result.

After ``jax.distributed.initialize(...)`` every process takes its share of the chunks (round
robin), computes them on its local devices independently (no lock-step between hosts) and writes
them to its own chunks of the store (which must then be on a file system all hosts see); without
a store the results are gathered with :func:`jax.experimental.multihost_utils.process_allgather`
(on CPU through the gloo collectives). Process 0 creates the store.
"""

from __future__ import annotations

import jax
import numpy as np

from ._output import OutputSpec
from ._space import Space


class Hosts:
    """This process's index and the process count, with the meeting points of a sweep."""

    def __init__(self):
        self.index, self.count = jax.process_index(), jax.process_count()

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

    def gather(self, arrays: dict, kept: dict, missing: list[int], space: Space,
               spec: OutputSpec):
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
