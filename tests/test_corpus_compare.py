"""``lidarloc corpus compare BASE NEW`` and ``lidarloc view --run … --at SCAN``: on corpus output
folders written here as ``corpus run`` writes them (corpus.json with each drive's health from
:func:`~lidarloc.app.corpus.health.drive_health`, scans.csv, events.json, drive.json), identical
runs give nothing; a planted poor fit is ranked first with its stretch, figure and viewer
command; a change within the seed-to-seed spread is not reported (and the same change without
seeds is); the first diverging scan; the HTML stands alone (a browser opens it in
test_corpus_report_browser.py); the JSON's keys; one-line errors; and a recorded run opened at a
scan shows that scan."""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, wait_for
from lidarloc.core.errors import LidarlocError

N = 80  # scans of each synthetic drive
MIN_SHARE = 0.6  # localize.min_inlier_share the health is computed with
COLUMNS = ("scan", "time", "x", "y", "yaw", "localized", "error_m", "inlier_share", "pf_ms")
# one log under three seeds (their RMSE 0.2, 0.3, 0.45 m: a spread of 0.25 m), and two drives of their own
RMSE = {"loop-s0": 0.2, "loop-s1": 0.3, "loop-s2": 0.45, "solo": 0.2, "town1": 0.25}


def drive_table(name: str, seed: int) -> dict[str, np.ndarray]:
    """A drive localized from scan 5 on, its error about ``RMSE[name]``, inlier share about 0.8."""
    rng = np.random.default_rng(seed * 7 + len(name))
    scan = np.arange(N, dtype=float)
    localized = (scan >= 5).astype(float)
    error = RMSE[name] * (1 + 0.02 * rng.standard_normal(N))
    error[:5] = 20.0
    return {
        "scan": scan,
        "time": 100.0 + 0.1 * scan,
        "x": 2.0 * scan,
        "y": 0.5 * scan + 0.01 * rng.standard_normal(N),
        "yaw": 0.01 * scan,
        "localized": localized,
        "error_m": error,
        "inlier_share": 0.8 + 0.01 * rng.standard_normal(N),
        "pf_ms": np.full(N, 20.0),
    }


def write_output(out: Path, tables: dict[str, tuple[dict, int]], identities: bool = True) -> Path:
    """A corpus output folder: each drive's scans.csv, events.json, summary.json and drive.json
    (one log per name without its "-sN"), and corpus.json with their health."""
    from lidarloc.app.corpus.health import run_health

    drives = {}
    for name, (table, seed) in tables.items():
        folder = out / "drives" / name
        folder.mkdir(parents=True)
        with open(folder / "scans.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(COLUMNS)
            for i in range(len(table["scan"])):
                w.writerow([f"{table[c][i]:.6g}" for c in COLUMNS])
        (folder / "events.json").write_text("[]")
        summary = {"seed": seed, "scans": len(table["scan"])}
        (folder / "summary.json").write_text(json.dumps(summary))
        if identities:
            log = name.rsplit("-s", 1)[0]
            identity = {"source": {"town_seed": log}, "config": {"pf": {"sigma": 1}}, "seed": seed, "preset": None}
            (folder / "drive.json").write_text(json.dumps({**identity, "code": "abc"}))
        drives[name] = {"summary": summary, "health": run_health(folder, MIN_SHARE)}
    (out / "corpus.json").write_text(json.dumps({"drives": drives, "drives_failed": {}}))
    return out


def base_tables() -> dict[str, tuple[dict, int]]:
    seeds = {"loop-s0": 0, "loop-s1": 1, "loop-s2": 2, "solo": 0, "town1": 0}
    return {name: (drive_table(name, seed), seed) for name, seed in seeds.items()}


@pytest.fixture
def base(tmp_path) -> Path:
    tables = base_tables()
    tables["retired"] = (drive_table("solo", 5), 0)
    return write_output(tmp_path / "base", tables)


def compare(base: Path, new: Path) -> dict:
    from lidarloc.app.corpus.compare import compare_outputs
    from lidarloc.app.corpus.figures import read_output

    return compare_outputs(read_output(base, "BASE"), read_output(new, "NEW"))


def planted(tmp_path: Path) -> Path:
    """NEW: drive "solo" drifts 0.3 m from scan 27 on and fits poorly over scans 30–49."""
    tables = base_tables()
    solo, _ = tables["solo"]
    solo["x"][27:] += 0.3
    solo["inlier_share"][30:50] = 0.4
    tables["extra"] = (drive_table("town1", 3), 0)
    return write_output(tmp_path / "new", tables)


def test_identical_runs_give_no_regression(base, tmp_path):
    same = tmp_path / "same"
    shutil.copytree(base, same)
    result = compare(base, same)
    assert result["regressions"] == [] and result["improvements"] == []
    assert result["drives_compared"] == 6 and sorted(result["unchanged"]) == sorted([*base_tables(), "retired"])
    assert set(result["first_diverging_scan"].values()) == {None}
    assert result["noise"]["seed_groups"] == 1  # loop-s0…s2


def test_a_planted_poor_fit_is_ranked_first_with_its_stretch_and_viewer_command(base, tmp_path):
    new = planted(tmp_path)
    result = compare(base, new)
    first = result["regressions"][0]
    assert first["drive"] == "solo" and first["stretch"] == {"first_scan": 30, "last_scan": 49}
    assert first["figure"] == "poor_fit_scans" and first["kind"] == "poor_fit"
    assert (first["base"], first["new"], first["threshold"]) == (0, 20, 5.0)  # the floor: no seed spread
    assert first["first_diverging_scan"] == 27 and first["at"] == 30
    assert first["view"] == f"lidarloc view --run {base}/drives/solo --run {new}/drives/solo --at 30"
    assert "scans 30–49: poor fit" in first["text"]
    # the same poor fit is not counted again as the whole drive's poor-fit scans
    assert [(e["drive"], e["figure"]) for e in result["regressions"]].count(("solo", "poor_fit_scans")) == 1
    assert result["only_in_base"] == ["retired"] and result["only_in_new"] == ["extra"]
    assert result["first_diverging_scan"]["solo"] == 27 and result["first_diverging_scan"]["town1"] is None
    assert "solo" not in result["unchanged"] and "town1" in result["unchanged"]
    # swapped, the poor fit is gone: an improvement of NEW over BASE, no regression
    back = compare(new, base)
    assert back["regressions"] == [] and [e["stretch"] for e in back["improvements"]] == [first["stretch"]]


def test_wrong_localization_ranks_before_a_larger_poor_fit(base, tmp_path):
    tables = base_tables()
    tables["solo"][0]["inlier_share"][30:60] = 0.4  # 30 poor-fit scans: severity (30 − 5) / 5
    tables["town1"][0]["error_m"][60:62] = 8.0  # 2 scans localized 8 m off: severity 2
    result = compare(base, write_output(tmp_path / "new", tables))
    kinds = [(e["drive"], e["figure"], e["stretch"]) for e in result["regressions"]]
    assert kinds[0] == ("town1", "wrong_scans", {"first_scan": 60, "last_scan": 61})
    assert kinds[1] == ("solo", "poor_fit_scans", {"first_scan": 30, "last_scan": 59})
    assert result["regressions"][0]["severity"] < result["regressions"][1]["severity"]


def test_a_change_within_the_seed_spread_is_not_reported(base, tmp_path):
    """loop-s1's RMSE 0.3 → 0.5 m: the three seeds of its log spread 0.25 m (threshold 2 × 0.25),
    so it is noise; the same change in a corpus without seeds (the floor, 0.05 m) is not."""
    tables = base_tables()
    tables["loop-s1"][0]["error_m"][5:] += 0.2
    result = compare(base, write_output(tmp_path / "new", tables))
    assert result["regressions"] == []
    # a drive of no group is weighed against the largest group spread: solo's +0.2 m is noise too
    tables = base_tables()
    tables["solo"][0]["error_m"][5:] += 0.2
    assert compare(base, write_output(tmp_path / "new-solo", tables))["regressions"] == []
    # without drive.json no drive has seed siblings: the floor alone decides, and it is reported
    plain_base = write_output(tmp_path / "plain-base", base_tables(), identities=False)
    plain_new = write_output(tmp_path / "plain-new", tables, identities=False)
    found = compare(plain_base, plain_new)["regressions"]
    assert [(e["drive"], e["figure"]) for e in found] == [("solo", "rmse_localized_m")]
    assert found[0]["threshold"] == pytest.approx(0.05) and found[0]["stretch"] is None
    assert found[0]["first_diverging_scan"] is None and found[0]["at"] == 0  # the estimates agree


def test_first_diverging_scan():
    from lidarloc.app.corpus.compare import first_diverging_scan

    a = drive_table("solo", 0)
    b = {k: v.copy() for k, v in a.items()}
    assert first_diverging_scan(a, b) is None
    b["x"][40:] += 0.03  # within the tolerance (scans.csv's rounding)
    assert first_diverging_scan(a, b) is None
    b["yaw"][33] += 2 * np.pi  # the same heading
    assert first_diverging_scan(a, b) is None
    b["yaw"][31] += 0.05
    b["y"][45] += 1.0
    assert first_diverging_scan(a, b) == 31
    # a scan only one run processed (a kidnap skipped it in the other)
    c = {k: np.delete(v, 12) for k, v in a.items()}
    assert first_diverging_scan(a, c) == 12
    # a longer run is compared up to the shorter one's last scan
    assert first_diverging_scan(a, {k: v[:50] for k, v in a.items()}) is None


def test_the_html_report_stands_alone_with_the_plots_inline(base, tmp_path):
    from lidarloc.app.corpus.compare import compare_outputs
    from lidarloc.app.corpus.compare_report import write_reports
    from lidarloc.app.corpus.figures import read_output

    new = planted(tmp_path)
    b, n = read_output(base, "BASE"), read_output(new, "NEW")
    result = compare_outputs(b, n)
    md, page = write_reports(result, b, n, tmp_path / "report")
    text = page.read_text()
    images = re.findall(r'<img [^>]*src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(images) == len({e["drive"] for e in result["regressions"]}) >= 1
    import base64

    assert all(base64.b64decode(i).startswith(b"\x89PNG") for i in images)
    outside = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "", text)
    assert not re.search(r"https?:|//[a-z]", outside, re.IGNORECASE), re.findall(r".{40}https?:.{40}", outside)
    assert "<style>" in text and "<link" not in text and "<script" not in text
    # regressions first, then improvements, then the unchanged drives
    assert text.index("Regressions") < text.index("Improvements") < text.index("Unchanged drives")
    assert _escaped(result["regressions"][0]["view"]) in text
    mdt = md.read_text()
    assert f"`{result['regressions'][0]['view']}`" in mdt and mdt.index("## Regressions") < mdt.index("## Noise")


def _escaped(text: str) -> str:
    import html

    return html.escape(text, quote=True)


def test_cli_json_keys_and_default_report_folder(base, tmp_path):
    from lidarloc.app import cli
    from typer.testing import CliRunner

    new = planted(tmp_path)
    r = CliRunner().invoke(cli.app, ["corpus", "compare", str(base), str(new), "--json"])
    assert r.exit_code == 0, r.output  # a regression is a finding, not an error
    data = json.loads(r.stdout)
    assert set(data) == {"regressions", "drives_compared", "improvements", "only_in_base", "only_in_new"}
    assert data["drives_compared"] == 5 and data["regressions"][0]["view"].endswith("--at 30")
    assert (new / "compare" / "compare.md").is_file() and (new / "compare" / "compare.html").is_file()
    r = CliRunner().invoke(cli.app, ["corpus", "compare", str(base), str(new), "--out", str(tmp_path / "elsewhere")])
    assert r.exit_code == 0 and (tmp_path / "elsewhere" / "compare.html").is_file()
    assert "1. solo: scans 30–49: poor fit" in r.stderr and "--at 30" in r.stderr


def test_bad_input_is_one_line(base, tmp_path):
    from lidarloc.app.corpus.figures import read_output

    (tmp_path / "empty").mkdir()
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "corpus.json").write_text("{not json")
    for folder, needle in (
        (tmp_path / "missing", "no such folder"),
        (tmp_path / "empty", "no corpus.json"),
        (tmp_path / "broken", "unreadable"),
    ):
        with pytest.raises(LidarlocError) as caught:
            read_output(folder, "NEW")
        assert needle in str(caught.value) and "\n" not in str(caught.value)
    # through the command line: one line on stderr, a non-zero status, no report written
    r = run_cli("corpus", "compare", base, tmp_path / "empty", cache=tmp_path / "cache")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "no corpus.json" in lines[0], r.stderr
    assert not (tmp_path / "empty" / "compare").exists()


# ------------------------------------------------------------------------------ view --at
def test_view_at_opens_a_recorded_run_at_that_scan(recorded_town_run, cache_root, tmp_path):
    from lidarloc.app.viewer.runs import open_runs

    run_dir, _ = recorded_town_run
    handle = open_runs([run_dir], port=0, cache_root=cache_root, record_to=tmp_path, at=5)
    try:
        v = handle.viewer
        tl = v.travel.timeline
        assert tl.step == 5 and "**Scan 5**" in tl.where.content  # before any tab or display update
        wait_for(
            lambda: v.update_display(force_plots=True) is not None and v.travel.scan_shown,
            timeout=30,
            what="scan 5 drawn",
        )
        assert v.drawn.scan_index == 5 and "**Scan 5 of" in v.controls.status.content
    finally:
        handle.stop()
    # a scan the run did not record: one line, before any server starts
    with pytest.raises(LidarlocError) as caught:
        open_runs([run_dir], port=0, cache_root=cache_root, at=14)
    message = str(caught.value)
    assert "--at 14" in message and "scans 0…13" in message and "\n" not in message


def test_view_at_on_the_command_line(monkeypatch, tmp_path):
    from lidarloc.app import cli
    from lidarloc.app.viewer import runs
    from typer.testing import CliRunner

    seen: dict = {}
    monkeypatch.setattr(runs, "serve_runs", lambda run_dirs, **kwargs: seen.update(kwargs, run_dirs=run_dirs))
    r = CliRunner().invoke(cli.app, ["view", "--run", str(tmp_path / "a"), "--run", str(tmp_path / "b"), "--at", "5"])
    assert r.exit_code == 0, r.output
    assert seen["at"] == 5 and [Path(p).name for p in seen["run_dirs"]] == ["a", "b"]
    r = CliRunner().invoke(cli.app, ["view", "--at", "5"])
    assert isinstance(r.exception, LidarlocError) and "--run" in str(r.exception)
    assert "\n" not in str(r.exception)


def test_example_seeds_are_one_log_under_several_seeds(tmp_path):
    """``corpus example --seeds 3``: each drive three times, and the drive.json that ``corpus run``
    writes puts the three in one seed group (what compare measures the noise from)."""
    from lidarloc.app.corpus.example import example_corpus
    from lidarloc.app.corpus.figures import DriveRun
    from lidarloc.app.corpus.run import plan_drives
    from lidarloc.app.corpus.spec import IDENTITY_FILE, load_corpus

    path = tmp_path / "seeds.yaml"
    path.write_text(example_corpus(2, 10, seeds=3))
    corpus = load_corpus(path)
    names = [f"town0-{sensor}-s{k}" for sensor in ("hdl64e", "vlp16") for k in range(3)]
    assert [d.name for d in corpus.drives] == names and [d.seed for d in corpus.drives] == [0, 1, 2] * 2
    plan_drives(corpus, tmp_path / "out", 1, [], str(tmp_path / "cache"))
    groups = [
        DriveRun(name, Path(), {}, {}, json.loads((tmp_path / "out" / "drives" / name / IDENTITY_FILE).read_text()))
        for name in names
    ]
    keys = [g.seed_group for g in groups]
    assert keys[0] == keys[1] == keys[2] != keys[3] == keys[4] == keys[5]
    assert [g.seed for g in groups] == [0, 1, 2] * 2
