"""Stand-in run functions for the sweep executor's tests: deterministic per seed, quick, and
importable by the process pool's and Ray's workers (tests/ is on their path)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np


def fake_run(run_dir: str, a: float, b: float, seed: int, work_s: float = 0.0, fail_at: float | None = None) -> dict:
    """A "run": a seeded number from (a, b, seed), its folder's summary.json written last (as a
    real run writes it), and one line in runs/done.log per run that got that far."""
    if fail_at is not None and a == fail_at and seed == 0:
        raise ValueError(f"a = {a} is out of range")
    if work_s:
        time.sleep(work_s)  # the run's own work, not a wait for another process
    rng = np.random.default_rng([seed, int(1000 * a), int(1000 * b)])
    summary = {"rmse_after_localized_m": float(a * b + rng.random()), "seed": seed, "pid": os.getpid()}
    folder = Path(run_dir)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder.parent.parent / "done.log", "a") as log:
        log.write(f"{folder.parent.name}/{folder.name}\n")
    tmp = folder / "summary.json.tmp"
    tmp.write_text(json.dumps(summary))
    os.replace(tmp, folder / "summary.json")
    return summary


def fake_localize(spec_d, cfg_d, seed, cache_root, run_dir, numba_threads, preset=None, record=False) -> dict:
    """A seeded "run" whose RMSE after localization is lowest at pf.sigma = 1 and which fires
    falsely above pf.sigma = 2.5: summary.json and scans.csv as a real run writes them."""
    sigma = float(cfg_d["pf"]["sigma"])
    rng = np.random.default_rng([seed, int(1e6 * sigma)])
    false_fire = sigma > 2.5
    rmse = (sigma - 1.0) ** 2 + 0.1 + 0.01 * rng.random()
    folder = Path(run_dir)
    folder.mkdir(parents=True, exist_ok=True)
    error = 9.0 if false_fire else rmse
    (folder / "scans.csv").write_text(f"scan,localized,error_m\n0,0,20.0\n1,1,{error:f}\n2,1,{error:f}\n")
    summary = {"seed": seed, "rmse_after_localized_m": rmse, "false_fire": false_fire, "metrics": {}}
    (folder / "summary.json").write_text(json.dumps(summary))
    return summary


def no_prepare(spec_d, cfg_d, cache, threads) -> None:
    """The fake runs need no map."""
