"""The viewer around one Localizer: the panel's controls wired to what they do, the display
thread that draws the newest snapshot, and the localizer's arrival (or failure to start).

The panel's controls are built in :mod:`~lidarloc.app.viewer.panel`; every folder with controls
has a section below (the Particles and Parameters folders in :mod:`~lidarloc.app.viewer.controls`),
whose ``_wire_*`` method connects each control to the handler that follows it (each tab's own
camera folder is wired in :mod:`~lidarloc.app.viewer.camera`, the keyboard shortcuts in
:mod:`~lidarloc.app.viewer.keys`). Handlers run on
viser's worker threads through :meth:`Viewer._guard`: a refused value or a failure becomes a
message in the panel, never a dead callback or server.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import traceback
from collections.abc import Callable
from contextlib import contextmanager
from typing import TYPE_CHECKING

import viser

from ...core.errors import LidarlocError
from ...core.snapshot import Snapshot
from .camera import TabCameras, start_pose
from .controls import ParameterControls, ParticleControls
from .display import Display
from .faults import BlockFailed, FaultReporter
from .heap import HeapTrimmer
from .history import History
from .layers import LayerFolder
from .messages import Messages
from .minimap import Overview
from .panel import build_panel
from .params import ParamForm
from .playback import Playback
from .player import Player
from .readouts import Readouts
from .retired import Retired
from .scene import SceneView
from .status import AlarmNotice, ReplayWaits
from .travel import TimeTravel
from .why import WhyViews
from .why_worker import LatestOnly

if TYPE_CHECKING:
    from ...core.localizer import Localizer

#: How long stopping waits for the player's step and the display's update in flight to finish
#: (a GUI update after the server stopped is lost and warned about).
STOP_WAIT_S = 5.0


class Viewer(Playback, Display, Messages, ParticleControls, ParameterControls):
    """GUI, scene and threads around one Localizer. Use
    :func:`~lidarloc.app.viewer.serve.serve` to start one."""

    def __init__(
        self, server: viser.ViserServer, *, autoplay: bool | None = None, speed: str = "10", display_thread: bool = True
    ):
        """``autoplay``: True plays as soon as the localizer is ready, False stays paused, None
        (default) plays once the localizer is ready and a browser tab is open, so the user sees
        the run from its first scan."""
        self.server = server
        self.localizer: Localizer | None = None
        self.player: Player | None = None
        self.history = History()
        self.scene = SceneView(server.scene)
        self.controls = build_panel(server.gui, speed=speed, layers=self.scene.layers)
        self.overview = Overview(self.controls.overview)
        self.readouts = Readouts(self.controls, self.history)
        self.params = ParamForm(self.controls.params, self.controls.q)
        self.cameras = TabCameras(
            server,
            self.scene,
            lambda: self._latest,
            self._camera_guarded,
            folder_order=self.controls.particles_folder.order + 0.5,
        )
        self.cache_root = None  # where a branch finds the map's tables (serve sets it)
        self.replay_only = ""  # why controls that need a localizer refuse (a recorded run)
        # the timeline heads the control panel, above Playback
        self.travel = TimeTravel(self, order=self.controls.playback_folder.order - 0.5)
        # the Why views read the localizer, or a recorded run's map and table when there is none
        self.why = WhyViews(
            server,
            self.scene,
            localizer=lambda: self.localizer or self.travel.context,
            drawn=lambda: self._drawn,
            guarded=self._guarded,
            show_message=self.show_message,
            folder_order=self.controls.particles_folder.order + 0.25,
        )
        self.owns_localizer = False
        self.retired = Retired()  # runs a branch took over, closing meanwhile
        self._display_lock = threading.RLock()  # one display update at a time (update_display)
        # GUI writes from callbacks and messages hold the gate; close_gui() takes it before the
        # server stops, so nothing is queued on a stopped server (viser warns of each such write)
        self._gui_gate = threading.RLock()
        self.closed = False
        self.sinks: list = []  # more consumers of each step played (the Foxglove stream)
        self._autoplay = autoplay
        self._start_lock = threading.Lock()
        self._tab_seen = False  # a browser tab has connected (autoplay=None starts then)
        self._auto_started = False
        self._map_shown = None  # the prior map the scene shows (show_map, before attach)
        self._acting = threading.local()  # the tab whose GUI action is being handled
        self._latest: Snapshot | None = None
        self._drawn: Snapshot | None = None
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._ready = threading.Event()
        self._message = ""
        self._message_until: float | None = None  # when the message under the status goes (None: stays)
        self._last_draw = 0.0
        self._last_update = 0.0
        self.first_scan_shown = threading.Event()  # set once a processed scan has been drawn
        self.step_failed: str | None = None  # the newest failed step's message
        self.replay_waits = ReplayWaits()  # the status's note on the replay clock's waits
        self.alarm = AlarmNotice(
            lambda text: self.show_message(text, error=True, everyone=True, title="lidarloc: false fire")
        )
        # set in the thread where the viewer itself writes GUI values (viser runs the callbacks of
        # a value written on the server in the writing thread): only those callbacks are quiet
        self._syncing = threading.local()
        self.display_faults = FaultReporter(
            "viewer display", lambda line: self.show_message(line, error=True, everyone=True)
        )
        self.on_finished: Callable[[], None] | None = None  # called when playing reached the end (a loop)
        self.scene.on_map_tiles = self.wake  # tiles of a city's map were read: the display shows them
        self.clock_worker = LatestOnly("lidarloc-clock")  # clock changes wait for the step here
        self._wire_playback()
        self._wire_particles()
        self._wire_parameters()
        self.layers = LayerFolder(
            self.controls,
            self.scene,
            guarded=self._guarded,
            localizer=lambda: self.localizer,
            quietly=self._quietly,
            on_toggle=self.travel.set_layer,
        )
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self.cameras.disconnect)
        # what a tab that left or a finished run freed goes back to the system (see heap.py)
        self.heap = HeapTrimmer()
        server.on_client_disconnect(self.heap.request)
        # Without the display thread (benchmarks) the owner calls update_display() itself.
        self._display = threading.Thread(target=self._display_loop, name="lidarloc-display", daemon=True)
        if display_thread:
            self._display.start()

    # ============================================================== callbacks and messages
    def _guard(self, event, action: Callable[[], object], needs_localizer: bool = True, gated: bool = True) -> None:
        """Run a GUI action; a refused value or any failure becomes a visible message, never a
        dead callback thread or a crashed server. ``gated``: the action holds the GUI gate (it
        waits for a display update in progress); a tab's own camera moves do not, so that they
        answer at once however long the display takes on a busy machine."""
        if getattr(self._syncing, "on", False) or self.closed:
            return
        client = getattr(event, "client", None)
        # messages the action shows go to this tab as notifications too (show_message)
        self._acting.client = client
        try:
            if needs_localizer and not self._ready.is_set():
                raise LidarlocError(
                    self.replay_only or "the localizer is still starting (map and tables are being built)"
                )
            with self._gui_gate if gated else contextlib.nullcontext():
                if self.closed:
                    return
                action()
        except LidarlocError as exc:
            self.show_message(f"refused: {exc}", error=True, client=client)
        except Exception as exc:  # keep the server alive and say what went wrong
            traceback.print_exc(file=sys.stderr)
            self.show_message(f"internal error: {type(exc).__name__}: {exc}", error=True, client=client)
        finally:
            self._acting.client = None

    def _guarded(self, action: Callable[[], object], needs_localizer: bool = True, gated: bool = True) -> Callable:
        """``action`` as a GUI callback, run through :meth:`_guard`."""
        return lambda event: self._guard(event, action, needs_localizer, gated)

    def _camera_guarded(self, action: Callable[[], object], needs_localizer: bool = True) -> Callable:
        """A tab's camera control as a GUI callback: not behind a display update (see _guard)."""
        return self._guarded(action, needs_localizer, gated=False)

    @contextmanager
    def _quietly(self):
        """The viewer writes GUI values itself: their callbacks (run in this thread by viser) do
        nothing meanwhile. A tab's action handled on another thread meanwhile is not dropped."""
        self._syncing.on = True
        try:
            yield
        finally:
            self._syncing.on = False

    @property
    def latest(self) -> Snapshot | None:
        """The newest snapshot handed to the display (None before the localizer is attached)."""
        return self._latest

    @property
    def drawn(self) -> Snapshot | None:
        """The snapshot the scene shows now (the display draws the newest one when it gets to it)."""
        return self._drawn

    # ============================================================== localizer lifecycle
    def build_progress(self, stage, frac=None) -> None:
        """Progress callback for the Localizer constructor: (stage, fraction)."""
        self.readouts.building(stage, frac)
        self._wake.set()

    def startup_failed(self, message: str) -> None:
        self.readouts.failed(message)
        self.show_message(f"could not start: {message}", error=True, everyone=True, keep=True)

    def show_map(self, prior_map) -> None:
        """Draw the prior map and move every tab's camera onto it, before the localizer is ready
        (the Localizer's ``on_map`` callback, on the thread that builds it: the lookup table and
        pyramid are still to come). :meth:`attach` then leaves the map as it is."""
        # held like a display update: the display thread draws the overview and the map's tiles
        # too, and two threads writing one node at once can leave it stale
        with self.drawing():
            if prior_map is self._map_shown:
                return
            self.scene.set_map(prior_map)
            self.overview.set_map(self.scene.footprint)
            self._map_shown = prior_map
        self.cameras.overview()
        self._wake.set()

    def _on_connect(self, client: viser.ClientHandle) -> None:
        """A new tab: its camera folder; the first one starts playback when autoplay waits for it."""
        self.cameras.connect(client)
        with self._start_lock:
            self._tab_seen = True
            start = self._autoplay is None and self._ready.is_set() and not self._auto_started
            if start:
                self._auto_started = True
        if start:
            self.play()

    def attach(self, localizer: Localizer) -> None:
        """Show a ready Localizer: its map (once), its parameters, and start playing it (at once,
        when the first tab opens, or not at all: see ``autoplay``)."""
        self.localizer = localizer
        self.show_map(localizer.prior_map)
        start = start_pose(localizer)
        if start is not None:
            self.cameras.near(start)
        self._adopt(localizer)
        with self._start_lock:
            self._ready.set()
            start = self._autoplay is True or (self._autoplay is None and self._tab_seen)
            self._auto_started = start
        if start:
            self.play()
        self._wake.set()

    def _adopt(self, localizer: Localizer, *, record: dict | None = None) -> None:
        """Everything of :meth:`attach` but the map and autoplay: the panel shows ``localizer``,
        a paused player drives it, its run is recorded (``record``: the recorder's ``start``
        arguments; default a new run)."""
        self.readouts.set_scan_axis(localizer.n_scans)
        live = localizer.live_params()
        self._show_live_params(live)
        self.layers.show_s2m_tables()
        if not localizer.seq.has_poses:
            self.readouts.no_ground_truth()
        speed = self.controls.speed.value
        with self.travel.lock:
            self.travel.started(localizer, **(record or {}))
            self.player = Player(
                localizer,
                self._on_step,
                self._on_player_error,
                speed=None if speed == "max" else float(speed),
                clock=live["clock"],
                on_finished=self._finished,
            )
        self.player.start()
        for h in (
            self.controls.play,
            self.controls.step,
            self.controls.restart,
            self.controls.reset,
            self.controls.kidnap,
        ):
            h.disabled = False
        self.replay_only = ""
        self.why.attach(localizer)
        self.readouts.built()
        self.publish(localizer.snapshot())

    def switch_to(
        self, localizer: Localizer, *, head: dict, head_events: list, name: str, branch_of: dict, first_step: int
    ) -> None:
        """Carry on with ``localizer`` (a branch; the viewer owns it and closes it): the old run's
        player stops (and its localizer closes if the viewer built it), the plots and the
        trajectory start from the original's steps ``head`` (:meth:`RecordedRun.series`) and go
        on with the branch's, recorded as ``name`` in the recorder's root."""
        old, old_player, owned = self.localizer, self.player, self.owns_localizer
        self.travel.stop_replay()
        if old_player is not None:
            old_player.stop(timeout=1.0)
        with self.travel.lock:
            self.travel.close()
            self.localizer, self.owns_localizer = localizer, True
            self.history.load(head, head_events)
            self.why.clear()
            self._adopt(localizer, record={"name": name, "branch_of": branch_of, "first_step": first_step})
            self._ready.set()
        if old is not None and owned and old is not localizer:
            self.retired.close(old)
        self._wake.set()

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Block until a localizer is attached (False on timeout)."""
        return self._ready.wait(timeout)

    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    def _show_live_params(self, live: dict) -> None:
        """The localizer's current values (``Localizer.live_params()``) in the panel; they count
        as applied."""
        c = self.controls
        with self._quietly():
            self.params.show(live)
            c.s2m_enabled.value = bool(live["s2m_enabled"])
            c.clock.value = live["clock"]
            c.seed.value = int(self.localizer.cfg.seed)
        self._mark_pending()

    # ============================================================== snapshots and display
    def publish(self, snap: Snapshot) -> None:
        """Hand a snapshot to the display (any thread; never blocks on the display)."""
        self.history.record(snap)
        self._latest = snap
        self._wake.set()

    def _on_step(self, snap: Snapshot) -> None:
        """A snapshot from the player thread: recorded, then shown. A restart that landed between
        the step returning and this call has replaced the localizer's snapshot: this one is from
        the old run, drop it."""
        loc = self.localizer
        if snap is loc.snapshot():
            try:
                self.travel.on_step(loc, snap)
            except Exception as exc:  # the player pauses with one line naming the recorder
                raise BlockFailed("recorder", exc) from exc
            for sink in self.sinks:
                try:
                    sink.on_step(loc, snap)
                except Exception as exc:
                    raise BlockFailed(getattr(sink, "block", type(sink).__name__), exc) from exc
            self.publish(snap)

    def _finished(self) -> None:
        """Playing reached the end of the sequence (player thread): the owner's ``on_finished``
        (``loop``: restart and play again)."""
        if self.on_finished is not None and not self.stopping:
            self.on_finished()

    def wake(self) -> None:
        """Have the display thread update soon (any thread)."""
        self._wake.set()

    def _on_player_error(self, message: str) -> None:
        self.step_failed = message
        self.show_message(message, error=True, everyone=True, keep=True)
        self._wake.set()

    # ============================================================== shutdown
    def stop(self) -> None:
        """Stop the threads that write to the GUI, and wait for them (bounded: a step waiting for
        a block that hangs must not hang the exit), so that the server stops after them."""
        self._stopping.set()
        self._wake.set()
        self.heap.stop()
        self.why.stop()
        self.clock_worker.stop()
        if self.player is not None:
            self.player.stop(timeout=STOP_WAIT_S)
        try:
            self.travel.stop()
        except Exception:  # stopping goes on: the recording stays readable up to its last step
            traceback.print_exc(file=sys.stderr)
        if self._display.is_alive():
            self._display.join(timeout=STOP_WAIT_S)

    def close_gui(self, timeout: float = STOP_WAIT_S) -> None:
        """No GUI write from now on: waits (bounded) for a callback's or the display's write in
        flight, so that the server can stop after it. Called by the handle right before the server
        stops; a write after that would be queued on a closed connection and lost."""
        got_gate = self._gui_gate.acquire(timeout=timeout)
        got_display = self._display_lock.acquire(timeout=timeout)
        self.closed = True
        if got_display:
            self._display_lock.release()
        if got_gate:
            self._gui_gate.release()
