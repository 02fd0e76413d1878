r"""Continuation: one predictor-corrector loop with one step control (:mod:`._steps`), one set
of detectors and refinements of special points (:mod:`._detectors`), and Keller's
pseudo-arclength continuation of equilibria for every model (:mod:`._equilibria`). The Hopf
boundary (:mod:`rbo_jax.bifurcation`) and the limit cycles follow their curves with the same
loop and detectors."""

from .. import _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    {  # loaded on first use
        "._steps": ("Steps", "follow", "progress_bar"),
        "._detectors": ("crossing", "parabola_vertex", "sign_changes"),
        "._equilibria": ("follow_equilibria",),
    },
)
