"""The batch engine: parameter sweeps at scale — batched, memory-bounded, sharded over devices and
hosts, resumable — and the stability maps built on it. See :mod:`rbo_jax.batch._engine`."""

from ._engine import sweep as sweep
from ._errors import SweepError as SweepError
from ._maps import STABILITY_KIND_NAMES as STABILITY_KIND_NAMES
from ._maps import critical_load as critical_load
from ._maps import stability_map as stability_map
from ._output import status_counts as status_counts
from ._output import summary_line as summary_line
from ._space import POINT_DIM as POINT_DIM
from ._store import open_sweep as open_sweep
