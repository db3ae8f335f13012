"""``lidarloc run``: localize over a sequence without a viewer and write the results to disk.

Ctrl-C stops after the scan in progress and still writes everything computed so far.
"""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from lidarloc.core.config import Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.geometry import pose_to_xyz_ypr, wrap_angle
from lidarloc.core.localizer import Interrupted, Localizer
from lidarloc.core.metrics import ScanLog, compute_metrics
from lidarloc.core.results import write_events, write_json, write_kitti, write_records_csv, write_tum
from lidarloc.core.sequences.factory import SourceSpec, open_sequence


def summarize(loc: Localizer, wall_s: float, lags_ms: list[float] | None = None,
              cpu_s: dict | None = None) -> dict:
    """The run's summary.json. ``lags_ms`` (real-time clock): for each processed scan, how long
    after its arrival time its step started. ``cpu_s``: CPU seconds each block's process used
    during the run (differences of :meth:`Localizer.cpu_seconds`)."""
    recs = loc.records
    localized = np.array([r.localized for r in recs], dtype=bool)
    err = np.array([np.nan if r.error_m is None else r.error_m for r in recs], dtype=float)
    yaw_err = np.array([np.nan if r.gt_yaw is None else float(wrap_angle(r.yaw - r.gt_yaw)) for r in recs], dtype=float)
    metrics = compute_metrics(ScanLog(localized, err, yaw_err))
    first_loc = next((r.scan for r in recs if r.localized), None)
    after = err[localized] if localized.any() else np.array([])
    after = after[np.isfinite(after)]
    pf_ms = np.array([r.pf_ms for r in recs], dtype=float)
    s2m_ms = np.array([r.s2m_ms for r in recs if r.s2m_ms is not None], dtype=float)
    kinds = [e.kind for e in loc.events]
    return {
        "source": loc.seq.name, "seed": loc.cfg.seed, "scans": len(recs), "clock": loc.cfg.localize.clock,
        "s2m": loc.cfg.s2m.enabled, "particles": loc.cfg.pf.n_particles,
        "localized_at_scan": first_loc,
        "within_5m_for_50_at_scan": None if metrics["D"] is None else metrics["D"] - 1,
        "rmse_after_localized_m": float(np.sqrt(np.mean(after**2))) if after.size else None,
        "final_error_m": float(err[-1]) if len(err) and np.isfinite(err[-1]) else None,
        "pf_ms_median": float(np.median(pf_ms)) if pf_ms.size else None,
        "s2m_ms_median": float(np.median(s2m_ms)) if s2m_ms.size else None,
        "scans_per_second": len(recs) / wall_s if wall_s > 0 else None,
        "s2m_landed": kinds.count("s2m_accepted") + kinds.count("s2m_rejected"),
        "s2m_accepted": kinds.count("s2m_accepted"),
        "s2m_cancelled": kinds.count("s2m_cancelled"),
        "false_positives": kinds.count("false_positive"), "losses": kinds.count("loss"),
        **_lag_summary(lags_ms),
        **_cpu_summary(cpu_s, len(recs), wall_s),
        "metrics": metrics,
    }


def _cpu_summary(cpu_s: dict | None, scans: int, wall_s: float) -> dict:
    """CPU milliseconds per scan of each block's process, and all of them as a share of one core
    (200 % = both cores of the reference machine busy for the whole run)."""
    if not cpu_s or scans == 0:
        return {"cpu_ms_per_scan": None, "cpu_percent": None}
    known = [v for v in cpu_s.values() if v is not None]
    return {"cpu_ms_per_scan": {k: None if v is None else 1000.0 * v / scans for k, v in cpu_s.items()},
            "cpu_percent": 100.0 * sum(known) / wall_s if wall_s > 0 else None}


LATE_MS = 100.0   # a step that starts this much after its scan arrived is late (one LiDAR period)


def _lag_summary(lags_ms: list[float] | None) -> dict:
    """How well the real-time clock kept up: late scans, the largest lag, and from which scan on
    it kept up (every later step started within LATE_MS of its scan's arrival; None = it was
    still late at the end). None everywhere in replay."""
    if lags_ms is None:
        return {"late_scans": None, "max_lag_ms": None, "lag_at_end_ms": None, "kept_up_from_scan": None}
    lag = np.asarray(lags_ms, dtype=float)
    late = np.flatnonzero(lag > LATE_MS)
    return {"late_scans": int(late.size), "max_lag_ms": float(lag.max()) if lag.size else 0.0,
            "lag_at_end_ms": float(lag[-1]) if lag.size else 0.0,
            "kept_up_from_scan": 0 if not late.size else (int(late[-1]) + 1 if late[-1] + 1 < lag.size else None)}


def write_outputs(loc: Localizer, out: Path, summary: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    recs = loc.records
    times = np.array([r.time for r in recs])
    poses = np.array(loc.est_trajectory).reshape(-1, 4, 4)
    write_kitti(out / "trajectory_kitti.txt", poses)
    write_tum(out / "trajectory_tum.txt", times, poses)
    if loc.seq.has_poses and recs:
        gt = np.array([loc.seq.pose(r.scan) for r in recs])
        write_kitti(out / "groundtruth_kitti.txt", gt)
        write_tum(out / "groundtruth_tum.txt", times, gt)
    write_records_csv(out / "scans.csv", recs)
    write_events(out / "events.json", loc.events)
    write_json(out / "summary.json", summary)


def make_out_dir(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LidarlocError(f"{out}: cannot create the output directory ({exc.strerror})") from None


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def run_headless(spec: SourceSpec, cfg: Config, out: Path, cache_root: Path | None = None,
                 console: Console | None = None, stop_after: int | None = None) -> tuple[dict, bool]:
    """Run the localizer over the whole sequence; returns (summary, interrupted)."""
    from .cli import progress_bar

    console = console or Console(stderr=True)
    seq = open_sequence(spec, cfg)
    make_out_dir(out)  # fail on an unwritable --out before the long part
    with progress_bar() as bar:
        task = bar.add_task("preparing map", total=100)
        loc = Localizer(seq, cfg, cache_root, progress=lambda stage, f: bar.update(
            task, description=f"preparing {stage}", completed=100 * f))
    realtime = cfg.localize.clock == "realtime"
    if realtime:
        try:
            loc.wait_ready()     # the sensor's clock starts once every block is up
        except BaseException:
            loc.close()
            raise
    lags: list[float] = []
    # Ctrl-C sets a flag that the loop checks between scans, and a step still waiting for a
    # block (the odometry, a match due now) gives up at once (Localizer.interrupt): that scan is
    # not recorded, everything before it is written.
    stop = threading.Event()

    def on_ctrl_c(*_):
        stop.set()
        loc.interrupt()
    previous = signal.signal(signal.SIGINT, on_ctrl_c) if _main_thread() else None
    cpu_start = loc.cpu_seconds()
    t_start = time.perf_counter()
    try:
        console.print(f"localizing {len(seq)} scans of {seq.name} (seed {cfg.seed}, {cfg.localize.clock} clock)")
        with progress_bar(transient=False) as bar:
            task = bar.add_task(f"localizing {seq.name}", total=len(seq))
            while not loc.done and not stop.is_set() and (stop_after is None or loc.steps < stop_after):
                if realtime:
                    # Scans arrive at the sequence's own rate; a step that starts after its scan's
                    # arrival time is late (we never drop scans, we count the lag).
                    due = t_start + seq.timestamp(loc.k)
                    now = time.perf_counter()
                    if now < due:
                        # sleep, not stop.wait(): the Ctrl-C handler sets ``stop`` on this same
                        # thread, and would deadlock on the Event's lock if it interrupted wait()
                        time.sleep(min(due - now, 0.05))
                        continue
                    lags.append(max(0.0, (now - due) * 1000.0))
                try:
                    snap = loc.step()
                except Interrupted:
                    break
                bar.update(task, completed=snap.scan_index + 1,
                           description=f"localizing {seq.name}" + (" [green]localized" if snap.localized else ""))
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        wall = time.perf_counter() - t_start
        cpu_end = loc.cpu_seconds()          # before close(): the child processes end there
        cpu_used = {k: None if cpu_start[k] is None or cpu_end[k] is None else cpu_end[k] - cpu_start[k]
                    for k in cpu_start}
        loc.close()
        interrupted = stop.is_set()
        if interrupted:
            console.print("[yellow]interrupted: writing what was computed[/yellow]")
        summary = summarize(loc, wall, lags[: len(loc.records)] if realtime else None, cpu_used)
        summary["interrupted"] = interrupted
        write_outputs(loc, out, summary)
    console.print(f"results in {out}: localized at scan {summary['localized_at_scan']}, "
                  f"RMSE after {summary['rmse_after_localized_m']}, PF {summary['pf_ms_median']} ms median")
    return summary, interrupted
