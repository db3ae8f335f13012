"""``lidarloc bench soak`` on a short loop: a real ``demo --loop`` in a child process, sampled,
stopped by SIGTERM, with nothing left behind; and its growth arithmetic."""

from __future__ import annotations

import csv
import json

import pytest
from helpers import MAPPING_SCANS
from lidarloc.app.bench import soak


def test_growth_is_measured_from_the_first_sample_after_the_first_loop():
    rows = [{"t_s": t, "rss_mb": m} for t, m in [(0, 100.0), (10, 400.0), (20, 410.0), (30, 415.5)]]
    assert soak.growth(rows, 10, "rss_mb") == 15.5
    assert soak.growth(rows, 30, "rss_mb") is None  # one sample after it: no growth to speak of


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_short_soak_loops_samples_and_stops_cleanly(cache_root, tmp_path):
    command = ["demo", "--scans", "20", "--set", f"town.n_scans={MAPPING_SCANS}"]
    r = soak.run(command, minutes=0.5, out_dir=tmp_path, sample_s=2.0, cache=str(cache_root), client="socket")
    assert r["client"] == "one websocket tab"
    assert r["loops"] >= 1 and r["loop_lines"][0]["scans"] == 20, r
    assert not r["crashed"] and r["exit_code"] == 0, r  # SIGTERM stops it as Ctrl-C does
    assert r["orphans_after_stop"] == 0, r["orphan_commands"]
    rows = list(csv.DictReader(open(tmp_path / "soak.csv")))
    assert len(rows) == r["samples"] >= 5 and float(rows[0]["rss_mb"]) > 100 and int(rows[0]["children"]) >= 1
    assert (tmp_path / "soak.png").stat().st_size > 1000
    # every loop is a run of its own, recorded (the viewer's default budget keeps them all here)
    assert len(list((tmp_path / "runs").glob("run*/recording/index.json"))) >= r["loops"]
    json.dumps(r)  # what --json prints
