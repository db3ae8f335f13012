"""``lidarloc corpus``: the corpus file checked field by field, the example accepted as it is, a
corpus of short-town drives run on the process pool (each drive the same run as ``run_one`` of
that drive, a drive with a missing file failed alone, a second run doing nothing again), and the
health's stretches found on a table made by hand."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import run_cli
from lidarloc.core.errors import LidarlocError

SCANS = 3
# The short town's mapping drive (helpers.MAPPING_SCANS, whose world the session's cache holds),
# few particles, no S2M: what is tested is the running of drives, not localization, and a
# whole-map match on a drive's first scan costs seconds the replay would wait for.
SHORT = ["town.n_scans=150", "pf.n_particles=300", "s2m.enabled=false", "s2m.replay_process_nice=0"]
# figures measured in wall-clock time: the only ones two runs of one drive may differ in
TIMED = ("pf_ms_median", "s2m_ms_median", "scans_per_second", "cpu_ms_per_scan", "cpu_percent")


def write_corpus(folder: Path, data: dict, name: str = "corpus.yaml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def short_corpus(folder: Path) -> Path:
    return write_corpus(
        folder,
        {
            "defaults": {"scans": SCANS, "set": SHORT},
            "drives": [
                {"name": "plain", "seed": 0},
                {"name": "lived-vlp16", "world": "lived-in", "seed": 1, "set": ["town.sensor=vlp16"]},
                {"name": "moved-away", "bag": "logs/gone.mcap", "map": "maps/gone.pcd"},
                {"name": "damaged-map", "map": "maps/damaged.pcd"},
            ],
        },
    )


@pytest.fixture(scope="module")
def corpus_run(town_cache, tmp_path_factory):
    """The short corpus run once on a 2-worker pool: (its file, --out, corpus.json, the tally)."""
    from lidarloc.app.corpus.run import run_corpus
    from lidarloc.app.corpus.spec import load_corpus
    from rich.console import Console

    folder = tmp_path_factory.mktemp("corpus")
    path = short_corpus(folder)
    (folder / "maps").mkdir()
    (folder / "maps" / "damaged.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y\nnot a point cloud\n")
    out = folder / "out"
    report, tally = run_corpus(
        load_corpus(path), out, 2, cache_root=town_cache, console=Console(stderr=True, quiet=True)
    )
    return path, out, report, tally


def test_example_is_a_corpus_run_accepts(tmp_path):
    from lidarloc.app.corpus.example import example_corpus
    from lidarloc.app.corpus.spec import load_corpus

    path = tmp_path / "example.yaml"
    path.write_text(example_corpus(6, scans=20))
    corpus = load_corpus(path)
    assert [d.name for d in corpus.drives] == [
        "town0-hdl64e",
        "town0-vlp16",
        "town0-vlp32c",
        "town0-os1-128",
        "town1-hdl64e",
        "town1-vlp16",
    ]
    configs = [d.config_for() for d in corpus.drives]
    assert [c.town.sensor for c in configs] == ["hdl64e", "vlp16", "vlp32c", "os1-128", "hdl64e", "vlp16"]
    assert [d.spec.town_seed for d in corpus.drives] == [0, 0, 0, 0, 1, 1]
    assert all(c.town.traffic and c.town.changes == 0.3 and c.town.skew for c in configs)  # lived-in
    assert [c.town.traffic_seed for c in configs] == list(range(6))  # each drive its own day's traffic
    assert all(d.spec.scans == 20 and d.missing_path() is None for d in corpus.drives)


def test_drive_settings_come_in_order(tmp_path):
    """defaults' set, then the drive's, then the command's --set; a drive's fields replace the defaults'."""
    from lidarloc.app.corpus.spec import load_corpus

    path = write_corpus(
        tmp_path,
        {
            "defaults": {"seed": 4, "scans": 9, "set": ["pf.sigma=0.5", "pf.d_max=2"]},
            "drives": [{"name": "a", "set": ["pf.sigma=0.6"]}, {"name": "b", "seed": 7, "scans": 3}],
        },
    )
    a, b = load_corpus(path, ["pf.d_max=3"]).drives
    assert (a.config_for(["pf.d_max=3"]).pf.sigma, a.config_for(["pf.d_max=3"]).pf.d_max) == (0.6, 3.0)
    assert b.config_for().pf.sigma == 0.5 and (a.seed, b.seed, a.spec.scans, b.spec.scans) == (4, 7, 9, 3)


@pytest.mark.parametrize(
    "data, needle",
    [
        ({"drives": [{"name": "a", "bagg": "x.mcap"}]}, "drive 'a': unknown field 'bagg'"),
        ({"drives": [{"name": "a"}, {"name": "a", "town_seed": 1}]}, "drive 'a': duplicate name"),
        ({"drives": [{"town_seed": 1}]}, "drive 1: missing field 'name'"),
        ({"drives": [{"name": "k", "kitti_odometry": "/d", "sequence": 5}]}, "drive 'k': sequence: write it in quotes"),
        (
            {"drives": [{"name": "a", "set": ["pf.sigmx=1"]}]},
            "drive 'a': invalid configuration: unknown key 'pf.sigmx'",
        ),
        ({"drives": [{"name": "a", "world": "sunny"}]}, "drive 'a': invalid configuration: unknown world 'sunny'"),
        ({"drives": [{"name": "a", "gt": "gt.tum"}]}, "drive 'a': --gt applies to a recording"),
        ({"defaults": {"scan": 3}, "drives": [{"name": "a"}]}, "defaults: unknown field 'scan'"),
        ({"drives": []}, "drives: must be a list of at least one drive"),
        ({"drives": [{"name": "../up"}]}, "drive 1: name: '../up' must be"),
    ],
)
def test_bad_corpus_files_are_one_line_naming_drive_and_field(tmp_path, data, needle):
    from lidarloc.app.corpus.spec import load_corpus

    path = write_corpus(tmp_path, data)
    with pytest.raises(LidarlocError) as caught:
        load_corpus(path)
    message = str(caught.value)
    assert needle in message and "\n" not in message and message.startswith(str(path)), message


def test_bad_corpus_file_through_the_command_line(tmp_path):
    path = write_corpus(tmp_path, {"drives": [{"name": "a", "bagg": "x.mcap"}]})
    r = run_cli("corpus", "run", path, "--out", tmp_path / "out", cache=tmp_path / "cache")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "drive 'a': unknown field 'bagg'" in lines[0], r.stderr
    assert not (tmp_path / "out").exists()  # refused before anything was made


@pytest.mark.slow
def test_each_drive_is_the_run_one_of_that_drive(corpus_run, town_cache, tmp_path):
    from lidarloc.app.bench.localize import run_one
    from lidarloc.app.corpus.spec import load_corpus
    from lidarloc.core.runs import recording

    path, out, report, tally = corpus_run
    assert tally.done == 2 and sorted(report["drives"]) == ["lived-vlp16", "plain"]
    written = json.loads((out / "corpus.json").read_text())
    assert written["drives"].keys() == report["drives"].keys()
    for name, drive in report["drives"].items():
        folder = out / "drives" / name
        assert drive["summary"] == json.loads((folder / "summary.json").read_text())
        assert drive["summary"]["scans"] == SCANS and (folder / "scans.csv").is_file()
        assert recording.open(folder).n == SCANS  # what `lidarloc view --run` opens
        assert set(drive["health"]) >= {"first_fix", "withdrawals", "false_fires", "rmse_localized_m", "stretches"}
    lived = report["drives"]["lived-vlp16"]["summary"]
    assert lived["seed"] == 1 and lived["world"]["sensor"] == "vlp16" and lived["world"]["traffic"]
    # the lived-in drive again, run_one called directly with the drive's source, seed and configuration
    drive = next(d for d in load_corpus(path).drives if d.name == "lived-vlp16")
    cfg_d = drive.config_for().to_dict()
    cfg_d.pop("seed")
    direct = run_one(drive.spec.to_dict(), cfg_d, drive.seed, str(town_cache), str(tmp_path / "direct"), 1, record=True)
    untimed = {k: v for k, v in direct.items() if k not in TIMED}
    assert untimed == {k: v for k, v in lived.items() if k not in TIMED}
    columns = ("x", "y", "yaw", "n_eff", "inlier_share")
    ours = np.genfromtxt(out / "drives" / "lived-vlp16" / "scans.csv", delimiter=",", names=True)
    theirs = np.genfromtxt(tmp_path / "direct" / "scans.csv", delimiter=",", names=True)
    for c in columns:
        np.testing.assert_array_equal(ours[c], theirs[c])


@pytest.mark.slow
def test_failed_drives_fail_alone_and_a_second_run_runs_nothing(corpus_run, town_cache):
    path, out, report, _ = corpus_run
    assert list(report["drives_failed"]) == ["moved-away", "damaged-map"]  # in the corpus's order
    gone, damaged = report["drives_failed"].values()
    assert gone.startswith("bag: ") and gone.endswith("logs/gone.mcap does not exist")
    assert "damaged.pcd" in damaged and "\n" not in damaged, damaged
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("drives/*/summary.json")}
    assert len(stamps) == 2
    r = subprocess.run(
        [sys.executable, "-m", "lidarloc.app.cli", "corpus", "run", str(path), "--out", str(out)]
        + ["--workers", "2", "--cache", str(town_cache), "--json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1, r.stderr  # a drive failed
    again = json.loads(r.stdout)
    assert again["ran_now"] == 0 and again["drives_failed"] == report["drives_failed"]
    assert again["drives"] == json.loads(json.dumps(report["drives"]))  # the same summaries and health
    assert {p: p.stat().st_mtime_ns for p in out.glob("drives/*/summary.json")} == stamps
    # a finished drive is not kept under a definition it was not run with
    from lidarloc.app.corpus.run import plan_drives
    from lidarloc.app.corpus.spec import load_corpus

    with pytest.raises(LidarlocError, match="drive 'plain' now names; use another --out"):
        plan_drives(load_corpus(path), out, 2, ["pf.sigma=0.9"], str(town_cache))


def _table(n: int, **columns) -> dict[str, np.ndarray]:
    table = {"scan": np.arange(n, dtype=float), "time": 0.1 * np.arange(n) + 5.0}
    table.update({k: np.asarray(v, dtype=float) for k, v in columns.items()})
    return table


def test_health_finds_the_stretches_of_a_drive():
    from lidarloc.app.corpus.health import drive_health

    n = 60
    localized = np.ones(n)
    localized[:8] = 0  # first fix at scan 8
    localized[40:43] = 0  # withdrawn at 40, back at 43
    share = np.full(n, 0.8)
    share[15:27] = 0.55  # 12 scans: a poor fit
    share[30:35] = 0.3  # 5 scans: too short to report
    share[:8] = 0.1  # before the first fix: not the map's fault
    error = np.full(n, 0.4)
    error[:8] = 30.0
    error[43] = 9.0  # back, but in the wrong place: a false fire
    error[50:53] = 7.5  # localized but wrong
    pf_ms = np.full(n, 20.0)
    pf_ms[0] = 9000.0  # the first step compiles the kernels
    pf_ms[20] = 180.0
    h = drive_health(
        _table(n, localized=localized, inlier_share=share, error_m=error, pf_ms=pf_ms),
        [{"scan": 40, "kind": "unconfirmed"}],
        min_inlier_share=0.6,
    )
    assert h["first_fix"] == {"scan": 8, "seconds": pytest.approx(0.8)}
    assert h["withdrawals"] == [40]
    assert h["false_fires"] == 1 and h["wrong_scans"] == 4  # the onset at 8 was right, at 43 wrong
    ok = error[localized == 1]
    assert h["rmse_localized_m"] == pytest.approx(float(np.sqrt(np.mean(ok**2))))
    found = [(s["first_scan"], s["last_scan"], s["kind"]) for s in h["stretches"]]
    assert found == [
        (15, 26, "poor_fit"),
        (20, 20, "late"),
        (40, 42, "unlocalized"),
        (43, 43, "wrong"),
        (50, 52, "wrong"),
    ]
    poor = h["stretches"][0]
    assert poor["figure"] == pytest.approx(0.55) and poor["text"] == "scans 15–26: poor fit, inlier share 0.55"
    assert h["poor_fit_scans"] == 12 and h["late_scans"] == 1
    # without truth: nothing is called wrong, no RMSE
    blind = drive_health(_table(n, localized=localized, inlier_share=share, pf_ms=pf_ms), [], 0.6)
    assert blind["false_fires"] is None and blind["rmse_localized_m"] is None
    assert "wrong" not in {s["kind"] for s in blind["stretches"]}
    # never localized: no first fix, no stretch that needs one
    never = drive_health(_table(5, localized=np.zeros(5), inlier_share=np.full(5, 0.1)), [], 0.6)
    assert never["first_fix"] is None and never["stretches"] == [] and never["withdrawals"] == []


def test_bench_corpus_drives_repeat_each_log_under_its_seeds():
    from lidarloc.app.bench.corpus import bench_drives

    rows = bench_drives(3, 20, 2, 4, real=False)
    assert [r["name"] for r in rows[:2]] == ["town0-hdl64e-r0", "town0-hdl64e-r1"]
    assert [r["seed"] for r in rows] == [4, 5] * 3 and len({r["name"] for r in rows}) == 6
    # the same names under other seeds: compare pairs them drive by drive
    assert [r["name"] for r in bench_drives(3, 20, 2, 0, real=False)] == [r["name"] for r in rows]


def test_bench_corpus_removes_one_building_from_the_drives_map(town_cache, tmp_path):
    from lidarloc.app.bench.corpus import building_removed_map
    from lidarloc.core.config import Config, load_config
    from lidarloc.core.maps.map_source import MapFileSource
    from lidarloc.core.maps.mapping import load_or_build_map
    from lidarloc.core.sequences.factory import SourceSpec, open_sequence

    row = {"town_seed": 0, "set": ["town.n_scans=150"]}
    out = tmp_path / "removed.ply"
    info = building_removed_map(row, 40, town_cache, out)
    seq = open_sequence(SourceSpec(town_seed=0, scans=40), load_config(None, row["set"], world="lived-in"))
    whole = load_or_build_map(seq.map_source, Config().map, town_cache, road_removal=False).value.points
    left = MapFileSource(out).read().points
    assert info["points_removed"] > 100 and len(left) == len(whole) - info["points_removed"]
    assert info["from_middle_scan_m"] <= 30.0

    # what the footprint (0.5 m wider) holds is gone, nothing else
    def inside(p, margin):
        (cx, cy), (length, width), yaw = info["building_xy_m"], info["size_m"], np.radians(info["yaw_deg"])
        dx, dy = p[:, 0] - cx, p[:, 1] - cy
        along, across = np.abs(np.cos(yaw) * dx + np.sin(yaw) * dy), np.abs(-np.sin(yaw) * dx + np.cos(yaw) * dy)
        return (along <= length / 2 + margin) & (across <= width / 2 + margin)

    # (the figures are rounded to 0.1 m and 0.01°: the margins allow for it)
    assert inside(whole, 0.65).sum() >= info["points_removed"] and not inside(left, 0.35).any()
