"""``lidarloc view --run DIR [--run DIR2]``: finished runs in the viewer, without recomputing them.

The map and the scans come from the source each run names (its recording's index): the map and
its lookup table from the cache (built once if the cache lost them), the scans read on demand as
the timeline moves. A source that moved is a one-line error naming the path the run expected.

With two runs the first is drawn as usual and the second beside it in blue (trajectory, particle
cloud and vehicle at the same step, dashed plot lines), stepped in lockstep by step; the Compare
folder puts their figures side by side. Both runs must be of the same sequence (same
source and scan count): their steps are compared one for one.

"Branch from here" works on a recorded run too: it continues from the step on the timeline in a
live localizer, recorded under a new ``runs/<date-time>`` folder of the cache root.

A run the viewer kept as a rolling window under its recording budget opens at the window's first
step; the timeline covers the window only.

``--at SCAN`` opens the run at the step that processed that scan (the timeline is moved there
before any tab connects), e.g. where ``lidarloc corpus compare`` found a regression.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import viser
from rich.console import Console

from ...core.config import LIVE_PARAMS
from ...core.errors import LidarlocError
from ...core.runs import recording
from ..console import wait_for_stop
from .collector import release_at_exit
from .recorded import RecordedRun
from .recorder import Recorder, default_record_root
from .serve import ViewerHandle, announce
from .token_gate import resolve_token, start_server
from .travel import RunContext

REPLAY_ONLY = "a recorded run: play or move the timeline, or Branch from here to continue it with a live filter"


def load_run(path, cache_root: Path | None = None, seq=None, progress=None) -> tuple[RecordedRun, RunContext]:
    """A recorded run and what the viewer needs to show it: its sequence, map and lookup table.
    One-line :class:`LidarlocError` for a missing, foreign or corrupt folder, or a moved source."""
    from ...core.maps.world import open_world

    rec = recording.open(path)
    if rec.n == 0:
        raise recording.RecordingError(f"{rec.path}: the recording has no complete step")
    cfg = rec.config()
    if seq is None:
        seq = rec.open_sequence()  # checks the source first: one line naming the moved path
    world = open_world(seq.map_source, cfg, cache_root, pyramid=False, road_removal=False, progress=progress)
    prior_map, lookup = world.prior_map, world.lookup
    use_origin = getattr(seq, "use_map_origin", None)
    if use_origin is not None:
        use_origin(prior_map.origin)
    return RecordedRun(rec.run_dir, seq), RunContext(cfg=cfg, seq=seq, prior_map=prior_map, lookup=lookup)


def step_at_scan(run: RecordedRun, scan: int) -> int:
    """The step of ``run`` that processed ``scan``; a one-line :class:`LidarlocError` naming the
    scans it holds when none did (out of range, skipped by a kidnap, dropped by a rolling window)."""
    first, last = run.first_kept, run.n - 1
    if last >= first:
        for step in range(first, last + 1):  # steps process scans in increasing order
            found = run.scan_of(step)
            if found == scan:
                return step
            if found > scan:
                break
        held = f"scans {run.scan_of(first)}…{run.scan_of(last)}"
    else:
        held = "no scan"
    raise LidarlocError(f"--at {scan}: {run.path} recorded no step of scan {scan} (it holds {held})")


def _same_sequence(a: RecordedRun, b: RecordedRun) -> bool:
    return a.meta.get("source") == b.meta.get("source") and a.meta.get("n_source_scans") == b.meta.get("n_source_scans")


def show_runs(viewer, run: RecordedRun, context: RunContext, other: RecordedRun | None = None) -> None:
    """Put recorded ``run`` (and ``other`` beside it) on a viewer that has no localizer."""
    v = viewer
    v.travel.context = context
    v.replay_only = REPLAY_ONLY
    v.show_map(context.prior_map)
    v.readouts.set_scan_axis(len(context.seq))
    if not context.seq.has_poses:
        v.readouts.no_ground_truth()
    cfg = context.cfg
    live = {key: getattr(getattr(cfg, p.section), p.attr) for key, p in LIVE_PARAMS.items()}
    with v._quietly():
        v.params.show(live)
        v.controls.s2m_enabled.value = bool(live["s2m_enabled"])
        v.controls.clock.value = live["clock"]
        v.controls.seed.value = int(cfg.seed)
    v._mark_pending()
    v.controls.play.label, v.controls.play.icon = "Play", viser.Icon.PLAYER_PLAY
    v.controls.play.disabled = v.controls.step.disabled = False  # they play the timeline
    v.why.attach(context)
    v.history.load(run.series(), run.events())
    v.readouts.built()
    v.travel.timeline.set_run(run, live_available=False)
    v.travel.timeline.recording_text.content = f"<small>recorded run `{run.path}`</small>"
    if other is not None:
        v.travel.set_reference(other, label=Path(other.path).name, primary_label=Path(run.path).name)
    v.first_scan_shown.clear()
    v.wake()


def open_runs(
    run_dirs,
    host: str = "127.0.0.1",
    port: int = 8080,
    cache_root: Path | None = None,
    open_browser: bool = False,
    record_to: Path | None = None,
    token: str | None = None,
    at: int | None = None,
    staleness: Path | None = None,
) -> ViewerHandle:
    """Start a viewer on one or two recorded runs and return at once (the runs are read first: a
    bad folder, a scan ``at`` the first run did not record or a moved source raises before any
    server starts). ``token``: as :func:`.serve.serve`'s. ``at``: the scan the timeline shows first.
    ``staleness``: the output folder of ``lidarloc corpus staleness``, shown as a layer."""
    from .app import Viewer

    token = resolve_token(token)
    dirs = [Path(d) for d in run_dirs]
    if not dirs:
        raise LidarlocError("view --run needs a run folder")
    if len(dirs) > 2:
        raise LidarlocError(f"view --run shows one or two runs side by side, got {len(dirs)}")
    # before the map is opened: a scan the run does not hold fails at once
    step = None if at is None else step_at_scan(RecordedRun(dirs[0]), at)
    if staleness is not None:
        from ..corpus.staleness_out import read_grid

        read_grid(staleness)  # a wrong folder fails before the map is loaded
    run, context = load_run(dirs[0], cache_root)
    other = None
    if len(dirs) == 2:
        other = RecordedRun(dirs[1], context.seq)
        if other.n == 0:
            raise recording.RecordingError(f"{other.rec.path}: the recording has no complete step")
        if not _same_sequence(run, other):
            raise LidarlocError(
                f"{dirs[1]} is a run of another sequence than {dirs[0]} "
                f"({other.rec.meta.get('source_description')} vs {run.meta.get('source_description')})"
            )
    server = start_server(token, host=host, port=port, label="lidarloc", verbose=False)
    try:
        viewer = Viewer(server, autoplay=False)
        viewer.cache_root = cache_root
        root = record_to if record_to is not None else default_record_root(cache_root)
        viewer.travel.record_with(
            Recorder(
                root,
                run.rec.source_spec(),
                run.meta.get("preset"),
                on_failure=lambda m: viewer.show_message(m, error=True, everyone=True),
            )
        )
        show_runs(viewer, run, context, other)
        if staleness is not None:
            from .staleness_layer import show_staleness

            show_staleness(viewer, staleness)
        if step is not None:
            viewer.travel.timeline.go(step)
    except BaseException:
        server.stop()
        raise
    handle = ViewerHandle(viewer, server, host, token)
    if open_browser:
        import webbrowser

        threading.Thread(target=webbrowser.open, args=(handle.url,), daemon=True).start()
    return handle


def serve_runs(
    run_dirs,
    host: str = "127.0.0.1",
    port: int = 8080,
    cache_root: Path | None = None,
    open_browser: bool = False,
    console: Console | None = None,
    token: str | None = None,
    at: int | None = None,
    staleness: Path | None = None,
) -> None:
    """``lidarloc view --run DIR [--run DIR2] [--at SCAN]``: serve recorded runs until Ctrl-C
    (``token``: as :func:`.serve.serve`'s; ``at``: the scan shown first; ``staleness``: a
    ``lidarloc corpus staleness`` output shown as a layer)."""
    console = console or Console(stderr=True)
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        handle = open_runs(run_dirs, host, port, cache_root, open_browser, token=token, at=at, staleness=staleness)
        announce(handle, host, console)
        run = handle.viewer.travel.timeline.run
        first = run.first_kept
        held = (
            f"steps {first}…{run.n - 1} (a rolling window: the recording budget dropped the steps before)"
            if first > 0
            else f"{run.n} recorded scans"
        )
        if at is not None:
            held += f", opened at scan {at}"
        console.print(
            f"showing {held} of {run.path}; branches are recorded under {handle.viewer.travel.recorder.root}",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )
        try:
            wait_for_stop(stop)
        finally:
            console.print("stopping viewer")
            handle.stop()
            release_at_exit()
    finally:
        signal.signal(signal.SIGINT, previous)
