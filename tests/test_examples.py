"""The scripts in examples/ run on the public API and do what their docstrings say."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from bagfixtures import kitti_drive, kitti_recordings  # noqa: F401  (fixtures)
from helpers import MAPPING_SCANS
from lidarloc.core.runs import recording

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run_example(name: str, *args, cwd: Path) -> str:
    r = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory, cache_root):
    """A recorded run of the town's first 40 scans (the short mapping drive the other tests cache)."""
    out = tmp_path_factory.mktemp("examples") / "run0"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "lidarloc.app.cli",
            "run",
            "--scans",
            "40",
            "--set",
            f"town.n_scans={MAPPING_SCANS}",
            "--set",
            "localize.recorded_odometry=true",
            "--cache",
            str(cache_root),
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return out


@pytest.mark.slow
def test_plot_recording_draws_n_eff_and_the_error(recorded_run, tmp_path):
    out = run_example("plot_recording.py", recorded_run, "--out", tmp_path / "run.png", cwd=tmp_path)
    assert (tmp_path / "run.png").stat().st_size > 10_000
    n = recording.open(recorded_run).n
    assert out.startswith(f"{n} steps;") and n == 40


@pytest.mark.slow
def test_branch_and_compare_continues_with_another_sigma(recorded_run, tmp_path, cache_root, monkeypatch):
    monkeypatch.setenv("LIDARLOC_CACHE", str(cache_root))
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
    )
    m = re.search(r"RMSE original σ ([\d.]+) m, σ 0.7 ([\d.]+) m", out)
    assert m, out
    assert float(m.group(1)) < 1.0 and float(m.group(2)) < 1.0  # both localized runs
    rows = (tmp_path / "branch" / "scans.csv").read_text().splitlines()
    assert len(rows) == 1 + 40  # the branch's whole run, scans 0–39


@pytest.mark.slow
def test_localize_a_bag_in_a_map_file(kitti_recordings, kitti_raw_seq, tmp_path):  # noqa: F811
    from lidarloc.core.config import Config
    from lidarloc.core.maps.mapfile_write import write_map
    from lidarloc.core.maps.mapping import build_prior_map

    write_map(tmp_path / "map.pcd", build_prior_map(kitti_raw_seq, Config().map, road_removal=False).points)
    out = run_example(
        "localize_bag_in_map.py",
        tmp_path / "map.pcd",
        kitti_recordings["mcap"],
        kitti_recordings["tum"],
        "--out",
        tmp_path / "error.png",
        cwd=tmp_path,
    )
    m = re.search(r"localized at scan (\d+); RMSE after: ([\d.]+) m", out)
    assert m, out
    assert float(m.group(2)) < 0.5
    assert (tmp_path / "error.png").stat().st_size > 10_000
