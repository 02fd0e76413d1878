r"""The one continuation loop and its step control.

From a point of a curve, ``advance(point, ds)`` predicts along the tangent by the arclength
``ds`` and corrects (a pseudo-arclength corrector: equilibria, the Hopf boundary, limit
cycles); the step grows ×1.5 (up to ``ds_max``) after a correction of at most three Newton
steps and halves after a failed one, or after a point that ``accept`` refuses without ending
the curve (a step that overshot an endpoint: the curve comes to it by halving steps); the
curve ends when the step falls below ``ds_min``, after ``max_points`` points, or when
``accept`` says why (a parameter left its bounds, an endpoint was reached). The loop is
Python around compiled corrector steps: each step's outcome decides the next.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from .._progress import progress_bar

__all__ = ["Steps", "follow", "progress_bar"]


class Steps(NamedTuple):
    """The step control: the first step ``ds``, its bounds, and how it changes."""

    ds: float
    ds_min: float
    ds_max: float
    grow: float = 1.5
    shrink: float = 0.5
    easy: int = 3  # Newton steps of an easy correction: the next step grows

    def check(self, owner: str = "continuation") -> Steps:
        if not (self.ds > 0 and self.ds_min > 0 and self.ds_max >= self.ds >= self.ds_min):
            raise ValueError(
                f"{owner}: need 0 < ds_min <= ds <= ds_max, got ds={self.ds}, "
                f"ds_min={self.ds_min}, ds_max={self.ds_max}."
            )
        return self


def follow(
    advance: Callable,
    first,
    steps: Steps,
    *,
    max_points: int,
    accept: Callable | None = None,
    progress: bool = False,
    desc: str = "continuation",
):
    """The continuation loop (module docstring). ``advance(point, ds) -> (new, newton_steps)``
    (``new`` is ``None`` where the correction failed); ``accept(points, new) -> (keep,
    reason)``: whether ``new`` joins the curve and, where the curve ends there, why; ``(False,
    None)`` refuses ``new`` as a failed correction (the step halves). Returns ``(points,
    reason)``."""
    points, reason, ds = [first], "max_points", steps.ds
    bar = progress_bar(progress, max_points, desc)
    bar.update(1)
    while len(points) < max_points:
        new, k = advance(points[-1], ds)
        if new is None:
            keep, end = False, None
        else:
            keep, end = accept(points, new) if accept is not None else (True, None)
        if not keep and end is None:  # a failed or refused step: retried shorter
            ds *= steps.shrink
            if ds < steps.ds_min:
                reason = "step size below ds_min"
                break
            continue
        if keep:
            points.append(new)
            bar.update(1)
        if end is not None:
            reason = end
            break
        ds = min(ds * steps.grow, steps.ds_max) if k <= steps.easy else ds
    bar.close()
    return points, reason
