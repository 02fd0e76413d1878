"""Memory needs of a command, estimated before it computes anything.

A request larger than the machine (``--samples 1000000000``, a grid of 10^13 points) would
otherwise run until the kernel kills the process, silently, minutes later. Each command estimates
its peak from its sizes (samples, bodies, grid points) and refuses, with exit status 2, an
estimate above half the physical memory (the share :func:`rbo_jax.sweep` allows an in-memory
result), naming the number, the estimate, the machine's memory and the way out.

The bytes per unit below are about twice the measured peak (the peak resident memory of the
command at two sizes, the difference divided by the difference of the sizes: benchmarks/README.md,
History): they cover the device arrays of the solve, their host copies, the xarray Dataset and
the file writers, with room for other versions of the libraries.
"""

from __future__ import annotations

import os

from ._common import Failure

SHARE = 0.5

# One body, per sample
BYTES_PER_SAMPLE = 400
# A lattice or a rod, per sample and body; per body (the solver's stages, the couplings, the
# compiled program's buffers)
BYTES_PER_BODY_SAMPLE = 400
BYTES_PER_BODY = 4000
# A stability map, per grid point
BYTES_PER_MAP_POINT = 1000
# A fit, per sample and fitted direction (the residuals, their Jacobian, the solver's tangents)
BYTES_PER_FIT_SAMPLE = 500


def physical_memory() -> int | None:
    """The machine's physical memory in bytes (None where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(need: float, what: str, way_out: str) -> None:
    """Refuse (exit status 2) a request whose estimated peak ``need`` (bytes) exceeds
    :data:`SHARE` of the physical memory; ``what`` names the request (``--samples 1000000000``),
    ``way_out`` says what to do instead."""
    total = physical_memory()
    if total is None or need <= SHARE * total:
        return
    raise Failure(
        f"{what}: needs about {need / 2**30:,.1f} GiB of memory, more than "
        f"{SHARE:.0%} of this machine's {total / 2**30:.1f} GiB; {way_out}."
    )
