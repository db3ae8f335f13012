"""``lidarloc bench sweep``: what running a sweep on Ray costs beside the local process pool.

The same sweep — ``runs`` runs of a fixed amount of CPU work each, ``workers`` at a time — goes
through both executors, one after the other. A run here burns ``run_s`` seconds of CPU instead of
localizing, so the runs' own time is the same on both and what differs is the scheduling: handing
a run out, starting or reusing its worker, the trial bookkeeping, collecting the result. Ray's own
start (``ray.init``) is measured apart: it is paid once per sweep, not per run.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

from rich.console import Console

from ...core.errors import LidarlocError
from .bookkeeping import Run
from .executor import execute


def burn(run_dir: str, seconds: float) -> dict:
    """A stand-in run: ``seconds`` of this process's CPU time, its summary.json written last."""
    t0, c0 = time.perf_counter(), time.process_time()
    x = 0
    while time.process_time() - c0 < seconds:
        for i in range(20000):
            x += i * i
    summary = {"run_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    (Path(run_dir) / "summary.json").write_text(json.dumps(summary))
    return summary


def _sweep(out: Path, runs: int, workers: int, run_s: float, ray: str | None) -> tuple[float, list[float]]:
    plan = [Run((i,), f"run {i}", str(out / f"run_{i:03d}"), (str(out / f"run_{i:03d}"), run_s)) for i in range(runs)]
    own: list[float] = []
    t0 = time.perf_counter()
    tally = execute(
        burn,
        {"run": list(range(runs))},
        plan,
        workers,
        on_done=lambda run, s: own.append(s["run_s"]),
        ray=ray,
        ray_dir=out / "ray",
        console=Console(file=open(os.devnull, "w")),
    )
    if not tally.finished:
        raise LidarlocError(f"the sweep on {'Ray' if ray else 'the process pool'} did not finish: no figures")
    return time.perf_counter() - t0, own


def measure(runs: int = 16, workers: int = 2, run_s: float = 20.0) -> dict:
    """Wall time of the same sweep on the process pool and on a local Ray instance."""
    from .cluster import connect

    with tempfile.TemporaryDirectory(prefix="lidarloc-sweep-bench-") as tmp:
        pool_s, pool_own = _sweep(Path(tmp) / "pool", runs, workers, run_s, None)
        t0 = time.perf_counter()
        connect("local", workers)
        ray_start_s = time.perf_counter() - t0
        ray_s, ray_own = _sweep(Path(tmp) / "ray", runs, workers, run_s, "local")
    own = sorted(pool_own + ray_own)[len(pool_own + ray_own) // 2]
    per_run = (ray_s - pool_s) * workers / runs
    return {
        "runs": runs,
        "workers": workers,
        "run_cpu_s": run_s,
        "run_wall_s_median": own,
        "pool_wall_s": pool_s,
        "ray_wall_s": ray_s,
        "ray_start_s": ray_start_s,
        "ray_over_pool": ray_s / pool_s,
        "overhead_per_run_s": per_run,
        "overhead_share_of_run": per_run / own,
        "load_1min": os.getloadavg()[0],
    }
