"""The status of the run on screen as the viewer reads it off the live localizer: the play state
(with what a step is waiting for), S2M's readiness as it is now, and the truth alarm's
notification, once per onset. :func:`~lidarloc.app.viewer.readouts.status_markdown` words it."""

from __future__ import annotations

import sys
import time
import traceback
from collections.abc import Callable

from ...core.snapshot import Snapshot
from .readouts import status_markdown, truth_alarm
from .style import EVENTS_SHOWN


def _ask(localizer, name: str):
    """``localizer.name()`` where the localizer has it (None otherwise, or when it fails: a
    status line must never take the display down)."""
    method = getattr(localizer, name, None)
    if not callable(method):
        return None
    try:
        return method()
    except Exception:  # the status goes on without it
        traceback.print_exc(file=sys.stderr)
        return None


def play_state(player, localizer) -> str:
    """ "playing", "paused", "finished", … or, while a step is blocked on a block, what it waits
    for and for how long (``Localizer.waiting()``): a silent "playing" there looked like a hang."""
    if player is None:
        return "starting"
    if localizer is not None and localizer.done and player.idle:
        return "finished"
    waiting = _ask(localizer, "waiting") if localizer is not None else None
    if waiting:
        what, seconds = waiting
        return f"waiting for {what} ({float(seconds):.1f} s)"
    if player.playing:
        return "playing"
    return "paused" if player.idle else "stepping"


#: how long the note on the replay clock's waits stays after the last wait seen: each scan may
#: wait a moment only, and a note and a button that came and went every scan could not be read
#: or clicked
REPLAY_WAIT_NOTE_S = 10.0

REPLAY_WAIT_NOTE = (
    "<small>The replay clock waits for every S2M match, so that the run, any replay of it and "
    "its branches repeat exactly. The real-time clock does not wait: faster, but the results "
    "then depend on the machine's load, and a branch no longer repeats its original step for "
    "step.</small>"
)


class ReplayWaits:
    """Whether the status explains the replay clock's waits for S2M (and offers the real-time
    clock): while playing on the replay clock, from a wait for S2M on until
    REPLAY_WAIT_NOTE_S after the last one."""

    def __init__(self):
        self._seen: float | None = None

    def shown(self, state: str, clock: str, playing: bool, now: float) -> bool:
        if clock != "replay" or not playing:
            self._seen = None
            return False
        if state.startswith("waiting for") and "S2M" in state:
            self._seen = now
        return self._seen is not None and now - self._seen <= REPLAY_WAIT_NOTE_S


def viewer_status(v, snap: Snapshot) -> str:
    """The status markdown of ``snap`` on a :class:`~.app.Viewer` ``v`` (live, or a recorded step
    being scrubbed)."""
    p, loc = v.player, v.localizer
    clock = p.clock if p else "replay"
    floor = None if loc is None else loc.cfg.localize.min_inlier_share
    recorded = v.travel.scrubbing
    live_s2m = None
    if recorded:
        # the scan on the timeline, as it was recorded: its own events, no live rates
        state = "recorded" if loc is None else f"recorded (live run {play_state(p, loc)})"
        tl = v.travel.timeline
        end, step = tl.own_end, tl.step
        if end is not None and step is not None and step > end:
            state += f" · this run ended at step {end}; the blue run is at step {step}"
        events = list(snap.events)[-EVENTS_SHOWN:]
    else:
        state, events = play_state(p, loc), v.history.recent_events()
        if loc is not None:
            live_s2m = _ask(loc, "s2m_status")
    # the next scan is named only when the shown snapshot is the localizer's newest: a display
    # that is a scan behind the player is no skipped scan
    newest = loc is not None and not recorded and snap is loc.snapshot()
    playing = p is not None and not recorded and p.playing
    # the clock chosen counts: a switch to real time lands once the step waiting now lets go
    chosen = clock if v.controls.clock.value == "replay" else "realtime"
    waits = v.replay_waits.shown(state, chosen, playing, time.monotonic())
    if v.controls.realtime.visible != waits:
        v.controls.realtime.visible = waits
    text = status_markdown(
        snap,
        state,
        clock,
        v.controls.speed.value,
        events,
        min_inlier_share=floor,
        s2m_enabled=True if loc is None else bool(loc.cfg.s2m.enabled),
        rate=None if p is None or recorded else p.achieved_rate(),
        lag_s=None if p is None or recorded else p.lag_s,
        next_scan=loc.k if newest else None,
        playing=p is not None and not recorded and p.playing,
        s2m_status=tuple(live_s2m) if live_s2m else None,
    )
    if waits:  # under the play state's line, beside the button it explains
        head, _, rest = text.partition("\n")
        text = f"{head}\n\n{REPLAY_WAIT_NOTE}\n\n{rest}"
    return text


class AlarmNotice:
    """A notification to every tab when the truth alarm goes up (once per onset: it stays up
    scan after scan while the estimate is wrong; the status line keeps saying so)."""

    def __init__(self, notify: Callable[[str], None]):
        self._notify = notify
        self._onset: int | None = None  # localized_since (or scan) of the alarm notified

    def check(self, snap: Snapshot, live: bool) -> None:
        if not live:
            return
        alarm = truth_alarm(snap)
        if alarm is None:
            self._onset = None
            return
        onset = snap.localized_since if snap.localized_since is not None else snap.scan_index
        if onset != self._onset:
            self._onset = onset
            self._notify(f"false fire at scan {snap.scan_index}: {alarm}")

    def clear(self) -> None:
        self._onset = None
