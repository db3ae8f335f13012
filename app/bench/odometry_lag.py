"""The odometry behind the clock: what the localizer shows when KISS-ICP cannot keep up.

``lidarloc bench odometry-lag [--pause-ms P] [--runs N] [--json]``: the built-in town's drive
played in real time by ``lidarloc run --clock realtime`` (one process per run, as a user starts
it), its KISS-ICP child process stopped (SIGSTOP) ``P`` ms of every 100 ms and let go again
(SIGCONT): a machine whose other work takes that share of the odometry's core. Finished scan-to-map
matches then wait for the odometry to land, the filter goes uncorrected, and a drift must not
stay green. Per run: scans green while more than 5 m off, false fires, withdrawals, losses, RMSE
after localization, matches landed, accepted and agreeing before they could land, the odometry's
lag behind the current scan (median, 90th percentile, max) and late scans.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from .common import load_avg, machine

PERIOD_S = 0.1  # the pause repeats every 100 ms
ODOMETRY_CHILD = "lidarloc.core.odometry.worker"  # the KISS-ICP child's module (its command line)


def odometry_child(parent: int) -> int | None:
    """The pid of ``parent``'s KISS-ICP child process, or None (not started yet, or gone)."""
    import psutil

    try:
        children = psutil.Process(parent).children()
    except psutil.Error:  # the run ended
        return None
    for child in children:
        try:
            if ODOMETRY_CHILD in child.cmdline():
                return child.pid
        except psutil.Error:  # ended meanwhile
            continue
    return None


class Pauser:
    """Stops ``parent``'s KISS-ICP child ``pause_s`` of every ``PERIOD_S`` (and its replacement, if
    it is restarted) until :meth:`stop`; the child is always let go again."""

    def __init__(self, parent: int, pause_s: float):
        self.parent, self.pause_s = parent, pause_s
        self.pauses = 0
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="odometry-pauser", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        child = None
        while not self._done.is_set():
            if child is None:
                child = odometry_child(self.parent)
                if child is None:
                    self._done.wait(0.05)
                    continue
            try:
                os.kill(child, signal.SIGSTOP)
                try:
                    self._done.wait(self.pause_s)
                finally:
                    os.kill(child, signal.SIGCONT)
                self.pauses += 1
            except ProcessLookupError:
                child = None  # gone (the run ended, or the child was restarted)
                continue
            self._done.wait(max(0.0, PERIOD_S - self.pause_s))

    def stop(self) -> None:
        self._done.set()
        self._thread.join()


def _lag(run_dir: Path) -> dict:
    """The odometry's lag behind the current scan, in scans, from the run's recording."""
    from ...core.runs.branch import open_recording

    rec = open_recording(run_dir)
    used = np.asarray(rec.field("odom_used"), np.int64)
    scans = np.asarray(rec.field("scan_index"), np.int64)
    lag = (scans - used)[used >= 0]
    if not len(lag):
        return {"lag_scans_median": None, "lag_scans_p90": None, "lag_scans_max": None}
    return {
        "lag_scans_median": float(np.median(lag)),
        "lag_scans_p90": float(np.percentile(lag, 90)),
        "lag_scans_max": int(lag.max()),
    }


KEYS = (
    "localized_wrong_scans",
    "false_fire",
    "withdrawals",
    "spurious_withdrawals",
    "losses",
    "localized_at_scan",
    "rmse_after_localized_m",
    "s2m_landed",
    "s2m_accepted",
    "s2m_agreed_early",
    "late_scans",
    "max_lag_ms",
)


def one_run(out: Path, seed: int, pause_ms: float, scans: int | None, cache_root) -> dict:
    """One ``lidarloc run --clock realtime`` with its KISS-ICP child paused; its figures."""
    cmd = [sys.executable, "-m", "lidarloc.app.cli", "run", "--clock", "realtime", "--seed", str(seed)]
    cmd += ["--out", str(out), "--json"]
    if scans is not None:
        cmd += ["--scans", str(scans)]
    if cache_root is not None:
        cmd += ["--cache", str(cache_root)]
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "run.err", "wb") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        pauser = Pauser(proc.pid, pause_ms / 1000.0) if pause_ms > 0 else None
        try:
            code = proc.wait()
        finally:
            if pauser is not None:
                pauser.stop()
            if proc.poll() is None:
                proc.terminate()
                proc.wait()
    if code != 0:
        last = (out / "run.err").read_text(errors="replace").strip().splitlines()[-1:] or ["no message"]
        raise LidarlocError(f"the run with seed {seed} failed (exit {code}): {last[0]}")
    pauses = 0 if pauser is None else pauser.pauses
    if pause_ms > 0 and pauses == 0:
        raise LidarlocError(f"the run with seed {seed}: its KISS-ICP child was never found to pause")
    summary = json.loads((out / "summary.json").read_text())
    row = {key: summary.get(key) for key in KEYS}
    row.update(_lag(out), seed=seed, pauses=pauses)
    return row


def run(out: Path, pause_ms: float = 30.0, runs: int = 3, scans: int | None = None, cache_root=None) -> dict:
    if not 0.0 <= pause_ms < PERIOD_S * 1000.0:
        raise LidarlocError(f"--pause-ms must be in [0, {PERIOD_S * 1000:.0f}) (got {pause_ms:g})")
    if pause_ms > 0 and not hasattr(signal, "SIGSTOP"):
        raise LidarlocError("bench odometry-lag pauses the KISS-ICP child with SIGSTOP (POSIX only)")
    load_start = load_avg()
    t0 = time.perf_counter()
    rows = [one_run(Path(out) / f"run-{seed}", seed, pause_ms, scans, cache_root) for seed in range(runs)]
    result = {
        "pause_ms_per_100": pause_ms,
        "runs": rows,
        "localized_wrong_scans": int(sum(r["localized_wrong_scans"] or 0 for r in rows)),
        "false_fires": int(sum(bool(r["false_fire"]) for r in rows)),
        "withdrawals": int(sum(r["withdrawals"] or 0 for r in rows)),
        "spurious_withdrawals": int(sum(r["spurious_withdrawals"] or 0 for r in rows)),
        "elapsed_s": round(time.perf_counter() - t0, 1),
        "load_avg": [round(load_start, 1), round(load_avg(), 1)],
        "machine": machine(),
    }
    return result
