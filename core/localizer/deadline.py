"""Real time: by when a step must end so that the next scan starts on time.

Whoever paces the scans (the viewer's player, ``lidarloc run`` on the real-time clock) knows when
the next scan arrives, and how long its own work after a step takes (publishing the snapshot,
writing the recording); it hands the localizer ``step(deadline=…)``: the ``time.perf_counter()``
by which the step should be over. The step's only wait that is not work, a finished S2M match
waiting for KISS-ICP to register the scan it lands in, then waits no longer than the time left
before that deadline, less what the step does after its landing (see
:meth:`~lidarloc.core.matching.schedule.S2MScheduler.land`). Without a deadline the waits keep
their fixed bounds.

Durations are tracked as a recent high-water mark (:class:`RecentPeak`): a step's tail is short
on most scans and long on a few (a snapshot with a plot, a resampling), and the wait should leave
room for the long ones it has seen lately, not for their average.
"""

from __future__ import annotations

# How much of the time before a deadline a landing leaves untouched, beyond the measured tails:
# the scheduler's wake-up and the landing's own work (carrying the match forward, re-weighting
# the one particle it is written into).
LANDING_MARGIN_S = 0.005


class RecentPeak:
    """A recent high-water mark of a duration (s), from 0: a new sample above it becomes the
    mark; below it, the mark decays by ``decay`` toward the sample."""

    def __init__(self, decay: float = 0.05):
        self.value = 0.0
        self._decay = float(decay)

    def add(self, seconds: float) -> None:
        s = max(0.0, float(seconds))
        self.value = s if s >= self.value else self.value - self._decay * (self.value - s)
