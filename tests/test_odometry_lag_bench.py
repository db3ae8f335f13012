"""``lidarloc bench odometry-lag``: KISS-ICP's child paused a share of every 100 ms, as on a busy
machine (app/bench/odometry_lag.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from helpers import wait_for
from lidarloc.app.bench.odometry_lag import ODOMETRY_CHILD, Pauser, odometry_child, run
from lidarloc.core.errors import LidarlocError


def _state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0]


def test_the_pauser_stops_only_the_odometry_child_and_always_lets_it_go():
    import os

    busy = "while True: pass"
    other = subprocess.Popen([sys.executable, "-c", busy])
    kiss = subprocess.Popen([sys.executable, "-c", busy, ODOMETRY_CHILD])  # named as the real one
    try:
        wait_for(lambda: odometry_child(os.getpid()) == kiss.pid, 10, "the child to be found")
        pauser = Pauser(os.getpid(), 0.05)
        stopped = []
        wait_for(lambda: stopped.append(_state(kiss.pid)) or "T" in stopped, 10, "the child to be stopped")
        wait_for(lambda: pauser.pauses >= 3, 10, "three pauses")
        assert _state(other.pid) != "T"
        pauser.stop()
        assert _state(kiss.pid) != "T"  # let go, whenever the pauser was stopped
    finally:
        for p in (other, kiss):
            p.kill()
            p.wait()


def test_a_pause_of_a_whole_period_is_refused(tmp_path):
    with pytest.raises(LidarlocError, match=r"--pause-ms must be in \[0, 100\)"):
        run(tmp_path, pause_ms=100.0)


@pytest.mark.slow
def test_a_short_run_behind_a_paused_odometry_reports_its_figures(tmp_path, default_town_cache):
    # the bench runs the default town: its map comes from the session's cache
    result = run(tmp_path, pause_ms=30.0, runs=1, scans=40, cache_root=default_town_cache)
    (row,) = result["runs"]
    assert row["seed"] == 0 and row["lag_scans_max"] is not None and row["lag_scans_max"] >= 0
    assert row["pauses"] > 0  # the KISS-ICP child was found and paused
    assert isinstance(row["localized_wrong_scans"], int) and row["late_scans"] is not None
    assert result["localized_wrong_scans"] == row["localized_wrong_scans"]
    assert (tmp_path / "run-0" / "summary.json").exists()
