"""Time travel in the viewer: what the timeline shows, the recording of the live run, "Branch from
here", and a second run beside the first (the original of a branch, or ``view --run A --run B``).

:class:`TimeTravel` is the viewer's one handle on all of it. The viewer calls it at a few points:
``on_step`` (player thread: record the step), ``shown`` (display thread: the recorded snapshot to
draw while scrubbing, else None), ``after_draw`` (display thread: the timeline, the second run's
particles, the plots' cursor), ``started`` (a new run to record) and ``close``.

The second run ("reference") is drawn in its own colour: its trajectory, its particles and
estimate at the step on screen (in lockstep by step; while scrubbing, both trajectories end at
that step), dashed lines in the plots, and its figures beside the first run's in the Compare
folder, over the steps after the branch point, following the run on screen as it grows.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from ...core.runs.recording import RecordingError
from ...core.snapshot import Snapshot
from .compare import compare_markdown
from .recorded import RecordedRun, open_branch_at, reopened
from .recorder import Recorder
from .shapes import ChunkedPolyline, vehicle_outline
from .style import REF_COLOR, REF_PARTICLE_COLOR
from .timeline import Timeline
from .why_worker import LatestOnly

COMPARE_INTERVAL_S = 0.5  # the Compare table follows a growing run at most this often


@dataclass
class RunContext:
    """What the Why views need of a localizer, for a recorded run shown without one: its
    configuration, map, lookup table and sequence (``k``: every recorded scan counts as processed)."""

    cfg: object
    seq: object
    prior_map: object
    lookup: object
    k: int = 1 << 62
    pyramid: object = None

    @property
    def effective_d_max(self) -> float:
        return self.lookup.capped(self.cfg.pf.d_max)


class TimeTravel:
    """Scrubbing, branching and a second run beside the first, for ``viewer`` (the
    :class:`~lidarloc.app.viewer.app.Viewer` that owns it; not imported here: the viewer imports
    this module)."""

    def __init__(self, viewer, order: float):
        self.v = viewer
        self.recorder: Recorder | None = None
        self.context: RunContext | None = None  # a recorded run's map and table (no localizer)
        self.reference: RecordedRun | None = None
        self.reference_label = ""
        self.primary_label = ""
        self._ref_series: dict | None = None
        self._ref_version = 0
        self._ref_drawn: tuple | None = None
        self._ref_nodes: dict = {}
        self._lock = threading.Lock()
        self._no_recorder_lock = threading.RLock()
        # scrubbing: the scans of recorded steps are recomputed here, the newest asked for only
        self._scans = LatestOnly("lidarloc-scrub")
        self._full: tuple | None = None  # ((run id, step), snapshot with its scan)
        self._pending: tuple | None = None
        self._replay: threading.Thread | None = None  # plays a recorded run's timeline
        self._replay_stop = threading.Event()
        # held by the replay thread while it takes a step, and by any other mover while it stops
        # the replay: a step the replay was taking lands before the user's move, never after it
        self._replay_step = threading.Lock()
        self.branching = False
        self._resume_on_live = False  # scrubbing paused live playback: Live plays on
        self._compared = (-1, 0.0)  # (steps, when) the Compare table was last computed for
        gui = viewer.server.gui
        self.timeline = Timeline(
            gui,
            guarded=viewer._guarded,
            on_move=self._moved,
            order=order,
            on_forward_live=lambda: viewer.step_once(),
            before_move=self._halt_replay,
        )
        self.timeline.branch.on_click(viewer._guarded(self.branch_from_here, needs_localizer=False))
        with gui.add_folder("Compare", order=order + 0.01, expand_by_default=True, visible=False) as folder:
            self.compare_folder = folder
            self.compare_text = gui.add_markdown("")
        self.ref_line = ChunkedPolyline(viewer.server.scene, "/reference/trajectory", REF_COLOR, 2.0)

    # ================================================================== recording the live run
    def record_with(self, recorder: Recorder) -> None:
        self.recorder = recorder

    @property
    def lock(self):
        """Held while a step is recorded; controls that change the filter between steps take it."""
        return self.recorder.lock if self.recorder is not None else self._no_recorder_lock

    def started(self, loc, name: str = "run", branch_of: dict | None = None, first_step: int = 0) -> None:
        """``loc`` starts a run (attached, restarted, branched): record it and put it on the slider."""
        rec = self.recorder
        if rec is None:
            self.timeline.recording_text.content = (
                "<small>not recorded: the timeline and branches need a viewer "
                "started with its source options (`lidarloc demo`, `view`)</small>"
            )
            self.timeline.set_run(None)
            return
        try:
            path = rec.start(loc, name, branch_of=branch_of, first_step=first_step)
        except LidarlocError as exc:
            self.v.show_message(f"not recording: {exc}", error=True, everyone=True)
            self.timeline.set_run(None)
            return
        self.timeline.recording_text.content = f"<small>recording into `{path}`</small>"
        self.timeline.set_run(rec.run, live_available=True)

    def on_step(self, loc, snap: Snapshot) -> None:
        """Player thread, after each step: append it to the recording."""
        if self.recorder is not None:
            self.recorder.on_scan(loc, snap)

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()

    def stop(self) -> None:
        """The viewer stops: the scan and replay threads too, and the recording is closed."""
        self._replay_stop.set()
        self._scans.stop()
        if self.recorder is not None:
            self.recorder.stop()

    # ================================================================== what is on screen
    @property
    def scrubbing(self) -> bool:
        return self.timeline.step is not None

    def _moved(self, step: int | None) -> None:
        """The user moved the timeline (GUI thread): dragging pauses live playback; back to live
        ("Live", or ▶ past the newest step) it plays on if it was playing."""
        p = self.v.player
        if step is not None and p is not None and p.playing:
            p.pause()
            self._resume_on_live = True
        elif step is None and self._resume_on_live:
            self._resume_on_live = False
            loc = self.v.localizer
            if p is not None and loc is not None and not loc.done:
                p.play()
        if threading.current_thread() is not self._replay:
            self._replay_stop.set()  # a drag pauses a recorded run's playback too
        self.v.wake()

    def keep_paused(self) -> None:
        """Pause was pressed: back to live, playback stays paused."""
        self._resume_on_live = False

    def to_live(self) -> None:
        """Play or Step was pressed: the scene shows the live run again."""
        if self.timeline.step is not None and self.timeline.live_available:
            self.timeline.live()

    def shown(self) -> Snapshot | None:
        """The recorded snapshot to draw (display thread), or None: draw the live one.

        The step's figures come at once; its scan, recomputed from the source, on the scan
        thread: until it is there the scene shows no scan (never another step's), then the
        display draws the step again with it."""
        self._follow_recording()  # a rolling window may have left the step on screen behind
        step, run = self.timeline.step, self.timeline.run
        if step is None or run is None:
            return None
        end = self.timeline.own_end
        if end is not None and step > end:
            step = end  # a longer second run goes on; this one stays on its last step
        key = (id(run), step)
        full = self._full
        if full is not None and full[0] == key:
            return full[1]
        try:
            quick = run.figures(step)
        except RecordingError:
            if step >= run.first_kept:
                raise
            return None  # dropped just now: the next update shows the window's first step
        if run.seq is not None and self._pending != key:
            self._pending = key
            self._scans.submit(
                "scan",
                lambda: run.snapshot(step),
                done=lambda snap: self._scan_ready(key, snap),
                failed=lambda message: self._scan_failed(run, step, message),
            )
        return quick

    def _scan_failed(self, run: RecordedRun, step: int, message: str) -> None:
        if step >= run.first_kept:  # else the window moved past it meanwhile: the timeline follows
            self.v.show_message(f"scan of step {step}: {message}", error=True)

    def _follow_recording(self) -> None:
        """The slider follows the live run's recording: its newest step and the first one a
        rolling window keeps."""
        tl = self.timeline
        if tl.run is not None and tl.live_available and self.recorder is not None and self.recorder.run is tl.run:
            n, first = self.recorder.n, self.recorder.first_kept
            if n != tl.n or first != tl.first:
                tl.sync(n, first)

    def _scan_ready(self, key: tuple, snap: Snapshot) -> None:
        self._full = (key, snap)
        self.v.wake()

    @property
    def scan_shown(self) -> bool:
        """The scene shows the scan of the step on the timeline (or the live one)."""
        step, run = self.timeline.step, self.timeline.run
        if step is None or run is None or run.seq is None:
            return True
        end = self.timeline.own_end
        if end is not None and step > end:
            step = end
        full = self._full
        return full is not None and full[0] == (id(run), step) and self.v.drawn is full[1]

    def after_draw(self, snap: Snapshot | None) -> None:
        """Display thread, after each update: the slider follows the recording, the second run
        shows the same step, the plots' cursor sits on the scan on screen."""
        tl = self.timeline
        self._follow_recording()
        self._draw_reference(tl.current() if tl.run is not None and tl.n else None, cut=tl.step is not None)
        if (
            self.reference is not None
            and tl.run is not None
            and tl.n != self._compared[0]
            and time.monotonic() - self._compared[1] >= COMPARE_INTERVAL_S
        ):
            self.update_compare_table()
        self.v.readouts.cursor = snap.scan_index if (snap is not None and tl.step is not None) else None

    # ================================================================== playing a recorded run
    @property
    def replaying(self) -> bool:
        return self._replay is not None and self._replay.is_alive() and not self._replay_stop.is_set()

    def toggle_replay(self, speed: str) -> None:
        """Play (or pause) a recorded run's timeline at ``speed`` steps per second ("max": as
        fast as the display draws)."""
        if self.replaying:
            self.stop_replay()
            return
        tl = self.timeline
        if tl.run is None or tl.n == 0:
            raise LidarlocError("nothing recorded to play")
        if tl.current() >= tl.n - 1:
            tl.go(tl.first)  # played to the end: from the start again (a rolling window's first step)
        self._replay_stop = threading.Event()
        interval = 1.0 / (30.0 if speed == "max" else float(speed))
        self._replay = threading.Thread(
            target=self._replay_loop, args=(self._replay_stop, interval), name="lidarloc-replay", daemon=True
        )
        self._replay.start()

    def stop_replay(self) -> None:
        self._replay_stop.set()

    def _halt_replay(self) -> None:
        """Before any move but the replay's own: stop the replay and wait out a step it is taking."""
        if threading.current_thread() is self._replay:
            return
        with self._replay_step:
            self._replay_stop.set()

    def _replay_loop(self, stop: threading.Event, interval: float) -> None:
        tl = self.timeline
        while not stop.wait(interval):
            with self._replay_step:
                if stop.is_set():  # a move came while this thread waited for the lock: it stands
                    break
                try:
                    cur = tl.current()
                    if cur >= tl.n - 1:
                        break
                    tl.go(cur + 1)
                except LidarlocError:
                    break
        stop.set()
        self.v.wake()

    # ================================================================== a second run
    def set_reference(self, run: RecordedRun | None, label: str = "", primary_label: str = "") -> None:
        """Show ``run`` beside the one on screen (None: no second run). Any thread (the branch's
        own): it draws while holding the display, as the display thread's updates do."""
        with self.v.drawing():
            self._set_reference(run, label, primary_label)

    def _set_reference(self, run: RecordedRun | None, label: str, primary_label: str) -> None:
        with self._lock:
            self.reference, self.reference_label, self.primary_label = run, label, primary_label
            self._ref_series = None if run is None else run.series()
            self._ref_version += 1
            self._ref_drawn = None
        self.v.readouts.reference = None if run is None else (label, self._ref_series)
        if run is None:
            self.ref_line.sync(self._ref_version, np.zeros((0, 3)), np.zeros(0, bool))
            for node in self._ref_nodes.values():
                node.visible = False
            self.compare_folder.visible = False
            return
        est = self._ref_series["est"]
        connected = np.ones(len(est), bool)
        if len(est):
            connected[0] = False
        self.ref_line.sync(self._ref_version, est, connected)
        self.compare_folder.visible = True
        self.update_compare_table()
        # a finished run beside a longer one: the timeline reaches the longer one's last step
        self.timeline.cover(run.n)

    def reference_node(self, name: str):
        """The second run's scene handle ``name`` ("particles", "vehicle", …), or None."""
        return self._ref_nodes.get(name)

    def set_layer(self, name: str, visible: bool) -> None:
        """A Layers checkbox: the second run's nodes of that layer follow it."""
        node = {"particles": self._ref_nodes.get("particles"), "vehicles": self._ref_nodes.get("vehicle")}.get(name)
        if node is not None:
            node.visible = visible
        if name == "trajectories":
            self.ref_line.set_visible(visible)

    def update_compare_table(self) -> None:
        """The Compare folder (:func:`~lidarloc.app.viewer.compare.compare_markdown`), recomputed as
        the run on screen grows (display thread, at most every COMPARE_INTERVAL_S) and when a
        second run is set."""
        ref, prim = self.reference, self.timeline.run
        if ref is None or prim is None:
            return
        self._compared = (prim.n, time.monotonic())
        text = compare_markdown(
            prim,
            ref,
            (self.primary_label or "this run", self.reference_label or "other run"),
            colours=(None, REF_COLOR),
        )
        if self.compare_text.content != text:
            self.compare_text.content = text

    def _draw_reference(self, step: int | None, cut: bool = False) -> None:
        """The second run's particles and estimate at the step on screen (or its last one); with
        ``cut`` (scrubbing) its trajectory ends there too."""
        ref, series = self.reference, self._ref_series
        if ref is None or series is None or step is None or ref.n == 0:
            return
        i = min(step, ref.n - 1)
        key = (self._ref_version, i, cut)
        if key == self._ref_drawn:
            return
        self._ref_drawn = key
        est = series["est"]
        upto = int(np.searchsorted(series["step"], i, side="right")) if cut else len(est)
        connected = np.ones(upto, bool)
        if upto:
            connected[0] = False
        self.ref_line.sync(self._ref_version, est[:upto], connected)
        if i < ref.first_kept:  # a rolling window dropped that step of the second run
            for node in self._ref_nodes.values():
                node.visible = False
            return
        with ref._lock:
            rec, j = ref._locate(i)
            P = rec.particles(j)
            pose = rec.mean_pose[j]
        xyz = np.ascontiguousarray(P[:, :3], np.float32)
        scene = self.v.server.scene
        layers = self.v.scene.layers
        dots = self._ref_nodes.get("particles")
        if dots is None:
            self._ref_nodes["particles"] = scene.add_point_cloud(
                "/reference/particles",
                xyz,
                REF_PARTICLE_COLOR,
                point_size=0.6,
                precision="float32",
                point_shape="circle",
                point_shading="flat",
                visible=layers.particles,
            )
        else:
            dots.points = xyz
            dots.visible = layers.particles
        if np.isfinite(pose).all():
            segs = vehicle_outline(pose)
            veh = self._ref_nodes.get("vehicle")
            if veh is None:
                self._ref_nodes["vehicle"] = scene.add_line_segments(
                    "/reference/vehicle",
                    segs,
                    REF_COLOR,
                    thickness=3.0,
                    thickness_units="screen",
                    visible=layers.vehicles,
                )
            else:
                veh.points = segs
                veh.visible = layers.vehicles

    # ================================================================== branch from here
    def branch_from_here(self) -> None:
        """Continue from the step on the slider with the Parameters folder's values (GUI thread:
        the branch is built on a thread of its own; the page says when it is ready)."""
        tl = self.timeline
        run = tl.run
        if run is None and self.recorder is None:
            raise LidarlocError("this viewer does not record (started with --no-record): nothing to branch from")
        if run is None or tl.n == 0:
            raise LidarlocError("nothing recorded yet: play or step first")
        if self.branching:
            raise LidarlocError("a branch is being started already")
        step = tl.current()
        end = tl.own_end
        if end is not None and step > end:
            raise LidarlocError(
                f"this run ended at step {end}: branch from a step up to it, or open the blue run "
                "first (view --run) to branch from its later steps"
            )
        v = self.v
        changed = v.params.changed()
        overrides = v.params.to_si(changed) if changed else {}
        scan = run.scan_of(step)
        self.branching = True
        v.show_message(
            f"branching after scan {scan}"
            + (f" with {v.params.names(changed)}" if changed else " (no parameter changed)")
            + "…"
        )
        client = getattr(v._acting, "client", None)
        threading.Thread(
            target=self._branch, args=(run, step, scan, overrides, changed, client), name="lidarloc-branch", daemon=True
        ).start()

    def _branch(self, run: RecordedRun, step: int, scan: int, overrides: dict, changed: dict, client) -> None:
        v = self.v
        try:
            loc = open_branch_at(run, step, overrides, v.cache_root)
        except LidarlocError as exc:
            v.show_message(f"refused: branch: {exc}", error=True, client=client)
            self.branching = False
            return
        except Exception as exc:  # keep the viewer alive and say what went wrong
            import sys
            import traceback

            traceback.print_exc(file=sys.stderr)
            v.show_message(f"internal error: branch: {type(exc).__name__}: {exc}", error=True, client=client)
            self.branching = False
            return
        try:
            original = run
            rec, j = run._locate(step)
            # the step counted from the original recording's start: it stays put if its window moves
            branch_of = {"run": str(rec.run_dir), "step": int(j) + rec.dropped}
            v.switch_to(
                loc,
                head=original.series(step + 1),
                head_events=[(s, e) for s, e in original.events() if s <= step],
                name=f"branch-scan-{scan}",
                branch_of=branch_of,
                first_step=step + 1,
            )
            if changed:
                v.params.accept(changed)
                v._mark_pending()
            label = f"original ({Path(original.path).name})"
            self.set_reference(reopened(original), label=label, primary_label=f"branch after scan {scan}")
            where = self.recorder.run_dir if self.recorder is not None and self.recorder.run_dir else None
            v.show_message(
                f"branched after scan {scan}: press Play to continue" + (f"; recording into {where}" if where else ""),
                client=client,
            )
        finally:
            self.branching = False
