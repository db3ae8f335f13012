"""``lidarloc run``: localize over a sequence without a viewer and write the results to disk.

Every run records its steps into ``--out``'s ``recording/`` folder unless told not to
(:mod:`lidarloc.core.runs.recording`); a branch of a recorded run (:mod:`lidarloc.app.branch`) goes
through the same loop. Ctrl-C stops after the scan in progress and still writes everything
computed so far; SIGTERM and SIGHUP do the same. The source's notes (a bag's dropped scans, a folder without times) are printed
before the run, and a map and scans found to be in different frames are warned about as soon as
the localizer says so.
"""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from ..core.config import Config
from ..core.errors import LidarlocError
from ..core.localizer import Interrupted, Localizer
from ..core.localizer.deadline import RecentPeak, ScanClock
from ..core.runs.recording import RecordingWriter
from ..core.runs.results import make_out_dir, summarize_run, write_run
from ..core.sequences.factory import SourceSpec
from .console import preparing, progress_bar, stop_signals_like_ctrl_c
from .options import open_source


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def run_headless(
    spec: SourceSpec,
    cfg: Config,
    out: Path,
    cache_root: Path | None = None,
    console: Console | None = None,
    stop_after: int | None = None,
    preset: str | None = None,
    record: bool = True,
) -> tuple[dict, bool]:
    """Run the localizer over the whole sequence; returns (summary, interrupted). ``preset``: the
    named configuration ``cfg`` started from (``--preset``), recorded in the summary. ``record``:
    write every step's state into ``out/recording/`` as it happens (:mod:`lidarloc.core.runs.recording`;
    what was finished stays after Ctrl-C or a crash)."""
    console = console or Console(stderr=True)
    seq = open_source(spec, cfg, console)
    make_out_dir(out)  # fail on an unwritable --out before the long part
    if record:
        check_recording_target(out)
    loc = preparing(lambda progress: Localizer(seq, cfg, cache_root, progress=progress))
    try:
        writer = RecordingWriter(out, spec, cfg, seq, preset=preset) if record else None
    except BaseException:
        loc.close()
        raise
    return localize(loc, out, console, writer=writer, stop_after=stop_after, preset=preset)


def check_recording_target(out: Path) -> None:
    """Refuse, before the long part, an ``out`` that already holds a recording."""
    from ..core.runs.recording import FOLDER, STEPS, RecordingError

    if (Path(out) / FOLDER / STEPS).exists():
        raise RecordingError(f"{Path(out) / FOLDER}: a recording is already there; choose another --out")


def localize(
    loc: Localizer,
    out: Path,
    console: Console,
    writer=None,
    stop_after: int | None = None,
    preset: str | None = None,
    title: str | None = None,
) -> tuple[dict, bool]:
    """Step ``loc`` to the end of its sequence (or ``stop_after`` steps in all, or Ctrl-C), record
    each step with ``writer`` (a RecordingWriter, or None), and write the results into ``out``;
    returns (summary, interrupted). Closes ``loc``. A localizer that does not start at scan 0 (a
    branch) plays in real time from its first scan's time on."""
    seq, cfg = loc.seq, loc.cfg
    realtime = cfg.localize.clock == "realtime"
    if realtime:
        try:
            loc.wait_ready()  # the sensor's clock starts once every block is up
        except BaseException:
            loc.close()
            if writer is not None:
                writer.close()
            raise
    lags: list[float] = []
    # Ctrl-C sets a flag that the loop checks between scans, and a step still waiting for a
    # block (the odometry, a match due now) gives up at once (Localizer.interrupt): that scan is
    # not recorded, everything before it is written.
    stop = threading.Event()

    def on_ctrl_c(*_):
        stop.set()
        loc.interrupt()

    stop_signals_like_ctrl_c()  # SIGTERM and SIGHUP call on_ctrl_c too
    previous = signal.signal(signal.SIGINT, on_ctrl_c) if _main_thread() else None
    cpu_start = loc.cpu_seconds()
    warned = _warn_frames(console, loc.events, 0)
    n_before = len(loc.records)  # a branch starts with the recorded run's
    clock = ScanClock(seq, loc.k if not loc.done else 0)
    t_start = clock.start
    failure: str | None = None  # a block's failure that stopped the run (written into the summary)
    writing = RecentPeak()  # real time: what recording a scan takes after its step (s)
    deadline = None
    try:
        console.print(
            title or f"localizing {len(seq)} scans of {seq.name} (seed {cfg.seed}, {cfg.localize.clock} clock)"
        )
        with progress_bar(transient=False) as bar:
            task = bar.add_task(f"localizing {seq.name}", total=len(seq), completed=loc.k)
            while not loc.done and not stop.is_set() and (stop_after is None or loc.steps < stop_after):
                if realtime:
                    # Scans arrive at the sequence's own rate; a step that starts after its scan's
                    # arrival time is late (we never drop scans, we count the lag).
                    lag = clock.wait_due(loc.k, stop.is_set)
                    if lag is None:
                        break
                    lags.append(lag)
                    # the step's waits end in time for the next scan, after the writing below
                    deadline = clock.deadline(loc.k, writing.value)
                try:
                    snap = loc.step(deadline)
                except Interrupted:
                    break
                except LidarlocError as exc:  # one line naming the block: results up to the last scan
                    failure = str(exc)
                    raise
                if writer is not None:
                    written_from = time.perf_counter()
                    writer.on_scan(loc, snap)
                    writing.add(time.perf_counter() - written_from)
                warned = _warn_frames(console, loc.events, warned)
                bar.update(
                    task,
                    completed=snap.scan_index + 1,
                    description=f"localizing {seq.name}" + (" [green]localized" if snap.localized else ""),
                )
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        wall = time.perf_counter() - t_start
        cpu_end = loc.cpu_seconds()  # before close(): the child processes end there
        cpu_used = {
            k: None if cpu_start[k] is None or cpu_end[k] is None else cpu_end[k] - cpu_start[k] for k in cpu_start
        }
        loc.close()
        interrupted = stop.is_set()
        if interrupted:
            console.print("[yellow]interrupted: writing what was computed[/yellow]")
        n_new = len(loc.records) - n_before
        summary = summarize_run(loc, wall, lags[:n_new] if realtime else None, cpu_used, preset=preset)
        summary["interrupted"] = interrupted
        if failure is not None:
            summary["stopped_by"] = failure
        if getattr(loc, "branch_of", None) is not None:
            summary["branch_of"] = loc.branch_of
        try:
            if writer is not None:
                writer.close(summary)
        finally:  # a recording that failed never costs the results
            write_run(loc, out, summary)
    error = f"RMSE after {summary['rmse_after_localized_m']}" if loc.seq.has_poses else "no ground truth (no errors)"
    console.print(
        f"results in {out}: localized at scan {summary['localized_at_scan']}, "
        f"{error}, PF {summary['pf_ms_median']} ms median"
    )
    return summary, interrupted


def _warn_frames(console: Console, events, seen: int) -> int:
    """Print the ``frame_mismatch`` events after the first ``seen`` events; returns how many were seen."""
    for e in events[seen:]:
        if e.kind == "frame_mismatch":
            console.print(f"[yellow]warning:[/yellow] {escape(e.detail)}", highlight=False, soft_wrap=True)
    return len(events)
