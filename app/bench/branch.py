"""``lidarloc bench branch``: how fast a branch of a recorded run starts, and what resuming costs
the recording.

A recorded run (``--run DIR``, or one recorded here over the source: default the town's first
1000 scans at 1000 particles, the way ``lidarloc run`` records) is branched at each of its last
:data:`~lidarloc.core.runs.resume.CHECKPOINT_EVERY` steps, so every replay length from 0 to 9 steps
counts once per repeat. Branch start is the time :func:`~lidarloc.core.runs.branch.open_branch` takes
with the run's sequence already open (as in the viewer, which has it): building the localizer
on the cached map and tables, restoring the checkpoint, replaying to the step. Target ≤ 1 s
(median; the worst replay length is given too). Once, the same from nothing (the sequence opened
from the source too).

Also the resume payload's size per 1000 steps: the checkpoints, the S2M outcomes and the per-step
fields (budget: checkpoints and per-step fields ≤ 10 MB per 1000 steps of the run, at its own
particle counts). The same scaled to 1000 particles throughout is reported beside it: with
KLD-sampling the count changes from step to step, and a tempered filter's particles are all
different (float64, incompressible), so at 1000 particles a checkpoint is ~0.12 MB.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.runs import recording
from ...core.runs.branch import open_branch
from ...core.runs.resume import CHECKPOINT_EVERY
from .common import load_avg, machine, record_run

TARGET_START_S = 1.0
BUDGET_MB_PER_1000 = 10.0
RESUME_FIELDS = (
    "odom_pose",
    "odom_prev_pose",
    "odom_path_turned",
    "odom_prev_path_turned",
    "odom_origin",
    "odom_used",
    "s2m_landed_started",
)


def sizes(rec: recording.Recording) -> dict:
    """MB per 1000 steps of the resume payload's parts."""
    folder = rec.path / "resume"

    def mb(pattern: str) -> float:
        return sum(f.stat().st_size for f in folder.glob(pattern) if f.is_file()) / 1e6 * 1000.0 / max(rec.n, 1)

    per_step = (
        sum((rec.path / f"{name}.bin").stat().st_size for name in RESUME_FIELDS if (rec.path / f"{name}.bin").is_file())
        / 1e6
        * 1000.0
        / max(rec.n, 1)
    )
    checkpoints = mb("*-checkpoint.npz")
    # each checkpoint's particle arrays scaled to 1000 particles by its own count (KLD-sampling
    # changes it from step to step); the rest (rules, odometry, S2M state) as it is
    scaled = 0.0
    for f in folder.glob("*-checkpoint.npz"):
        with np.load(f) as data:
            per_particle = [
                data[k].nbytes for k in ("pf_states", "pf_log_weights", "pf_log_likelihoods") if k in data.files
            ]
            n = data["pf_states"].shape[0] if "pf_states" in data.files else 0
        particle_bytes = sum(per_particle)
        scaled += f.stat().st_size - particle_bytes + (particle_bytes * 1000.0 / n if n else 0.0)
    at_1000 = scaled / 1e6 * 1000.0 / max(rec.n, 1) + per_step  # per-step fields hold no particle
    return {
        "checkpoints_mb_per_1000": round(checkpoints, 2),
        "s2m_outcomes_mb_per_1000": round(mb("*-s2m_outcome.npz"), 2),
        "per_step_fields_mb_per_1000": round(per_step, 2),
        "checkpoints_and_per_step_mb_per_1000": round(checkpoints + per_step, 2),
        "checkpoints_and_per_step_mb_per_1000_at_1000_particles": round(at_1000, 2),
    }


def branch_start(
    rec: recording.Recording, seq, cache_root: Path | None = None, repeats: int = 3
) -> tuple[list[float], dict[int, list[float]]]:
    """Seconds :func:`open_branch` takes at each of the recording's last CHECKPOINT_EVERY steps,
    ``repeats`` times each (the sequence already open): all of them, and by replayed steps."""
    checkpoints = rec.resume_steps("checkpoint")
    by_replay: dict[int, list[float]] = {}
    times = []
    for _ in range(repeats):
        for k in range(max(rec.n - CHECKPOINT_EVERY, 0), rec.n):
            t0 = time.perf_counter()
            loc = open_branch(rec, k, seq=seq, cache_root=cache_root)
            dt = time.perf_counter() - t0
            loc.close()
            times.append(dt)
            by_replay.setdefault(k - max(s for s in checkpoints if s <= k), []).append(dt)
    return times, by_replay


def run(
    spec, seq, cfg, cache_root: Path | None = None, run_dir: Path | None = None, repeats: int = 3, progress=None
) -> dict:
    """Branch start times and payload sizes (module docstring)."""
    with tempfile.TemporaryDirectory(prefix="lidarloc-branch-") as tmp:
        t0 = time.perf_counter()
        if run_dir is None:
            run_dir = record_run(spec, seq, cfg, Path(tmp) / "run", cache_root, progress)
        record_s = time.perf_counter() - t0
        rec = recording.open(run_dir)
        if rec.n < 1:
            from ...core.errors import LidarlocError

            raise LidarlocError(f"{run_dir}: the recording has no step to branch from")
        if seq is None or len(seq) != rec.meta.get("n_source_scans"):
            seq = rec.open_sequence()
        times, by_replay = branch_start(rec, seq, cache_root, repeats)
        t1 = time.perf_counter()
        cold_rec = recording.open(run_dir)
        loc = open_branch(cold_rec, rec.n - 1, cache_root=cache_root)
        cold_s = time.perf_counter() - t1
        loc.close()
        particles = float(np.mean(rec.n_particles))
        size = sizes(rec)
    median = float(np.median(times))
    worst_replay = max(by_replay)
    return {
        "recorded_steps": rec.n,
        "particles_mean": round(particles, 1),
        "record_s": round(record_s, 1) if record_s > 0.5 else None,
        "branch_start_s_median": round(median, 3),
        "branch_start_s_by_replayed_steps": {
            str(r): round(float(np.median(v)), 3) for r, v in sorted(by_replay.items())
        },
        "branch_start_s_worst_replay_median": round(float(np.median(by_replay[worst_replay])), 3),
        "branch_start_cold_s": round(cold_s, 3),
        "target_start_s": TARGET_START_S,
        **size,
        "budget_mb_per_1000": BUDGET_MB_PER_1000,
        "met": bool(median <= TARGET_START_S and size["checkpoints_and_per_step_mb_per_1000"] <= BUDGET_MB_PER_1000),
        "repeats": repeats,
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
    }
