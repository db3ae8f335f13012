"""The scripts in examples/ run on the public API and do what their docstrings say."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from lidarloc.core.runs import recording

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run_example(name: str, *args, cwd: Path, cache: Path) -> str:
    """The example run as a user runs it, its maps cached in the session's cache (not the user's)."""
    env = dict(os.environ, LIDARLOC_CACHE=str(cache))
    r = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


@pytest.fixture(scope="module")
def recorded_run(recorded_town_run_40):
    """A recorded run of the town's first 40 scans (the session's, shared with the branching tests)."""
    return recorded_town_run_40


@pytest.mark.slow
def test_plot_recording_draws_n_eff_and_the_error(recorded_run, tmp_path, cache_root):
    out = run_example("plot_recording.py", recorded_run, "--out", tmp_path / "run.png", cwd=tmp_path, cache=cache_root)
    assert (tmp_path / "run.png").stat().st_size > 10_000
    n = recording.open(recorded_run).n
    assert out.startswith(f"{n} steps;") and n == 40


@pytest.mark.slow
def test_branch_and_compare_continues_with_another_sigma(recorded_run, tmp_path, cache_root):
    out = run_example(
        "branch_and_compare.py",
        recorded_run,
        "--step",
        "20",
        "--sigma",
        "0.7",
        "--out",
        tmp_path / "branch",
        cwd=tmp_path,
        cache=cache_root,
    )
    m = re.search(r"RMSE original σ ([\d.]+) m, σ 0.7 ([\d.]+) m", out)
    assert m, out
    assert float(m.group(1)) < 1.0 and float(m.group(2)) < 1.0  # both localized runs
    rows = (tmp_path / "branch" / "scans.csv").read_text().splitlines()
    assert len(rows) == 1 + 40  # the branch's whole run, scans 0–39


@pytest.mark.slow
def test_localize_a_bag_in_a_map_file(kitti_recordings, drive_maps, tmp_path, cache_root):
    out = run_example(
        "localize_bag_in_map.py",
        drive_maps["local"],
        kitti_recordings["mcap"],
        kitti_recordings["tum"],
        "--out",
        tmp_path / "error.png",
        cwd=tmp_path,
        cache=cache_root,
    )
    m = re.search(r"localized at scan (\d+); RMSE after: ([\d.]+) m", out)
    assert m, out
    assert float(m.group(2)) < 0.5
    assert (tmp_path / "error.png").stat().st_size > 10_000
