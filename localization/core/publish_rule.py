"""The publish rule: every output stream goes forward in time.

An estimate stamped t may follow the last one on its stream, stamped ``last``, when

    t > last                        NEWER     the stream moves on
    t < last - time_jump            RESTART   the data's clock went back (a bag played again, a looped
                                              recording): the stream starts again from t
    otherwise                       SAME      (t == last) or OLDER: not published

The node applies one rule per output stream (/pf/pose/odom with TF, /pf/pose): a message cannot be
taken back, so SAME is dropped (TF would report TF_REPEATED_DATA). The feed loop (``eval/feed.py``)
applies it to the estimates it logs as published; a log can keep the newer of two estimates of
one instant, so there SAME replaces the last entry. The verdict is returned as a value; the rule
only remembers ``last``. Not thread safe: a caller that publishes from two threads holds a lock
around ``admit`` and the publishing.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass

TIME_JUMP = 1.0  # s: a stamp this far behind the last one is a clock that went back, not a late output


class Verdict(enum.Enum):
    NEWER = "newer"
    RESTART = "restart"
    SAME = "same"
    OLDER = "older"

    @property
    def published(self) -> bool:
        """Whether the estimate goes out (NEWER or RESTART)."""
        return self in (Verdict.NEWER, Verdict.RESTART)


@dataclass
class ForwardInTime:
    """One output stream's rule (module docstring); ``last`` is the stamp of its newest output."""

    time_jump: float = TIME_JUMP
    last: float = -math.inf

    def judge(self, t: float) -> Verdict:
        """The verdict for an estimate stamped ``t``, without changing the stream."""
        if t > self.last:
            return Verdict.NEWER
        if t < self.last - self.time_jump:
            return Verdict.RESTART
        return Verdict.SAME if t == self.last else Verdict.OLDER

    def admit(self, t: float) -> Verdict:
        """The verdict for ``t``; a published one (NEWER, RESTART) becomes the stream's ``last``."""
        verdict = self.judge(t)
        if verdict.published:
            self.last = t
        return verdict

    def reset(self) -> None:
        """A new run: the next estimate is published whatever its stamp."""
        self.last = -math.inf
