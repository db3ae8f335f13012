"""evo's APE and RPE of a run: computed through evo (not re-implemented), equal to what the
evo_ape / evo_rpe commands print for the written files, no alignment, in summary.json and in
``compare``."""

from __future__ import annotations

import io
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from lidarloc.core.runs.trajectory_errors import trajectory_errors
from rich.console import Console

EVO_BIN = Path(sys.executable).parent


def evo_rmse(command: str, gt: Path, est: Path) -> float:
    """The rmse line of ``evo_ape tum GT EST`` / ``evo_rpe tum GT EST`` (their defaults)."""
    out = subprocess.run(
        [str(EVO_BIN / command), "tum", str(gt), str(est)], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    return float(re.search(r"^\s*rmse\s+([0-9.eE+-]+)\s*$", out, re.M).group(1))


def write_tum(path: Path, t: np.ndarray, xyz: np.ndarray, yaw: np.ndarray) -> Path:
    q = np.c_[np.zeros((len(t), 2)), np.sin(yaw / 2), np.cos(yaw / 2)]
    np.savetxt(path, np.c_[t, xyz, q], fmt="%.6f")
    return path


def test_evo_figures_equal_the_evo_commands_and_are_not_aligned(tmp_path):
    rng = np.random.default_rng(3)
    t = np.arange(60) * 0.1
    truth = np.c_[t * 8.0, 5 * np.sin(t), np.zeros_like(t)]
    yaw = 0.3 * t
    gt = write_tum(tmp_path / "groundtruth_tum.txt", t, truth, yaw)
    # the estimate: 4 ms late (associated by time), a constant 3 m offset plus noise, one pose more
    est_xyz = truth + [3.0, 0.0, 0.0] + rng.normal(0, 0.2, truth.shape)
    est = write_tum(
        tmp_path / "trajectory_tum.txt", np.r_[t + 0.004, 6.5], np.r_[est_xyz, [[60.0, 0, 0]]], np.r_[yaw, 0.0]
    )
    got = trajectory_errors(est, gt)
    assert got["ape_rmse_m"] == pytest.approx(evo_rmse("evo_ape", gt, est), abs=1e-6)
    assert got["rpe_rmse_m"] == pytest.approx(evo_rmse("evo_rpe", gt, est), abs=1e-6)
    # not aligned: the 3 m offset is in the APE (an alignment would remove it)
    direct = float(np.sqrt(np.mean(np.sum((np.loadtxt(est)[:60, 1:4] - truth) ** 2, axis=1))))
    assert got["ape_rmse_m"] == pytest.approx(direct, abs=1e-5) and got["ape_rmse_m"] > 2.9


def test_without_matching_poses_the_figures_are_none(tmp_path):
    gt = write_tum(tmp_path / "gt.txt", np.arange(5) * 0.1, np.zeros((5, 3)), np.zeros(5))
    est = write_tum(tmp_path / "est.txt", 100 + np.arange(5) * 0.1, np.zeros((5, 3)), np.zeros(5))
    assert trajectory_errors(est, gt) == {"ape_rmse_m": None, "rpe_rmse_m": None}
    (tmp_path / "empty.txt").write_text("")
    assert trajectory_errors(tmp_path / "empty.txt", gt) == {"ape_rmse_m": None, "rpe_rmse_m": None}


def test_a_runs_summary_holds_evo_figures_of_its_written_files(recorded_town_run):
    run, summary = recorded_town_run
    on_disk = json.loads((run / "summary.json").read_text())
    gt, est = run / "groundtruth_tum.txt", run / "trajectory_tum.txt"
    for key, command in (("ape_rmse_m", "evo_ape"), ("rpe_rmse_m", "evo_rpe")):
        assert on_disk[key] == summary[key] is not None
        assert on_disk[key] == pytest.approx(evo_rmse(command, gt, est), abs=1e-6), key
    # beside the paper's metrics and the RMSE after localization, not instead of them
    assert "metrics" in on_disk and "rmse_after_localized_m" in on_disk


def test_compare_shows_the_evo_figures(recorded_town_run, tmp_path):
    from lidarloc.app.compare import compare_runs

    run, summary = recorded_town_run
    other = tmp_path / "copy"
    shutil.copytree(run, other)
    data = compare_runs([run, other], None, console=Console(file=io.StringIO()))
    for row in data["runs"]:
        assert row["ape_rmse_m"] == pytest.approx(summary["ape_rmse_m"])
        assert row["rpe_rmse_m"] == pytest.approx(summary["rpe_rmse_m"])
