"""A run's results: trajectories in KITTI and TUM formats (so ``evo`` reads them), the per-scan
CSV, the event list and the summary JSON (:func:`summarize_run`), written by :func:`write_run`.
``lidarloc run`` and every run of ``lidarloc bench localize`` write the same files.

Poses are LiDAR poses in the map's frame: for a map built from a drive, the drive's first LiDAR
pose; for a map file (``--map``), the file's own coordinates — the localizer's local frame plus the
map's float64 origin, so a georeferenced (UTM) map gets UTM poses back at full precision (KITTI
files then carry 13 significant digits, TUM files micrometres). The ground truth is written
beside the estimate in the same frame and format (``groundtruth_*.txt``) so
``evo_ape kitti groundtruth_kitti.txt trajectory_kitti.txt`` compares like with like; the
summary's ``ape_rmse_m`` and ``rpe_rmse_m`` are evo's own figures on the TUM files once written
(:mod:`lidarloc.core.trajectory_errors`).

Every file is written under a temporary name and renamed into place
(:func:`~lidarloc.core.cache.atomic_write_file`): a run killed at any moment leaves each file
complete or absent, never cut short. A write that fails (disk full, no permission) is one line
naming the file (:func:`writing`), and the files written before it stay as they were.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import errno
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from ..cache import atomic_write_file
from ..errors import LidarlocError
from ..geometry import wrap_angle
from .metrics import ScanLog, compute_metrics, confidence_metrics
from .trajectory_errors import trajectory_errors

if TYPE_CHECKING:
    from ..localizer import Localizer


@contextlib.contextmanager
def writing(path: Path) -> Iterator[None]:
    """A failed write of ``path`` as one line naming it (exit 2 on the command line): disk full,
    no permission, a read-only file system."""
    try:
        yield
    except OSError as exc:
        why = exc.strerror or str(exc)
        if exc.errno == errno.ENOSPC:
            why += " (files written before it are intact)"
        raise LidarlocError(f"{path}: cannot write it: {why}") from None


def _write_text(path: Path, fill) -> None:
    """``fill(file)`` into ``path``, atomically (see the module docstring)."""

    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as f:
            fill(f)

    with writing(Path(path)):
        atomic_write_file(Path(path), write)


def write_kitti(path: Path, poses: np.ndarray, digits: int = 6) -> None:
    """KITTI rows with ``digits`` decimals in the mantissa (6: local frames; 12 keeps a
    micrometre at UTM's 4·10⁶ m)."""

    def fill(f):
        for T in poses:
            f.write(" ".join(f"{v:.{digits}e}" for v in np.asarray(T)[:3, :4].reshape(-1)) + "\n")

    _write_text(path, fill)


def in_map_frame(poses: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """Local-frame poses (N, 4, 4) in the map file's frame (float64, + ``origin``)."""
    poses = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
    if origin is not None:
        poses[:, :3, 3] += np.asarray(origin, dtype=np.float64).reshape(3)
    return poses


def write_tum(path: Path, times: np.ndarray, poses: np.ndarray) -> None:
    def fill(f):
        for t, T in zip(times, poses):
            q = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_quat()  # x, y, z, w (TUM order)
            x, y, z = np.asarray(T)[:3, 3]
            f.write(f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")

    _write_text(path, fill)


def write_records_csv(path: Path, records: list) -> None:
    if not records:
        _write_text(path, lambda f: None)
        return
    names = [f.name for f in dataclasses.fields(records[0])]

    def fill(f):
        w = csv.writer(f)
        w.writerow(names)
        for r in records:
            row = []
            for n in names:
                v = getattr(r, n)
                if v is None:
                    row.append("")
                elif isinstance(v, bool):
                    row.append(int(v))
                elif isinstance(v, float):
                    row.append(f"{v:.6g}")
                else:
                    row.append(v)
            w.writerow(row)

    _write_text(path, fill)


def write_events(path: Path, events: list) -> None:
    text = json.dumps([dataclasses.asdict(e) for e in events], indent=1)
    _write_text(path, lambda f: f.write(text))


def json_safe(value):
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_json(path: Path, data: dict) -> None:
    text = json.dumps(json_safe(data), indent=2)
    _write_text(path, lambda f: f.write(text))


def make_out_dir(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LidarlocError(f"{out}: cannot create the output directory ({exc.strerror})") from None


def write_run(loc: Localizer, out: Path, summary: dict) -> None:
    """Every file of a run: trajectories (and the ground truth when the source has it), the
    per-scan CSV, the events, and ``summary.json`` last, with evo's APE and RPE of the written
    trajectories added to ``summary``."""
    make_out_dir(out)
    recs = loc.records
    times = np.array([r.time for r in recs])
    origin = np.asarray(loc.prior_map.origin, dtype=np.float64)
    digits = 12 if origin.any() else 6
    poses = in_map_frame(loc.est_trajectory, origin)
    write_kitti(out / "trajectory_kitti.txt", poses, digits)
    write_tum(out / "trajectory_tum.txt", times, poses)
    if loc.seq.has_poses and recs:
        gt = in_map_frame([loc.seq.pose(r.scan) for r in recs], origin)
        write_kitti(out / "groundtruth_kitti.txt", gt, digits)
        write_tum(out / "groundtruth_tum.txt", times, gt)
        summary.update(trajectory_errors(out / "trajectory_tum.txt", out / "groundtruth_tum.txt"))
    write_records_csv(out / "scans.csv", recs)
    write_events(out / "events.json", loc.events)
    write_json(out / "summary.json", summary)


# --------------------------------------------------------------------------------- run summary
def world_of(seq) -> dict | None:
    """The world options of the generated town's drive (changes, traffic, sensor, …); None for
    every other source."""
    world_options = getattr(seq, "world_options", None)  # only the generated town has one
    return world_options() if callable(world_options) else None


def summarize_run(
    loc: Localizer,
    wall_s: float,
    lags_ms: list[float] | None = None,
    cpu_s: dict | None = None,
    preset: str | None = None,
) -> dict:
    """The run's summary.json. ``lags_ms`` (real-time clock): for each processed scan, how long
    after its arrival time its step started. ``cpu_s``: CPU seconds each block's process used
    during the run (differences of :meth:`Localizer.cpu_seconds`). ``preset``: the named
    configuration the run started from (``--preset``; None = the defaults), recorded as given.

    ``world`` is the generated town's world options (changes, traffic, sensor, …; None for other
    sources); ``consistency_2sigma`` and ``false_fire`` are :func:`~lidarloc.core.runs.metrics.confidence_metrics`."""
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
    confidence = confidence_metrics(localized, err, [r.inside_2sigma for r in recs])
    n_particles = np.array([r.n_particles for r in recs], dtype=float)
    return {
        "source": loc.seq.name,
        "seed": loc.cfg.seed,
        "scans": len(recs),
        "clock": loc.cfg.localize.clock,
        "preset": preset,
        "world": world_of(loc.seq),
        "s2m": loc.cfg.s2m.enabled,
        "particles": loc.cfg.pf.n_particles,
        "n_particles_median": float(np.median(n_particles)) if n_particles.size else None,
        "localized_at_scan": first_loc,
        # the drive's own seconds from the first scan to that one: on the real-time clock the time
        # a user waits for the first fix; on the replay clock the drive's time, not a wait
        "localized_at_s": None
        if first_loc is None
        else float(loc.seq.timestamp(first_loc) - loc.seq.timestamp(recs[0].scan)),
        "within_5m_for_50_at_scan": None if metrics["D"] is None else metrics["D"] - 1,
        "rmse_after_localized_m": float(np.sqrt(np.mean(after**2))) if after.size else None,
        # evo's APE / RPE of the written TUM files (write_run fills them in; None without truth)
        "ape_rmse_m": None,
        "rpe_rmse_m": None,
        "final_error_m": float(err[-1]) if len(err) and np.isfinite(err[-1]) else None,
        "pf_ms_median": float(np.median(pf_ms)) if pf_ms.size else None,
        "s2m_ms_median": float(np.median(s2m_ms)) if s2m_ms.size else None,
        "scans_per_second": len(recs) / wall_s if wall_s > 0 else None,
        "s2m_landed": kinds.count("s2m_accepted") + kinds.count("s2m_rejected"),
        "s2m_accepted": kinds.count("s2m_accepted"),
        "s2m_cancelled": kinds.count("s2m_cancelled"),
        "s2m_agreed_early": kinds.count("s2m_agrees"),  # real time: agreed before the odometry let it land
        "false_positives": kinds.count("false_positive"),
        "losses": kinds.count("loss"),
        **integrity_summary(loc.events, recs),
        "map_origin_m": [float(v) for v in loc.prior_map.origin],
        "frame_mismatch": [e.detail for e in loc.events if e.kind == "frame_mismatch"],
        **confidence,
        **lag_summary(lags_ms),
        **cpu_summary(cpu_s, len(recs), wall_s),
        "metrics": metrics,
    }


def integrity_summary(events: list, records: list) -> dict:
    """How far the filter's word can be trusted (:mod:`lidarloc.core.rules.integrity`):
    ``relocalizations`` (the whole-map check moved the filter), ``spurious_relocalizations``
    (of those, the ones whose estimate was within the metrics' 5 m of the truth on the scan
    before: a correct estimate overturned), ``withdrawals`` ("localized" withdrawn because S2M no
    longer confirmed the estimate) and ``spurious_withdrawals`` (of a correct estimate), and
    ``localized_wrong_scans`` (scans the rule called localized while the truth was more than 5 m
    away). The spurious counts and the wrong scans need truth (else None)."""
    from ..rules.truth import FALSE_FIRE_M

    by_scan = {r.scan: r for r in records}
    has_truth = any(r.error_m is not None for r in records)

    def right_before(k: int) -> bool:
        r = by_scan.get(k - 1)
        return r is not None and r.error_m is not None and r.error_m <= FALSE_FIRE_M

    moves = [e.scan for e in events if e.kind == "relocalized"]
    spurious = sum(1 for k in moves if right_before(k))
    withdrawals = [e.scan for e in events if e.kind == "unconfirmed"]
    wrong = sum(1 for r in records if r.localized and r.error_m is not None and r.error_m > FALSE_FIRE_M)
    return {
        "relocalizations": len(moves),
        "spurious_relocalizations": spurious if has_truth else None,
        "withdrawals": len(withdrawals),
        "spurious_withdrawals": sum(1 for k in withdrawals if right_before(k)) if has_truth else None,
        "localized_wrong_scans": wrong if has_truth else None,
    }


def cpu_summary(cpu_s: dict | None, scans: int, wall_s: float) -> dict:
    """CPU milliseconds per scan of each block's process, and all of them as a share of one core
    (200 % = both cores of the reference machine busy for the whole run)."""
    if not cpu_s or scans == 0:
        return {"cpu_ms_per_scan": None, "cpu_percent": None}
    known = [v for v in cpu_s.values() if v is not None]
    return {
        "cpu_ms_per_scan": {k: None if v is None else 1000.0 * v / scans for k, v in cpu_s.items()},
        "cpu_percent": 100.0 * sum(known) / wall_s if wall_s > 0 else None,
    }


LATE_MS = 100.0  # a step that starts this much after its scan arrived is late (one LiDAR period)


def lag_summary(lags_ms: list[float] | None) -> dict:
    """How well the real-time clock kept up: late scans, the largest lag, and from which scan on
    it kept up (every later step started within LATE_MS of its scan's arrival; None = it was
    still late at the end). None everywhere in replay."""
    if lags_ms is None:
        return {"late_scans": None, "max_lag_ms": None, "lag_at_end_ms": None, "kept_up_from_scan": None}
    lag = np.asarray(lags_ms, dtype=float)
    late = np.flatnonzero(lag > LATE_MS)
    return {
        "late_scans": int(late.size),
        "max_lag_ms": float(lag.max()) if lag.size else 0.0,
        "lag_at_end_ms": float(lag[-1]) if lag.size else 0.0,
        "kept_up_from_scan": 0 if not late.size else (int(late[-1]) + 1 if late[-1] + 1 < lag.size else None),
    }
