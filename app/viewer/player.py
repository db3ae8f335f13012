"""Playback: one thread that calls ``localizer.step()`` when it is due.

The viewer's controls only flip flags here (play, pause, step, speed, clock) and return at once;
the thread does the blocking work, so a GUI callback never waits for a scan to be processed.

Pacing. In the "replay" clock the next scan is due one speed-interval after the previous one
started (or immediately at "max" speed). In the "realtime" clock scan k is due when as much wall
time has passed as the sequence's timestamps say since the scan playback (re)started from, so a
10 Hz drive plays at 10 Hz; a localizer slower than that simply runs behind (scans are not dropped:
which scans to skip is the localizer's business, not the player's). A step that starts more than
one scan period after its scan arrived is *late* (the next scan was already there): the player
counts them (:meth:`Player.take_counts`), which is what a long run in a loop reports per loop.

Why a scan was late. With ``$LIDARLOC_TRACE_LATE=FILE`` set, the player writes every thread's
Python stack into FILE at the very moment the next scan becomes late (its start more than one
period after its arrival), then a line naming that scan, its lag and the time (UTC) once it
starts. The dump comes from :mod:`faulthandler`'s own C thread, which does not wait for the GIL:
a stall inside an extension that holds it still shows the Python line that called in. A debugging
aid (a thread started per scan), off unless the variable is set.
"""

from __future__ import annotations

import faulthandler
import os
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from typing import Protocol

import numpy as np

from ...core.errors import LidarlocError
from ...core.localizer.deadline import RecentPeak
from ...core.snapshot import Snapshot
from .faults import block_of, describe
from .style import RATE_WINDOW_S

CLOCKS = ("replay", "realtime")
TRACE_LATE_ENV = "LIDARLOC_TRACE_LATE"


class LateTracer:
    """Every thread's stack into ``path`` when a real-time scan becomes late (see the module's
    docstring): :meth:`arm` at each step's start with the seconds until the next scan would be
    late; a step that starts in time re-arms it (which cancels the previous timer)."""

    def __init__(self, path: str):
        self._file = open(path, "a", buffering=1)  # open as long as the player lives
        self.armed_for: int | None = None  # the scan whose lateness the armed timer catches

    def arm(self, scan: int, seconds: float) -> None:
        faulthandler.dump_traceback_later(seconds, repeat=False, file=self._file)
        self.armed_for = scan

    def cancel(self) -> None:
        if self.armed_for is not None:
            faulthandler.cancel_dump_traceback_later()
            self.armed_for = None

    def late(self, scan: int, lag: float) -> None:
        """The line that says which scan the stacks above made late (or that this one is late
        only because the player is still catching up: no new dump)."""
        what = "the stacks above" if scan == self.armed_for else "catching up, no new stall"
        # the UTC time lets a trace be laid beside other logs (the soak's samples, the system's)
        at = time.strftime("%H:%M:%S", time.gmtime())
        self._file.write(f"^ {what}: scan {scan} started {lag:.3f} s after it arrived (late, {at} UTC)\n")

    def close(self) -> None:
        self.cancel()
        self._file.close()

    @classmethod
    def from_env(cls) -> LateTracer | None:
        path = os.environ.get(TRACE_LATE_ENV)
        if not path:
            return None
        try:
            return cls(path)
        except OSError as exc:
            raise LidarlocError(f"${TRACE_LATE_ENV}: cannot write {path}: {exc.strerror or exc}") from None


class _Timed(Protocol):
    @property
    def timestamps(self) -> np.ndarray: ...


class Steppable(Protocol):
    """What the player needs of a localizer: the next scan's index, its sequence's timestamps
    (for the realtime clock), whether it is done, and a step."""

    k: int

    @property
    def seq(self) -> _Timed: ...

    @property
    def done(self) -> bool: ...

    def step(self, deadline: float | None = None) -> Snapshot: ...


class Player:
    """Drives a Localizer on a background thread.

    ``on_snapshot`` is called on the player thread with every snapshot ``step()`` returns;
    ``on_error`` with a one-line message when a step fails (playback then pauses, the thread lives on);
    ``on_finished`` (optional) on the player thread when playing reached the end of the sequence.
    """

    def __init__(
        self,
        localizer: Steppable,
        on_snapshot: Callable[[Snapshot], None],
        on_error: Callable[[str], None],
        *,
        speed: float | None = 10.0,
        clock: str = "replay",
        on_finished: Callable[[], None] | None = None,
    ):
        self._loc = localizer
        self._on_snapshot = on_snapshot
        self._on_error = on_error
        self._on_finished = on_finished
        self._period: float | None = None  # the sequence's median scan interval (late scans)
        self._late = 0  # realtime steps that started over one scan period after their scan arrived
        self._max_lag = 0.0
        self._counted = 0  # steps counted since take_counts
        self._cond = threading.Condition()
        self._playing = False
        self._steps_pending = 0
        self._busy = False
        self._stopping = False
        self._speed = speed  # scans per second in replay; None = as fast as possible
        self._clock = clock
        self._anchor: tuple[float, float] | None = None  # (wall time, sequence time) realtime pacing starts from
        self._last_start: float | None = None  # wall time the previous step started (replay pacing)
        # rebase() counts up: a step in flight across a rebase belongs to the pacing before it
        self._rebases = 0
        self.steps_done = 0  # steps completed since start (any reason)
        self._finished_at: deque[float] = deque(maxlen=256)  # start times of steps finished while playing
        self._lag: float | None = None  # realtime: how late the newest step started after its scan arrived
        self._tracer = LateTracer.from_env()
        self._publishing = RecentPeak()  # what on_snapshot takes on the player thread (s)
        self._thread = threading.Thread(target=self._run, name="lidarloc-player", daemon=True)

    # ------------------------------------------------------------------ controls (any thread)
    def start(self) -> None:
        self._thread.start()

    def play(self) -> None:
        with self._cond:
            if not self._playing:
                self._playing = True
                self._anchor = None
                self._last_start = None
                self._finished_at.clear()
                self._lag = None
            self._cond.notify_all()

    def pause(self) -> None:
        with self._cond:
            self._playing = False
            self._untrace()
            self._cond.notify_all()

    def step_once(self) -> None:
        """Pause, then process exactly one more scan."""
        with self._cond:
            self._playing = False
            self._untrace()
            self._steps_pending += 1
            self._cond.notify_all()

    def set_speed(self, scans_per_second: float | None) -> None:
        if scans_per_second is not None and not scans_per_second > 0:
            raise LidarlocError(f"speed must be > 0 scans/s, got {scans_per_second}")
        with self._cond:
            self._speed = scans_per_second
            self._cond.notify_all()

    def set_clock(self, clock: str) -> None:
        if clock not in CLOCKS:
            raise LidarlocError(f"clock must be replay or realtime, got {clock!r}")
        with self._cond:
            self._clock = clock
            self._anchor = None
            self._untrace()
            self._cond.notify_all()

    def rebase(self) -> None:
        """Forget the pacing reference (after a restart or kidnap the sequence time jumps)."""
        with self._cond:
            self._anchor = None
            self._untrace()
            self._last_start = None
            self._finished_at.clear()
            self._lag = None
            self._rebases += 1
            self._cond.notify_all()

    def achieved_rate(self, window: float = RATE_WINDOW_S) -> float | None:
        """Scans per second actually processed while playing: over the steps started in the
        last ``window`` seconds, or over the last two steps when fewer started in it (a replay
        that waits seconds for each S2M match still advances, and says at what rate). None while
        paused, and until two steps started since play.

        A step that is still running counts as it runs: one that waits for a block pulls the
        rate down while it waits, instead of the rate of the scans before it staying on screen."""
        now = time.perf_counter()
        with self._cond:
            if not self._playing:
                return None
            starts = list(self._finished_at)
            busy = self._busy
        t = [x for x in starts if x >= now - window]
        if len(t) < 2:
            t = starts[-2:]
        if len(t) < 2 or not t[-1] > t[0]:
            return None
        rate = (len(t) - 1) / (t[-1] - t[0])
        # the running step's interval ends no earlier than now
        return min(rate, len(t) / (now - t[0])) if busy else rate

    def take_counts(self) -> dict:
        """Steps made, late steps and the largest lag (s) since the last call (or the start); the
        counts start again from zero. Late: a real-time step that started more than one scan
        period after its scan arrived."""
        with self._cond:
            out = {"steps": self._counted, "late": self._late, "max_lag_s": round(self._max_lag, 3)}
            self._counted, self._late, self._max_lag = 0, 0, 0.0
        return out

    @property
    def lag_s(self) -> float | None:
        """Real-time clock, while playing: how long after its scan arrived (on the sensor clock,
        replayed in real time) the newest step started; None in replay or while paused."""
        with self._cond:
            return self._lag if self._playing and self._clock == "realtime" else None

    @property
    def playing(self) -> bool:
        return self._playing

    @property
    def speed(self) -> float | None:
        return self._speed

    @property
    def clock(self) -> str:
        return self._clock

    @property
    def idle(self) -> bool:
        """Nothing running and nothing queued: the scan counter will not move until told to."""
        with self._cond:
            return not self._busy and self._steps_pending == 0 and not (self._playing and not self._loc.done)

    def wait_idle(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._busy or self._steps_pending or (self._playing and not self._loc.done):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def stop(self, timeout: float = 1.5) -> None:
        with self._cond:
            self._stopping = True
            self._playing = False
            self._cond.notify_all()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        with self._cond:
            tracer, self._tracer = self._tracer, None
        if tracer is not None:
            tracer.close()

    # ------------------------------------------------------------------ the thread
    def _due_in(self, now: float) -> float:
        """Seconds until the next scan is due while playing (≤ 0: now). Called with the lock held."""
        if self._clock == "realtime":
            k = self._loc.k
            stamps = self._loc.seq.timestamps
            if k >= len(stamps):
                return 0.0
            if self._anchor is None:
                self._anchor = (now, float(stamps[k]))
            return self._arrival(k) - now
        if self._speed is None or self._last_start is None:
            return 0.0
        return self._last_start + 1.0 / self._speed - now

    def _start_lag(self, now: float) -> float | None:
        """How late a step starting ``now`` is after its scan's arrival (realtime, playing). Called
        with the lock held."""
        if self._clock != "realtime" or not self._playing or self._anchor is None:
            return None
        stamps = self._loc.seq.timestamps
        k = self._loc.k
        if k >= len(stamps):
            return None
        return max(0.0, now - self._arrival(k))

    def _arrival(self, k: int) -> float:
        """Wall time scan k arrives in the realtime clock, from the pacing anchor (set). Called
        with the lock held."""
        assert self._anchor is not None
        return self._anchor[0] + (float(self._loc.seq.timestamps[k]) - self._anchor[1])

    def _step_deadline(self) -> float | None:
        """Real time, playing: by when the step starting now should be over (the next scan's
        arrival, less what publishing a snapshot takes here lately), so that its waits leave the
        next scan on time (:mod:`lidarloc.core.localizer.deadline`); None otherwise. Called with
        the lock held."""
        if self._clock != "realtime" or not self._playing or self._anchor is None:
            return None
        k = self._loc.k
        if k + 1 >= len(self._loc.seq.timestamps):
            return None
        return self._arrival(k + 1) - self._publishing.value

    def _scan_period(self) -> float:
        if self._period is None:
            stamps = np.asarray(self._loc.seq.timestamps, float)
            steps = np.diff(stamps)
            steps = steps[steps > 0]
            self._period = float(np.median(steps)) if steps.size else 0.1
        return self._period

    def _count(self) -> None:
        """A step started: count it, and whether it was late. Called with the lock held."""
        self._counted += 1
        if self._lag is not None:
            self._max_lag = max(self._max_lag, self._lag)
            if self._lag > self._scan_period():
                self._late += 1
                if self._tracer is not None:
                    self._tracer.late(self._loc.k, self._lag)
        if self._tracer is not None:
            self._arm_tracer(self._last_start)

    def _untrace(self) -> None:
        """No late scan to trace (paused, another clock, the pacing restarted). Called with the
        lock held."""
        if self._tracer is not None:
            self._tracer.cancel()

    def _arm_tracer(self, now: float | None) -> None:
        """Arm the late-scan trace for the scan after the one starting ``now`` (realtime, playing);
        cancel it otherwise. Called with the lock held."""
        assert self._tracer is not None
        stamps = self._loc.seq.timestamps
        k = self._loc.k + 1
        if now is None or self._lag is None or self._anchor is None or k >= len(stamps):
            self._tracer.cancel()
            return
        late_at = self._arrival(k) + self._scan_period()
        if late_at > now:
            self._tracer.arm(k, late_at - now)
        else:
            self._tracer.cancel()

    def _run(self) -> None:
        while True:
            finished = False
            started, rebases = 0.0, -1  # set with the step's start below
            with self._cond:
                while True:
                    if self._stopping:
                        return
                    if self._loc.done:
                        self._steps_pending = 0
                        if self._playing:
                            self._playing = False
                            self._cond.notify_all()
                            finished = self._on_finished is not None
                            if finished:
                                break
                        self._cond.wait()
                        continue
                    if self._steps_pending:
                        self._steps_pending -= 1
                        break
                    if self._playing:
                        wait = self._due_in(time.perf_counter())
                        if wait <= 0:
                            break
                        self._cond.wait(wait)
                        continue
                    self._cond.wait()
                if not finished:
                    self._busy = True
                    # kept here: rebase() may clear _last_start while this step runs (a kidnap
                    # waits for the step's lock, then rebases while its snapshot is published)
                    started = self._last_start = time.perf_counter()
                    rebases = self._rebases
                    self._lag = self._start_lag(self._last_start)
                    self._count()
                    deadline = self._step_deadline()
            if finished:
                # outside the lock: the callback may restart and play again (a loop)
                try:
                    self._on_finished()
                except Exception as exc:  # the player lives on, paused at the end
                    self._on_error(f"playback: restarting at the end failed: {type(exc).__name__}: {exc}")
                continue
            try:
                snapshot = self._loc.step(deadline)
            except LidarlocError as exc:
                snapshot = None
                self._fail(str(exc))
            except Exception as exc:  # a bug in a step must not kill playback or the server
                snapshot = None
                traceback.print_exc(file=sys.stderr)
                self._fail(f"scan {self._loc.k}: internal error: {type(exc).__name__}: {exc}")
            # Published before the busy flag drops, so whoever sees the player idle also sees
            # the snapshot of the last scan it processed.
            if snapshot is not None:
                published_from = time.perf_counter()
                try:
                    self._on_snapshot(snapshot)
                    self._publishing.add(time.perf_counter() - published_from)
                except Exception as exc:  # one line naming the block; the run pauses after its last complete scan
                    self._fail(
                        f"{block_of(exc)} failed after scan {getattr(snapshot, 'scan_index', self._loc.k - 1)}: {describe(exc)}; playback paused "
                        "(the filter's results up to that scan stand)"
                    )
            with self._cond:
                self._busy = False
                self.steps_done += 1
                if self._playing and snapshot is not None and rebases == self._rebases:
                    # the step's start: starts are what the pacing spaces (finish times bunch up
                    # after a slow scan), so the rate never reads above the set speed. A step
                    # that ran across a rebase is not counted: the rate starts again after it.
                    self._finished_at.append(started)
                self._cond.notify_all()

    def _fail(self, message: str) -> None:
        with self._cond:
            self._playing = False
            self._steps_pending = 0
        self._on_error(message)
