"""The timeline: a slider over the recorded steps of the run on screen, a step back and forward,
the previous and next event of the kinds the Events filter picks (localized, false fire, loss,
relocalized, kidnap, reset, S2M verdicts; by default all but the S2M verdicts, which come every
few scans) with a list of them, "Live" back to the newest step, and "Branch from here".

It keeps which step is on screen (``step``; None: live, the newest snapshot) and tells the viewer
when the user moves it (``on_move``); the viewer pauses playback and draws that step from the
recording (and plays on when the user goes back to live, if the move had paused it). While live,
the slider follows the newest recorded step. A run kept as a rolling window under the recording
budget holds only its newest steps: the slider's lower end follows the window's first step (a
step on screen that the window left behind moves up with it), and ◀ or ◀ event there says the
earlier steps were dropped by the recording budget. The viewer's own writes to the
slider (following the live run) do not count as moves: they are made with a thread-local flag up,
and viser runs an assigned value's callbacks on the assigning thread. A tab's drag is read on
viser's event loop as it is applied (a live follow written over it before its move runs does not
change where it goes).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np

from ...core.errors import LidarlocError
from .recorded import RecordedRun

PREV_EVENT, BACK, FORWARD, NEXT_EVENT, LIVE = "◀ event", "◀", "▶", "event ▶", "Live"
BUTTONS = (PREV_EVENT, BACK, FORWARD, NEXT_EVENT, LIVE)

_RUN_EVENTS = ("localized", "false_fire", "false_positive", "loss", "unconfirmed", "relocalized", "kidnap", "reset")
_S2M_EVENTS = ("s2m_accepted", "s2m_rejected")
#: the event buttons' filter: its choices and the event kinds each stops at. S2M verdicts come
#: every few scans, so the default leaves them out: "event ▶" then goes to what changed the run.
EVENT_FILTERS = {
    "all but S2M": _RUN_EVENTS,
    "localized": ("localized",),
    "false fire": ("false_fire",),
    "loss": ("loss", "false_positive", "unconfirmed"),
    "relocalized": ("relocalized",),
    "kidnap": ("kidnap",),
    "reset": ("reset",),
    "S2M": _S2M_EVENTS,
    "all": _RUN_EVENTS + _S2M_EVENTS,
}
DEFAULT_FILTER = "all but S2M"
EVENTS_LISTED = 12
LIST_INTERVAL_S = 1.0  # the list follows a growing recording at most this often (it reads its events)

HELP = (
    "Drag to any processed scan: the scene, the status, the Why views and the plots' cursor show "
    "that scan as it was recorded (playback pauses). ◀ ▶ step one scan (▶ at the newest one processes "
    "one more; keys ← →, and space plays and pauses); *event* jumps to the previous or next event of "
    "the kind chosen under **Events** (localized, false fire, loss, relocalized, kidnap, reset, S2M "
    "verdicts); **Live** goes back to the newest scan and plays on if it was playing."
)


class Timeline:
    """The Timeline folder and the step on screen. ``on_move(step)`` is called on the GUI thread
    after the user moved to ``step`` (None: back to live); it must stay cheap."""

    def __init__(
        self,
        gui,
        *,
        guarded: Callable,
        on_move: Callable[[int | None], None],
        order: float | None = None,
        on_forward_live: Callable[[], None] | None = None,
        before_move: Callable[[], None] | None = None,
    ):
        """``on_forward_live``: ▶ pressed while live at the newest step (the viewer processes one
        more scan). ``before_move()``: called first in every move (:meth:`go`, :meth:`live`), before
        the step changes (the viewer stops a recorded run's playback there, so that a step it was
        taking cannot land after the user's)."""
        self._on_move = on_move
        self._before_move = before_move
        self._on_forward_live = on_forward_live
        self._guarded = guarded
        self._own = threading.local()
        self._lock = threading.Lock()
        self.run: RecordedRun | None = None
        self.step: int | None = None  # the step on screen; None: live
        self.live_available = True  # False for a finished recording (view --run): no live run
        self._n = 0
        self._first = 0  # the first step the recording still holds (a rolling window's)
        # a finished run shown beside a longer one (view --run A --run B): the slider covers the
        # longer one's steps; past this run's end it stays on its last step
        self._span = 0
        self._written = 0  # the slider value this object wrote last (any other one is a user's move)
        self._listed_at = 0.0
        with gui.add_folder("Timeline", order=order):
            self.where = gui.add_markdown("No recording yet")
            # over the steps (the processed scans in order: a kidnap skips scans, not steps)
            self.slider = gui.add_slider(
                "Step", 0, 1, 1, 0, disabled=True, hint="Drag to a processed scan (pauses playback)"
            )
            # actions: the button group's callback names the button pressed; tests call the methods
            self.buttons = gui.add_button_group("Go to", BUTTONS)
            self.kinds = gui.add_dropdown(
                "Events",
                tuple(EVENT_FILTERS),
                initial_value=DEFAULT_FILTER,
                hint="Which events ◀ event and event ▶ stop at",
            )
            self.event_list = gui.add_markdown("")
            self.branch = gui.add_button(
                "Branch from here",
                disabled=True,
                hint="Continue from this scan's exact filter state with the parameters "
                "in the Parameters folder (changed or not); recorded in its own folder",
            )
            self.recording_text = gui.add_markdown("")
            gui.add_markdown(f"<small>{HELP}</small>")
        self._dragged: int | None = None  # the value a tab's drag set (read on viser's event loop)
        # first: a tab's drag is read on the event loop as it is applied; then the move itself
        self.slider.on_update(self._tab_moved)
        self.slider.on_update(self._slider_moved)
        self.buttons.on_click(guarded(self._button, needs_localizer=False))
        self.kinds.on_update(guarded(self.list_events, needs_localizer=False))

    # ------------------------------------------------------------------ the run on the slider
    def set_run(self, run: RecordedRun | None, live_available: bool = True) -> None:
        """The recording the slider moves over (a new run, a branch, a run opened with --run)."""
        with self._lock:
            self.run = run
            self.live_available = live_available
            self.step = None if live_available else (run.first_kept if run is not None and run.n else None)
            self._n = 0
            self._first = 0
            self._span = 0
        self.sync(moved=True)

    def cover(self, steps: int) -> None:
        """A finished run on the slider: cover ``steps`` steps at least (a second, longer run
        beside it), so that every step of both can be reached. A live run's slider follows its
        own recording only."""
        if self.live_available:
            return
        with self._lock:
            self._span = max(int(steps), 0)
        self.sync(moved=True)

    @property
    def own_end(self) -> int | None:
        """The last step of the run itself when the slider goes past it (a longer second run),
        else None."""
        run = self.run
        # a live run's slider follows its recording, which the run's own count may trail
        if self.live_available or run is None or run.n == 0 or self._n <= run.n:
            return None
        return run.n - 1

    @property
    def n(self) -> int:
        """Steps the slider covers: it ends at step ``n`` − 1."""
        return self._n

    @property
    def first(self) -> int:
        """The slider's first step: 0, or a rolling window's first step."""
        return self._first

    def sync(self, n: int | None = None, first: int | None = None, *, moved: bool = False) -> None:
        """Bring the slider up to date with the recording's steps ``first`` … ``n`` − 1 (the
        display thread, after each recorded step); while live it follows the newest one.

        ``moved``: the step on screen was just set (a move, a new run). Without it the slider's
        value is left alone when it is not the one written last: a user's drag has set it and its
        callback, on its way, moves the timeline there; following the newest step over it would
        make that callback read the newest step instead."""
        run = self.run
        if n is None:
            n = 0 if run is None else run.n
        if run is not None and not self.live_available and run.n:
            n = max(n, self._span)
        if first is None:
            first = 0 if run is None else run.first_kept
        first = min(first, max(n - 1, 0))
        s = self.slider
        # one writer at a time, from reading the step to writing the value: the step read here is
        # the one the value shows (a write's own callback returns at once, see _slider_moved)
        with self._lock, self._writing():
            grew = n != self._n or first != self._first
            self._n, self._first = n, first
            if self.step is not None and self.step < first:
                self.step = first  # the window left the step on screen behind
            step = self.step
            if grew:
                top = max(n - 1, first + 1)
                if s.max < top:  # widen first: the value must stay within min … max
                    s.max = top
                if s.min != first:
                    s.min = first
                if s.max != top:
                    s.max = top
                if s.disabled != (n - first < 2):
                    s.disabled = n - first < 2
            value = max((n - 1 if step is None else step) if n else 0, first)
            # read last, just before the write: a drag landing while the bounds above were sent
            # is then seen and kept (read first, it was overwritten, and its callback read the
            # newest step). Between this read and the write a drag can still be lost: viser has
            # no compare-and-set.
            seen = s.value
            if moved or seen == self._written:
                if s.value != value:
                    s.value = value
                self._written = value
            if self.branch.disabled != (n == 0):
                self.branch.disabled = n == 0
        self._describe()
        if grew and time.monotonic() - self._listed_at > LIST_INTERVAL_S:
            self.list_events()

    def _describe(self) -> None:
        run, step, n, first = self.run, self.step, self._n, self._first
        if run is None or n == 0:
            text = "No recorded scan yet"
        else:
            shown = n - 1 if step is None else step
            end = self.own_end
            past = end is not None and shown > end
            try:
                scan = run.scan_of(end if past and end is not None else shown)
            except LidarlocError:
                scan = shown
            where = "live" if step is None else ("recorded" if self.live_available else "recorded run")
            if past:
                where = f"this run ended at step {end}; the blue run goes on"
            text = f"**Scan {scan}** · step {shown} of {first}…{n - 1} · {where}"
            if first > 0:
                text += (
                    f"<br><small>rolling window: the steps before {first} were dropped by the recording budget</small>"
                )
        if self.where.content != text:
            self.where.content = text

    @contextmanager
    def _writing(self):
        self._own.active = True
        try:
            yield
        finally:
            self._own.active = False

    # ------------------------------------------------------------------ moves
    async def _tab_moved(self, event) -> None:
        """A tab's drag, on viser's event loop right after it set the slider's value: the value is
        kept here, because by the time the move runs (on a worker thread, after the display's
        update in progress) a live follow may have written the newest step over it. Writes made
        on the server (ours, or a test's) arrive here without a client and are left alone."""
        if event.client_id is not None:
            self._dragged = int(self.slider.value)

    def _slider_moved(self, event) -> None:
        if getattr(self._own, "active", False):
            return
        # the value moved to: a tab's as its update set it (read when the move runs: of several
        # quick drags the last one wins); a write made on this thread, read at once (this callback
        # runs right after it), not after the display's update in progress, which may follow live
        from_tab = getattr(event, "client_id", None) is not None and self._dragged is not None
        value = None if from_tab else int(self.slider.value)
        try:
            self._guarded(lambda: self.go(self._dragged if value is None else value), needs_localizer=False)(event)
        finally:
            if self.slider.value != self._written:  # a refused move: show the timeline's step again
                self.sync(moved=True)

    def _button(self) -> None:
        {
            PREV_EVENT: self.prev_event,
            BACK: self.back,
            FORWARD: self.forward,
            NEXT_EVENT: self.next_event,
            LIVE: self.live,
        }[self.buttons.value]()

    def _require(self) -> RecordedRun:
        if self.run is None or self._n == 0:
            raise LidarlocError("nothing recorded yet: play or step first")
        return self.run

    def current(self) -> int:
        """The step on screen (the newest while live)."""
        self._require()
        return self._n - 1 if self.step is None else self.step

    def dropped_error(self) -> LidarlocError:
        return LidarlocError(
            f"the steps before {self._first} were dropped by the recording budget (this run keeps a rolling "
            f"window of steps {self._first}…{self._n - 1})"
        )

    def go(self, step: int) -> int:
        """Show recorded ``step`` (a step a rolling window dropped: its first one); returns it. A
        step past the end is refused, not moved to another one."""
        self._require()
        if step > self._n - 1:
            raise LidarlocError(f"step {step} is past the end: the timeline ends at step {self._n - 1}")
        if self._before_move is not None:
            self._before_move()
        step = int(np.clip(step, self._first, self._n - 1))
        with self._lock:
            self.step = step
        self.sync(moved=True)
        self._on_move(step)
        return step

    def back(self) -> int:
        cur = self.current()
        if cur <= self._first and self._first > 0:
            raise self.dropped_error()
        return self.go(cur - 1)

    def forward(self) -> int:
        """One step later; past the newest recorded step, live again (if there is a live run),
        and already live there, one more scan (``on_forward_live``)."""
        if self.step is None and self.live_available and self._on_forward_live is not None:
            self._on_forward_live()
            return self._n
        cur = self.current()
        if cur + 1 >= self._n and self.live_available:
            self.live()
            return cur
        return self.go(cur + 1)

    @property
    def event_kinds(self) -> tuple:
        """The event kinds the event buttons stop at (the Events filter)."""
        return EVENT_FILTERS.get(self.kinds.value, EVENT_FILTERS[DEFAULT_FILTER])

    def _what(self) -> str:
        return "event" if self.kinds.value in ("all", DEFAULT_FILTER) else f"{self.kinds.value} event"

    def next_event(self) -> int:
        run, cur = self._require(), self.current()
        steps = run.event_steps(self.event_kinds)
        later = steps[(steps > cur) & (steps < self._n)]
        if not later.size:
            raise LidarlocError(f"no later {self._what()} in the recording")
        return self.go(int(later[0]))

    def prev_event(self) -> int:
        run, cur = self._require(), self.current()
        steps = run.event_steps(self.event_kinds)
        earlier = steps[(steps < cur) & (steps >= self._first)]
        if not earlier.size:
            if self._first > 0:
                raise LidarlocError(
                    f"no earlier {self._what()} in the recording's rolling window (the steps before "
                    f"{self._first} were dropped by the recording budget)"
                )
            raise LidarlocError(f"no earlier {self._what()} in the recording")
        return self.go(int(earlier[-1]))

    def list_events(self) -> None:
        """Under the filter: the scans of the run's events of the chosen kinds (the newest ones)."""
        run = self.run
        self._listed_at = time.monotonic()
        if run is None or self._n == 0:
            text = ""
        else:
            kinds = self.event_kinds
            found = [(s, e) for s, e in run.events() if e.kind in kinds and s < self._n]
            if not found:
                text = f"<small>no {self._what()} yet</small>"
            else:
                shown = ", ".join(f"{e.scan} {e.kind.replace('_', ' ')}" for _, e in found[-EVENTS_LISTED:])
                more = f"{len(found) - EVENTS_LISTED} earlier, " if len(found) > EVENTS_LISTED else ""
                text = f"<small>{len(found)} × ({more}scan and kind): {shown}</small>"
        if self.event_list.content != text:
            self.event_list.content = text

    def live(self) -> None:
        """Back to the newest step (a finished recording: its last step)."""
        if not self.live_available:
            self.go(self._n - 1)
            return
        if self._before_move is not None:
            self._before_move()
        with self._lock:
            self.step = None
        self.sync(moved=True)
        self._on_move(None)
