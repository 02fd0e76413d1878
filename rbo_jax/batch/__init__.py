"""The batch engine: parameter sweeps at scale — batched, memory-bounded, sharded over devices and
hosts, resumable — and the stability maps built on it. See :mod:`rbo_jax.batch._engine`."""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._engine": ("sweep",),
        "._errors": ("SweepError",),
        "._maps": ("critical_load", "stability_map"),
        "._output": ("status_counts", "summary_line"),
        "._space": ("POINT_DIM",),
        "._store": ("open_sweep",),
        "..stability": ("STABILITY_KIND_NAMES",),  # the names of the map's kind codes
    },
)
