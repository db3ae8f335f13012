"""``lidarloc compare``: two or more runs side by side — the table of their summary figures, the
same as JSON, and the overlay plot; any results folder (recorded or plain) is a run, anything
else gets one line."""

from __future__ import annotations

import io
import json
import shutil

import numpy as np
import pytest
from helpers import record_run
from lidarloc.app.compare import ROWS, _fmt, compare_runs, load_run, success
from lidarloc.core.errors import LidarlocError
from lidarloc.core.runs.metrics import METRIC_KEYS
from rich.console import Console

SCANS = 16


@pytest.fixture(scope="module")
def runs(cache_root, tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    out = []
    for seed in (0, 1):
        d = root / f"seed{seed}"
        record_run(d, cache_root, seed, scans=SCANS)
        out.append((d, json.loads((d / "summary.json").read_text())))
    return out


def expected(summary: dict) -> dict:
    return {
        **{k: summary["metrics"][k] for k in METRIC_KEYS},
        **{
            k: summary[k]
            for k in ("rmse_after_localized_m", "consistency_2sigma", "false_fire", "pf_ms_median", "scans")
        },
    }


def test_the_table_shows_each_runs_summary_and_the_plot_is_written(runs, tmp_path):
    png = tmp_path / "plots" / "compare.png"
    buf = io.StringIO()
    data = compare_runs([d for d, _ in runs], png, console=Console(file=buf, width=200))
    text = buf.getvalue()
    assert [r["label"] for r in data["runs"]] == ["seed0", "seed1"]
    for row, (d, summary) in zip(data["runs"], runs):
        assert row["recorded"] is True and row["run"] == str(d)
        for key, value in expected(summary).items():
            assert row[key] == (pytest.approx(value) if isinstance(value, float) else value), key
    assert any(s["localized_at_scan"] is not None for _, s in runs)  # the plot has marks to draw
    # every row of the table, with both runs' values as formatted
    for key, label, kind in ROWS:
        line = next(ln for ln in text.splitlines() if ln.count("│") > 2 and ln.split("│")[1].strip() == label)
        for row in data["runs"]:
            assert _fmt(row[key], kind) in line, (label, line)
    # the plot: a PNG with the four panels' colours (one per run) on white
    from PIL import Image

    assert data["plot"] == str(png)
    img = np.asarray(Image.open(png).convert("RGB"))
    assert img.shape[0] > 500 and img.shape[1] > 800
    blue, orange = np.array([31, 119, 180]), np.array([255, 127, 14])  # matplotlib's first two colours
    for color in (blue, orange):
        assert (np.abs(img.astype(int) - color).sum(axis=2) < 30).sum() > 200


def test_json_mode_prints_the_same_figures(runs, capsys):
    data = compare_runs([d for d, _ in runs], None, as_json=True)
    printed = json.loads(capsys.readouterr().out)
    assert printed == data and printed["plot"] is None
    for row, (_, summary) in zip(printed["runs"], runs):
        assert row["A"] == summary["metrics"]["A"] and row["scans"] == summary["scans"] == SCANS


def test_a_plain_results_folder_and_a_recording_without_summary_compare_alike(runs, tmp_path):
    (d0, s0), (d1, _) = runs
    plain = tmp_path / "plain"
    shutil.copytree(d0, plain)
    shutil.rmtree(plain / "recording")  # summary.json + scans.csv only
    bare = tmp_path / "bare"
    shutil.copytree(d1, bare)
    (bare / "summary.json").unlink()  # a run killed before its summary
    index = json.loads((bare / "recording" / "index.json").read_text())
    index["meta"].pop("summary", None)
    (bare / "recording" / "index.json").write_text(json.dumps(index))
    a, b = load_run(plain), load_run(bare)
    assert not a.recorded and b.recorded
    for key, value in expected(s0).items():
        assert a.figures[key] == (pytest.approx(value) if isinstance(value, float) else value), key
    # figures recomputed from the recorded steps: the same rules as the run's own summary
    for key, value in expected(runs[1][1]).items():
        assert b.figures[key] == (pytest.approx(value) if isinstance(value, float) else value), key
    # the curves of the plain folder are its scans.csv: the recording's own
    rec_curves = load_run(d0).curves
    np.testing.assert_allclose(a.curves.x, rec_curves.x, rtol=1e-5)  # the CSV keeps 6 digits
    np.testing.assert_array_equal(a.curves.localized, rec_curves.localized)


def test_success_is_the_rule_met_and_within_5_m_to_the_end():
    from lidarloc.app.compare import RunCurves

    def curves(localized, err):
        n = len(err)
        z = np.zeros(n)
        return RunCurves(
            np.arange(n), z, z, z, z, np.asarray(err, float), z, z, np.asarray(localized, bool), z, [None] * n
        )

    assert success(curves([0, 1, 1, 1], [30, 2, 4.9, 1])) is True
    assert success(curves([0, 1, 1, 1], [30, 2, 6.0, 1])) is False  # 6 m after the rule fired
    assert success(curves([0, 0, 0, 0], [1, 1, 1, 1])) is False  # never fired
    assert success(curves([0, 1, 1, 1], [np.nan] * 4)) is None  # no truth: unknown


@pytest.mark.parametrize("make", ["missing", "foreign", "one", "not_png"])
def test_bad_input_is_one_line(runs, tmp_path, make):
    d0 = runs[0][0]
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "cat.jpg").write_bytes(b"\xff\xd8")
    args = {
        "missing": ([d0, tmp_path / "nope"], None, "no such run folder"),
        "foreign": ([d0, foreign], None, "not a lidarloc run folder"),
        "one": ([d0], None, "at least two"),
        "not_png": ([d0, runs[1][0]], tmp_path / "plot.pdf", "PNG"),
    }[make]
    with pytest.raises(LidarlocError) as exc:
        compare_runs(args[0], args[1], console=Console(file=io.StringIO()))
    msg = str(exc.value)
    assert args[2] in msg and "\n" not in msg


def test_two_folders_of_the_same_name_get_labels_that_tell_them_apart(runs, tmp_path):
    """The viewer names every first run ``run``: two of them are told apart by the shortest
    ending of their paths that differs, not by a path cut off in the table."""
    from lidarloc.app.compare import distinct_labels

    a, b = tmp_path / "2026-11-01T10-00-00" / "run", tmp_path / "2026-11-02T09-30-00" / "run"
    for src, dst in zip((d for d, _ in runs), (a, b)):
        shutil.copytree(src, dst)
    buf = io.StringIO()
    data = compare_runs([a, b], console=Console(file=buf, width=200))
    assert [r["label"] for r in data["runs"]] == ["2026-11-01T10-00-00/run", "2026-11-02T09-30-00/run"]
    text = buf.getvalue()
    assert "2026-11-01T10-00-00/run" in text and "2026-11-02T09-30-00/run" in text
    assert distinct_labels([a, a]) == ["run #1", "run #2"]
    assert distinct_labels([a, tmp_path / "other"]) == ["run", "other"]
