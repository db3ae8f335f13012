"""``lidarloc bench soak`` on a short loop: a real ``demo --loop`` in a child process, sampled,
stopped by SIGTERM, with nothing left behind; and its growth arithmetic."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys

import psutil
import pytest
from helpers import MAPPING_SCANS, process_gone, wait_for
from lidarloc.app.bench import soak


def test_growth_is_measured_from_the_first_sample_after_the_first_loop():
    rows = [{"t_s": t, "rss_mb": m} for t, m in [(0, 100.0), (10, 400.0), (20, 410.0), (30, 415.5)]]
    assert soak.growth(rows, 10, "rss_mb") == 15.5
    assert soak.growth(rows, 30, "rss_mb") is None  # one sample after it: no growth to speak of


def test_memory_growth_compares_windows_not_single_samples():
    # flat at 400 MB with a 60 MB spike in every fifth sample (a match in flight), one per 10 s
    flat = [{"t_s": 10.0 * i, "rss_mb": 400.0 + (60.0 if i % 5 == 4 else 0.0)} for i in range(200)]
    assert soak.growth(flat, 0, "rss_mb") == 60.0  # the last sample caught a spike
    assert soak.memory_growth(flat, 0, "rss_mb") == 0.0
    # a real leak: +1 MB a minute for 33 minutes, spikes and all
    leak = [{"t_s": r["t_s"], "rss_mb": r["rss_mb"] + r["t_s"] / 60.0} for r in flat]
    # the leak between the windows' centres (2.5 and 30.7 min) is 28.2 MB
    assert soak.memory_growth(leak, 0, "rss_mb") == pytest.approx(28.2, abs=0.5)
    assert soak.memory_growth(leak, 1990, "rss_mb") is None  # one sample after the first loop
    # a short run: the windows shrink to a third of the span each, never overlapping
    short = [{"t_s": 10.0 * i, "rss_mb": 100.0 + i} for i in range(10)]
    assert soak.memory_growth(short, 0, "rss_mb") == 6.0  # samples 0–3 against 6–9


def test_a_loop_line_is_read_with_and_without_its_garbage_collections():
    line = "loop 3: 1200 scans, 1 late, largest lag 0.102 s, 4 full garbage collections (longest 1.5 ms)"
    assert soak.parse_loop_line(line) == {
        "loop": 3,
        "scans": 1200,
        "late": 1,
        "max_lag_s": 0.102,
        "full_collections": 4,
        "longest_full_collection_ms": 1.5,
    }
    older = soak.parse_loop_line("loop 2: 20 scans, 0 late, largest lag 0.0 s")
    assert older["scans"] == 20 and older["full_collections"] is None
    assert soak.parse_loop_line("ready: playing") is None
    loops = [{"full_collections": 2, "longest_full_collection_ms": 1.5}, older]
    assert soak._total(loops, "full_collections") == 2 and soak._largest(loops, "longest_full_collection_ms") == 1.5


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_short_soak_loops_samples_and_stops_cleanly(cache_root, tmp_path):
    command = ["demo", "--scans", "20", "--set", f"town.n_scans={MAPPING_SCANS}"]
    # 15 s after the viewer is ready: loops of the 20 scans (2 s of the drive each, on the
    # real-time clock) and ~8 samples; how memory holds over hours is `lidarloc bench soak`'s job
    r = soak.run(command, minutes=0.25, out_dir=tmp_path, sample_s=2.0, cache=str(cache_root), client="socket")
    assert r["client"] == "one websocket tab"
    assert r["loops"] >= 1 and r["loop_lines"][0]["scans"] == 20, r
    assert all(x["full_collections"] is not None for x in r["loop_lines"]), r["loop_lines"]  # counted, read
    assert not r["crashed"] and r["exit_code"] == 0, r  # SIGTERM stops it as Ctrl-C does
    assert r["orphans_after_stop"] == 0, r["orphan_commands"]
    rows = list(csv.DictReader(open(tmp_path / "soak.csv")))
    assert len(rows) == r["samples"] >= 5 and float(rows[0]["rss_mb"]) > 100 and int(rows[0]["children"]) >= 1
    assert (tmp_path / "soak.png").stat().st_size > 1000
    # every loop is a run of its own, recorded (the viewer's default budget keeps them all here)
    assert len(list((tmp_path / "runs").glob("run*/recording/index.json"))) >= r["loops"]
    json.dumps(r)  # what --json prints


def test_sigterm_to_the_benchmark_stops_its_viewer_too(cache_root, tmp_path):
    """``bench soak`` stopped by SIGTERM (a service manager, ``kill``) runs its cleanup as on
    Ctrl-C: the viewer it started, in a session of its own, does not outlive it."""
    cmd = [sys.executable, "-m", "lidarloc.app.cli", "bench", "soak", "--minutes", "5", "--client", "none"]
    cmd += ["--scans", "20", "--set", f"town.n_scans={MAPPING_SCANS}", "--cache", str(cache_root)]
    cmd += ["--out", str(tmp_path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: (tmp_path / "soak.csv").is_file(), timeout=300, what="the soak's first sample")
        viewers = [p.pid for p in psutil.Process(proc.pid).children(recursive=True)]
        assert viewers, "the soak's viewer is running"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    try:
        assert proc.returncode == 130 and "Traceback" not in err, err  # as Ctrl-C
        for pid in viewers:
            wait_for(lambda pid=pid: process_gone(pid), timeout=10, what=f"the viewer's process {pid} to end")
    finally:  # a failing test leaves nothing running either
        for pid in viewers:
            if not process_gone(pid):
                psutil.Process(pid).kill()
