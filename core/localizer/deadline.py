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

import time

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


class ScanClock:
    """Scans arriving at the sequence's own rate, from the moment the clock is made: when scan k
    is due, how late a step that starts now is, and the deadline its waits must keep for the next
    scan. Whoever plays a run on the real-time clock paces it with this (``lidarloc run``,
    ``bench localize``): scans are never dropped, a step that starts after its scan's arrival is
    late and the lag is counted. A localizer that does not start at scan 0 (a branch) plays from
    its first scan's time on."""

    def __init__(self, seq, first: int = 0):
        self.seq = seq
        self.origin = seq.timestamp(first) if first > 0 else 0.0
        self.start = time.perf_counter()

    def due(self, k: int) -> float:
        """When scan k arrives (``time.perf_counter()`` seconds)."""
        return self.start + self.seq.timestamp(k) - self.origin

    def wait_due(self, k: int, stopped=None) -> float | None:
        """Sleep until scan k is due, in slices of at most 50 ms so that ``stopped()`` is seen;
        the lag in ms of a step starting now (0 if on time), or None once ``stopped()``."""
        due = self.due(k)
        while True:
            if stopped is not None and stopped():
                return None
            now = time.perf_counter()
            if now >= due:
                return (now - due) * 1000.0
            # sleep, not an Event's wait(): a Ctrl-C handler that sets the caller's stop flag on
            # this same thread would deadlock on the Event's lock if it interrupted wait()
            time.sleep(min(due - now, 0.05))

    def deadline(self, k: int, tail_s: float = 0.0) -> float | None:
        """By when scan k's step must end for scan k + 1 to start on time, less ``tail_s`` (the
        caller's own work after a step); None after the last scan."""
        if k + 1 >= len(self.seq):
            return None
        return self.due(k + 1) - tail_s
