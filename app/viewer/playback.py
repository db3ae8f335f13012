"""The Playback folder's handlers: play, pause, step, speed, clock, restart, and the play button that follows the player."""

from __future__ import annotations

import threading

import viser

from ...core.errors import LidarlocError
from .controls import whole_number
from .keys import add_shortcuts
from .style import SPEEDS

#: how long a clock change waits for the localizer before the page says it lands later
CLOCK_SWITCH_WAIT_S = 1.0


class Playback:
    """A part of :class:`Viewer` (see the module docstring)."""

    def _sync_play_button(self) -> None:
        p, play = self.player, self.controls.play
        if p is None:
            if self.replay_only:
                label = "Pause" if self.travel.replaying else "Play"
                if play.label != label:
                    play.label = label
                    play.icon = viser.Icon.PLAYER_PAUSE if self.travel.replaying else viser.Icon.PLAYER_PLAY
            return
        label = "Pause" if p.playing else "Play"
        if play.label != label:
            play.label = label
            play.icon = viser.Icon.PLAYER_PAUSE if p.playing else viser.Icon.PLAYER_PLAY
        finished = self.localizer.done
        if play.disabled != finished:
            play.disabled = finished
            self.controls.step.disabled = finished

    # ============================================================== Playback folder
    def _wire_playback(self) -> None:
        c = self.controls
        # a recorded run without a localizer plays and steps its timeline (see _toggle_play)
        c.play.on_click(self._guarded(self._toggle_play, needs_localizer=False))
        c.step.on_click(self._guarded(self.step_once, needs_localizer=False))
        c.speed.on_update(self._guarded(self._apply_speed, needs_localizer=False))
        c.clock.on_update(self._guarded(self._apply_clock))
        c.realtime.on_click(self._guarded(self.realtime_clock))
        c.restart.on_click(self._guarded(self.restart))
        self.shortcuts = add_shortcuts(self.server.gui)

    def play(self) -> None:
        self.travel.to_live()
        self.player.play()
        self._wake.set()

    def pause(self) -> None:
        self.travel.keep_paused()
        self.player.pause()
        self._wake.set()

    def _replaying(self) -> bool:
        """No localizer: a recorded run is on screen (its timeline plays), or the localizer is
        still being built (refused)."""
        if self.localizer is not None:
            return False
        if not self.replay_only:
            raise LidarlocError("the localizer is still starting (map and tables are being built)")
        return True

    def _toggle_play(self) -> None:
        if self._replaying():
            self.travel.toggle_replay(self.controls.speed.value)
            self._wake.set()
            return
        if self.player.playing:
            self.pause()
        else:
            if self.localizer.done:
                raise LidarlocError("end of the sequence: restart to play again")
            self.play()

    def step_once(self) -> None:
        if self._replaying():
            self.travel.stop_replay()
            self.travel.timeline.forward()
            return
        if self.localizer.done:
            raise LidarlocError("end of the sequence: restart to play again")
        self.travel.to_live()
        self.player.step_once()
        self._wake.set()

    def _apply_speed(self) -> None:
        v = self.controls.speed.value
        if v not in SPEEDS:  # checked here: a modified page can send any text
            raise LidarlocError(f"speed must be one of {', '.join(SPEEDS)}, got {v!r}")
        if self.player is None:  # a recorded run's playback reads it when Play is pressed
            return
        self.player.set_speed(None if v == "max" else float(v))
        self._wake.set()

    def _apply_clock(self) -> None:
        """The clock, for the localizer and the player. A step waiting for S2M holds the
        localizer (for a minute, the first whole-map match on a busy machine): the change is
        handed to a thread of its own and lands when the step lets go, the page says so, and the
        click does not hang meanwhile."""
        clock = self.controls.clock.value
        if clock not in ("replay", "realtime"):
            raise LidarlocError(f"clock must be replay or realtime, got {clock!r}")
        applied = threading.Event()
        loc, player = self.localizer, self.player

        def done(_result) -> None:
            player.set_clock(clock)
            applied.set()

        def failed(message: str) -> None:
            applied.set()
            self.show_message(f"refused: clock: {message}", error=True)

        self.clock_worker.submit("clock", lambda: loc.set_params(clock=clock), done, failed)
        self.controls.speed.disabled = clock == "realtime"
        self.controls.realtime.visible = False
        cost = (
            "scans are not waited for: the results now depend on the machine's load"
            if clock == "realtime"
            else "every S2M match is waited for: the run repeats exactly"
        )
        if applied.wait(CLOCK_SWITCH_WAIT_S):
            self.show_message(f"clock: {clock} ({cost})")
        else:
            self.show_message(f"clock: {clock} once the scan in progress has its S2M match ({cost})")

    def realtime_clock(self) -> None:
        """The status window's button: the real-time clock, as if chosen under Playback."""
        with self._quietly():
            self.controls.clock.value = "realtime"
        self._apply_clock()

    def restart(self) -> None:
        seed = whole_number(self.controls.seed, "seed", 0)
        with self.travel.lock:
            self.travel.close()
            self.localizer.restart(seed=seed)
            self.travel.started(self.localizer)
        self.history.clear()
        self.scene.clear()
        self.why.clear()
        self.alarm.clear()
        self.player.rebase()
        self.publish(self.localizer.snapshot())
        self.heap.request()  # the run just left behind was freed
        self.show_message(f"restarted from scan 0 with seed {seed}")

    def play_again(self) -> None:
        """At the end of the sequence, from the player thread (``serve(loop=True)``): restart with
        the same seed and play on; the restart is recorded as a new run, as the Restart button's is."""
        self.restart()
        self.play()
