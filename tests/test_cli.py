"""The ``lidarloc`` command as a user runs it (a child process): every bad input named in the
brief is one line on stderr with exit code 2 and no half-written cache; ``map build --json``
and its cache; ``demo`` serves its page and ``run`` writes its results, and both stop on Ctrl-C."""

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from helpers import cli_here, make_odometry, run_cli

# Ctrl-C must stop a command within 2 s (the user's requirement; ``lidarloc bench stop`` measures
# it, ~0.35 s in the first scans of ``run``). These tests only catch a hang or a lost signal: a
# loaded 2-core machine can take seconds to schedule the child's exit, so they allow 10 s.
STOP_BOUND_S = 10.0


def cli(*args, env_cache):
    """A refusal, checked by the command's entry point in this process: the output is the
    command's, without a child's start-up. One refusal below and the commands that succeed or are
    stopped run as users start them (run_cli)."""
    return cli_here(*args, cache=env_cache)


def assert_one_line_error(result, *needles):
    assert result.returncode == 2, result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def corrupt(root: Path, how: str):
    d = root / "sequences" / "00" / "velodyne"
    if how == "size":
        with open(d / "000001.bin", "ab") as f:
            f.write(b"\0\0\0")
        return "000001.bin", "not a multiple of 16"
    if how == "empty":
        (d / "000001.bin").write_bytes(b"")
        return "000001.bin", "empty scan"
    if how == "nan":
        pts = np.fromfile(d / "000002.bin", dtype=np.float32).reshape(-1, 4)
        pts[5, 1] = np.nan
        pts.tofile(d / "000002.bin")
        return "000002.bin", "NaN"
    raise ValueError(how)


# ------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("how", ["size", "empty", "nan"])
def test_bad_scan_files_give_one_line_and_no_half_written_cache(tmp_path, how):
    root = make_odometry(tmp_path / "kitti")
    fname, needle = corrupt(root, how)
    cache = tmp_path / "cache"
    r = cli("map", "build", "--kitti-odometry", str(root), "--sequence", "00", env_cache=cache)
    assert_one_line_error(r, fname, needle)
    # nothing half-written: no map entry, and no temporary directory left behind
    assert not cache.exists() or not any(cache.iterdir())


@pytest.mark.parametrize("n_poses,word", [(5, "more poses"), (2, "fewer poses")])
def test_pose_count_mismatch(tmp_path, n_poses, word):
    root = make_odometry(tmp_path / "kitti", n_scans=3, n_poses=n_poses)
    r = cli("map", "build", "--kitti-odometry", str(root), "--sequence", "00", env_cache=tmp_path / "c")
    assert_one_line_error(r, "00.txt", word)


def test_missing_directory_and_unknown_sequence(tmp_path):
    r = run_cli("map", "build", "--kitti-odometry", str(tmp_path / "nope"), "--sequence", "00", cache=tmp_path / "c")
    assert_one_line_error(r, str(tmp_path / "nope"), "not found")
    root = make_odometry(tmp_path / "kitti")
    r = cli("map", "build", "--kitti-odometry", str(root), "--sequence", "42", env_cache=tmp_path / "c")
    assert_one_line_error(r, "unknown sequence id '42'", "found: 00")
    r = cli(
        "map",
        "build",
        "--kitti-raw",
        str(tmp_path / "nope"),
        "--date",
        "2011_09_26",
        "--drive",
        "0013",
        env_cache=tmp_path / "c",
    )
    assert_one_line_error(r, "not found")


def test_unreadable_config_via_cli(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("pf: {sigma: [")
    r = cli("map", "build", "--config", str(bad), "--scans", "1", env_cache=tmp_path / "c")
    assert_one_line_error(r, "bad.yaml", "unreadable config")
    r = cli("map", "build", "--set", "pf.sigma=0", "--scans", "1", env_cache=tmp_path / "c")
    assert_one_line_error(r, "sigma must be > 0")


# ------------------------------------------------------------------------------ map build
def test_map_build_json_and_cache(tmp_path):
    root = make_odometry(tmp_path / "kitti", n_scans=3, n_points=3000)
    args = ("map", "build", "--kitti-odometry", str(root), "--sequence", "00", "--json")
    first = run_cli(*args, cache=tmp_path / "c")
    assert first.returncode == 0, first.stderr
    a = json.loads(first.stdout)
    assert a["points"] > 0 and 0 < a["points_road_removed"] <= a["points"] and a["cached"] is False
    assert a["peak_rss_mb"] > 0 and a["seconds"] >= 0
    b = json.loads(run_cli(*args, cache=tmp_path / "c").stdout)
    assert b["cached"] is True and b["points"] == a["points"]


# ------------------------------------------------------------------------------ Ctrl-C
@pytest.mark.slow
def test_demo_serves_and_stops_on_ctrl_c(town_cache):
    """``lidarloc demo`` prints its URL, serves HTTP 200 on loopback, and ends on Ctrl-C."""
    env = dict(os.environ, LIDARLOC_CACHE=str(town_cache))
    # a short drive whose world is in the session's cache (the map of a short mapping drive); the
    # default town's first-start time is measured by `lidarloc bench startup` (BENCHMARKS.md)
    proc = subprocess.Popen(
        [sys.executable, "-m", "lidarloc.app.cli", "demo", "--port", "0", "--scans", "30", "--set", "town.n_scans=150"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    try:
        url, seen = None, ""
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and url is None:
            line = proc.stdout.readline()
            if not line:
                break
            seen += line
            m = re.search(r"lidarloc viewer: (http://[\w.\-]+:\d+)", line)
            if m:
                url = m.group(1)
        assert url is not None, seen
        assert url.startswith("http://127.0.0.1:"), "binds loopback by default"
        status = None
        while time.monotonic() < deadline and status is None:
            try:
                status = urllib.request.urlopen(url, timeout=5).status
            except OSError:
                time.sleep(0.2)  # retry pacing while the server comes up, not synchronisation
        assert status == 200
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        proc.wait(timeout=30)
        assert time.monotonic() - t0 <= STOP_BOUND_S, f"stopped after {time.monotonic() - t0:.2f} s"
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.slow
def test_run_ctrl_c_writes_results(tmp_path, cache_root):
    """``lidarloc run`` interrupted while localizing exits with 130 and still writes its results."""
    out = tmp_path / "run"
    env = dict(os.environ, LIDARLOC_CACHE=str(cache_root))
    # the localizer tests' town (a 150-scan mapping drive, 60 played): its map may already be in
    # the session's cache
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "lidarloc.app.cli",
            "run",
            "--out",
            str(out),
            "--scans",
            "60",
            "--set",
            "pf.n_particles=300",
            "--set",
            "town.n_scans=150",
        ],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    # wait until it is localizing (the progress line appears), then interrupt
    deadline = time.monotonic() + 240
    seen = ""
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        seen += line
        if "localizing" in line or line == "":
            break
    proc.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    proc.wait(timeout=30)
    assert time.monotonic() - t0 < STOP_BOUND_S, "Ctrl-C did not stop the run"
    assert proc.returncode == 130, seen + proc.stderr.read()
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"] is True
    assert (out / "scans.csv").is_file() and (out / "trajectory_kitti.txt").is_file()
