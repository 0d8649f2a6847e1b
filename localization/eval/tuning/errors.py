"""The tuner's errors: each message is one line saying what is wrong."""
from __future__ import annotations


class TuneError(RuntimeError):
    """A tuning run that cannot start: the message is one line saying what is wrong."""


class SpaceError(TuneError):
    """A search space file that cannot be used (unreadable, unknown parameter, bad range)."""
