"""The display thread: at most every MIN_DRAW_INTERVAL it draws the newest snapshot (or the
recorded step the timeline shows) with its status, plots and map tiles; a display update that
fails says so in the status and the next one draws everything again. A part of
:class:`~lidarloc.app.viewer.app.Viewer`."""

from __future__ import annotations

import sys
import time
import traceback
from contextlib import contextmanager

from ...core.snapshot import Snapshot
from .faults import one_line
from .status import viewer_status
from .style import MIN_DRAW_INTERVAL

#: after a display update failed, the next try waits this long (s): it draws the whole snapshot
FAILED_RETRY_S = 0.5


class Display:
    """A part of :class:`~lidarloc.app.viewer.app.Viewer` (see the module docstring)."""

    def _display_loop(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(timeout=0.1)
            self._wake.clear()
            if self._stopping.is_set():
                return
            # at most MIN_DRAW_INTERVAL apart, whatever woke it: while the map is built, progress
            # reports arrive once per fused scan (1200 for the town) and each update holds the GIL
            wait = max(self._last_draw, self._last_update) + MIN_DRAW_INTERVAL - time.perf_counter()
            if wait > 0:
                self._stopping.wait(wait)
            try:
                self.update_display()
            except Exception as exc:  # one line (once per distinct failure); the thread and server live on
                self.display_faults.report(exc, "the viewer keeps serving and the filter keeps playing")
                self._display_failed(exc)
                # the next try draws everything again: not at the display's pace while it keeps failing
                self._stopping.wait(FAILED_RETRY_S)
            else:
                self.display_faults.clear()
            self._last_update = time.perf_counter()

    def _display_failed(self, exc: Exception) -> None:
        """A display update raised: the status must not go on showing what it showed before as if
        it were current (a green "localized" of a scan long gone), and the next update starts
        over: the whole snapshot is drawn again, not only what changed since a draw that failed
        half-way."""
        self._drawn = None
        loc = self.localizer
        shown = self._latest
        try:
            with self._gui_gate:
                if self.closed:
                    return
                self.readouts.not_current(
                    one_line(exc),
                    shown=None if shown is None else shown.scan_index,
                    n_scans=None if shown is None else shown.n_scans,
                    at=None if loc is None else loc.k,
                )
            # the Play / Pause button says what the player does, drawn or not
            self._sync_play_button()
        except Exception:  # the page itself fails: the console line stands, the next update retries
            traceback.print_exc(file=sys.stderr)

    @contextmanager
    def drawing(self):
        """Hold the display: a scene write from another thread (a branch setting the second run)
        waits for a display update in progress and keeps the next one out until it is done. Two
        threads writing one chunked line at once can leave it holding a node that viser replaced
        (same name) and that later writes fail on."""
        # the gate first, as GUI actions take it (one of them may update the display): one order
        with self._gui_gate, self._display_lock:
            yield

    def update_display(self, force_plots: bool = False) -> float:
        """One display update: progress, scene, status and (rate-limited) plots. Returns ms spent
        on the scene and status (the per-scan cost). Updates are serialised: the display thread and
        a caller (a test, the timeline) never interleave, so the newest state is what stays shown."""
        with self.drawing():
            if self.closed:
                return 0.0
            return self._update_display(force_plots)

    def _update_display(self, force_plots: bool) -> float:
        self.readouts.update_progress(None if self.localizer is None else self.localizer.rebuild_progress)
        shown = self.travel.shown()  # a recorded step the timeline was moved to
        snap = shown if shown is not None else self._latest
        ms = 0.0
        if snap is not None and snap is not self._drawn:
            t0 = time.perf_counter()
            step = self.travel.timeline.step
            with self.server.atomic():
                cut = None if shown is None or step is None else max(step + 1 - self.history.first_step, 0)
                self.scene.draw(snap, self.history, cut=cut)
            self._drawn = snap
            if snap.scan_index >= 0:
                self.first_scan_shown.set()
            self.why.on_draw(snap, recorded=shown is not None)
            self.alarm.check(snap, live=shown is None)
            self.readouts.update_status(self.status_markdown(snap))
            self.cameras.follow(snap)
            ms = (time.perf_counter() - t0) * 1000.0
            self._last_draw = time.perf_counter()
        elif snap is not None:
            self.readouts.update_status(self.status_markdown(snap))  # play/pause state may have changed
        self._update_map(snap)
        self._expire_message()
        self.travel.after_draw(snap)
        self.readouts.update_plots(force_plots)
        self._sync_play_button()
        self.layers.on_display(self._ready.is_set())
        return ms

    def _update_map(self, snap: Snapshot | None) -> None:
        """A city's map: the tiles at full density follow the estimate (read on a thread of their
        own, swapped in here); the overview shows where the particles are (at most once a second,
        and only when something changed)."""
        with self.server.atomic():
            self.scene.follow_map(None if snap is None else snap.mean_pose)
        self.overview.update(snap, self.scene.near_tiles, time.monotonic())

    def status_markdown(self, snap: Snapshot) -> str:
        return viewer_status(self, snap)
