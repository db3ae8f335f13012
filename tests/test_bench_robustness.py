"""``lidarloc bench robustness`` (app/bench/robustness.py): the matrix and its slices, each cell's
configuration, bad slice values as one line, and a one-cell slice end to end (its four outputs,
the world reaching the run, resume)."""

import csv
import json

import pytest
from helpers import cli_here, run_cli
from lidarloc.core.config import PRESETS

SMALL_TOWN = ("--set", "town.extent_m=100", "--set", "town.n_scans=40")


def cli(*args, cache):
    return run_cli("bench", "robustness", *args, cache=cache)


def test_the_time_estimate_counts_each_configuration_at_its_own_pace():
    from types import SimpleNamespace

    from lidarloc.app.bench.robustness import CONFIGS, PREPARE_S_PER_SCAN, RUN_S_PER_SCAN, Matrix, estimate_s

    assert set(RUN_S_PER_SCAN) == set(CONFIGS)
    plans = {c.name: SimpleNamespace(todo=[(0, "d"), (1, "d")]) for c in Matrix(changes=(0.3,)).cells(real=True)}
    per_world = 2 * 100 * sum(RUN_S_PER_SCAN.values())
    # 12 worlds and the real drive, 2 runs of 100 scans per cell; 11 worlds left to prepare
    assert estimate_s(plans, 11, 100, 2) == pytest.approx((13 * per_world + 11 * 100 * PREPARE_S_PER_SCAN) / 2)


# ------------------------------------------------------------------------------ the matrix
def test_the_full_matrix_has_108_cells_and_slices_restrict_it():
    from lidarloc.app.bench.robustness import Matrix, parse_matrix

    full = Matrix()
    cells = full.cells(real=False)
    assert len(cells) == 3 * 2 * 3 * 2 * 3 == 108
    assert len({c.name for c in cells}) == 108
    assert len(full.cells(real=True)) == 111 and [c.name for c in full.cells(real=True)[-3:]] == [
        "real-paper",
        "real-default",
        "real-no-S2M",
    ]
    part = parse_matrix("0, 0.3", "on", "hdl64e", "off,on", "Paper,default")
    assert part.changes == (0.0, 0.3) and part.traffic == (True,) and part.sensors == ("hdl64e",)
    assert part.skew == (False, True) and part.configs == ("paper", "default")
    assert len(part.cells(real=False)) == 2 * 1 * 1 * 2 * 2
    assert parse_matrix("0.3,0.3", "on", "vlp16", "on", "no-s2m").configs == ("no-S2M",)  # once each


def test_each_cell_runs_its_preset_and_world_over_the_users_settings():
    from lidarloc.app.bench.robustness import Cell, World, cell_config

    world = World(0.6, True, "os1-128", True)
    paper = cell_config(Cell(world, "paper"), None, ["pf.n_particles=500"])
    default = cell_config(Cell(world, "default"), None, ["pf.n_particles=500"])
    no_s2m = cell_config(Cell(world, "no-S2M"), None, ["pf.n_particles=500"])
    for cfg in (paper, default, no_s2m):
        assert (cfg.town.changes, cfg.town.traffic, cfg.town.sensor, cfg.town.skew) == (0.6, True, "os1-128", True)
        assert cfg.pf.n_particles == 500 and cfg.localize.recorded_odometry
    assert paper.s2m.reject_if_weight_drops is PRESETS["paper"]["s2m.reject_if_weight_drops"] is True
    assert default.s2m.reject_if_weight_drops is False and default.s2m.enabled and not no_s2m.s2m.enabled
    assert default.to_dict() == {**no_s2m.to_dict(), "s2m": {**no_s2m.to_dict()["s2m"], "enabled": True}}
    real = cell_config(Cell(None, "paper"), None, None)
    assert real.s2m.reject_if_weight_drops is True


@pytest.mark.parametrize(
    "args,needle",
    [
        (("--changes", "0,1.5"), "--changes: '1.5' is not a share in [0, 1]"),
        (("--changes", "lots"), "--changes: 'lots' is not a share"),
        (("--traffic", "heavy"), "--traffic: 'heavy' is not on or off"),
        (("--skew", ""), "--skew: give at least one value"),
        (("--sensors", "hdl64e,lidar9000"), "unknown sensor 'lidar9000'"),
        (("--configs", "fast"), "unknown configuration 'fast'"),
        (("--set", "town.sensor=vlp16"), "the matrix sets it; restrict the matrix with --sensors"),
        (("--runs", "0"), "--runs and --workers must be ≥ 1"),
        (("--kitti-raw", "somewhere"), "--kitti-odometry and --kitti-raw do not apply"),
    ],
)
def test_bad_slice_values_are_one_line(tmp_path, args, needle):
    out = tmp_path / "out"
    # by the entry point in this process: the refusal's output, without a child's start-up (the
    # command as users start it: the one-cell slice below)
    r = cli_here("bench", "robustness", *args, "--out", str(out), cache=tmp_path / "cache")
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert needle in lines[0], lines[0]
    assert not out.exists()


# ------------------------------------------------------------------------------ end to end
@pytest.mark.timeout(300)
def test_one_cell_slice_writes_the_table_csv_json_and_heat_map(tmp_path, cache_root):
    from lidarloc.app.bench.robustness_report import COLUMNS

    out = tmp_path / "robust"
    args = (
        "--runs",
        "1",
        "--scans",
        "15",
        "--changes",
        "0.3",
        "--traffic",
        "on",
        "--sensors",
        "vlp16",
        "--skew",
        "on",
        "--configs",
        "no-S2M",
        "--no-real",
        "--workers",
        "1",
        *SMALL_TOWN,
        "--out",
        str(out),
    )
    r = cli(*args, "--json", cache=cache_root)
    assert r.returncode == 0, r.stderr
    assert "1 cell × 1 run of up to 15 scans" in r.stderr and "estimated" in r.stderr
    summary = json.loads(r.stdout)
    assert summary == json.loads((out / "summary.json").read_text())
    assert summary["matrix"] == {
        "changes": [0.3],
        "traffic": ["on"],
        "sensors": ["vlp16"],
        "skew": ["on"],
        "configs": ["no-S2M"],
    }
    assert summary["real"] is False and summary["runs"] == 1 and summary["scans"] == 15
    [cell] = summary["cells"]
    assert list(cell) == list(COLUMNS)
    assert (cell["changes"], cell["traffic"], cell["sensor"], cell["skew"], cell["config"]) == (
        0.3,
        "on",
        "vlp16",
        "on",
        "no-S2M",
    )
    assert cell["runs"] == 1 and cell["scans"] == 15 and cell["pf_ms_median"] > 0
    assert 0.0 <= cell["success"] <= 1.0 and cell["false_fire_rate"] in (0.0, 1.0)
    for k in "ABCDE":
        assert cell[f"{k}_success"] in (0.0, 1.0)
    # the CSV: the same columns, one row
    with open(out / "cells.csv", newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert tuple(reader.fieldnames) == COLUMNS and len(rows) == 1
    assert rows[0]["cell"] == cell["cell"] and rows[0]["sensor"] == "vlp16" and rows[0]["config"] == "no-S2M"
    # the markdown table
    report = (out / "report.md").read_text()
    assert "| changes | traffic | sensor | skew | config | success | RMSE after | A | B | C | D | E |" in report
    assert "| 0.3 | on | vlp16 | on | no-S2M |" in report and "heatmap.png" in report
    assert (out / "heatmap.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the cell's run met the cell's world, with S2M off, and says which preset it started from
    run = json.loads((out / "cells" / cell["cell"] / "runs" / "seed_000" / "summary.json").read_text())
    assert run["world"]["changes"] == 0.3 and run["world"]["traffic"] is True
    assert run["world"]["sensor"] == "vlp16" and run["world"]["skew"] is True
    assert run["s2m"] is False and run["preset"] == "default" and run["scans"] == 15
    # resumable: a second call runs nothing again and reports the same
    stamp = (out / "cells" / cell["cell"] / "runs" / "seed_000" / "summary.json").stat().st_mtime_ns
    again = cli(*args, "--json", cache=cache_root)
    assert again.returncode == 0, again.stderr
    assert "0 to do, 1 resumed" in again.stderr
    assert (out / "cells" / cell["cell"] / "runs" / "seed_000" / "summary.json").stat().st_mtime_ns == stamp
    assert json.loads(again.stdout)["cells"] == summary["cells"]
