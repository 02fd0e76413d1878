"""A progress bar for the host loops that can take long (continuations, fits, posteriors):
tqdm's where one is asked for, else one that does nothing; either closes on leaving a ``with``
block."""

from __future__ import annotations

__all__ = ["progress_bar"]


class _NoBar:
    """The bar that is not shown."""

    def update(self, n=1):
        pass

    def set_postfix(self, **kwargs):
        pass

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def progress_bar(progress: bool, total: int, desc: str, unit: str = "point"):
    """A tqdm bar of ``total`` ``unit`` named ``desc`` (``progress``), or one that does nothing."""
    if not progress:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit)
