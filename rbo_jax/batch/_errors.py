"""The error of the batch engine."""


class SweepError(RuntimeError):
    """A sweep could not be completed (a chunk raised, a store does not match, ...)."""
