"""``lidarloc inspect`` as a user runs it (a child process): on the town and on the real drive it
writes every file it promises (surfaces around the estimate and the truth as PNG and .npy, the
residual image, inspect.json) and prints the same JSON with --json; bad input is one line on
stderr and exit status 2."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import cli_here, run_cli
from lidarloc.app.inspect import FILES

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# the town's first scans, localized in the map of a short mapping drive (builds in seconds)
# S2M at the PF's priority: the replay waits for every match, and a niced S2M beside busy
# processes crawls (the priority never changes a replay's result)
AT_PF_PRIORITY = ["--set", "s2m.replay_process_nice=0"]
TOWN = ["--set", "town.n_scans=150", "--scans", "20", *AT_PF_PRIORITY]
REAL = ["--date", "2011_09_26", "--drive", "0013", *AT_PF_PRIORITY]


def lidarloc(*args, cache):
    return run_cli(*args, cache=cache, timeout=600)


def assert_one_line_error(result, needle):
    assert result.returncode == 2, result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert needle in lines[0], lines[0]


def check_outputs(out, printed: str, scan: int) -> dict:
    """Every file is there and readable, and --json printed what inspect.json holds."""
    for name in FILES:
        assert (out / name).is_file(), name
    for name in ("surface_estimate.png", "surface_truth.png", "residuals.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    saved = json.loads((out / "inspect.json").read_text())
    assert json.loads(printed) == saved
    assert saved["scan"] == scan
    for key in (
        "estimate",
        "truth",
        "surface_argmax_xy",
        "surface_argmax_error_m",
        "residual_share_beyond_dmax",
        "surface_ms",
    ):
        assert saved[key] is not None, key
    for around in ("surface_estimate", "surface_truth"):
        ll = np.load(out / f"{around}.npy")
        grid = saved[around]
        assert list(ll.shape) == grid["shape"] == [81, 81] and np.isfinite(ll).all()
        i, k = np.unravel_index(np.argmax(ll), ll.shape)
        best = [grid["x0"] + i * grid["cell"], grid["y0"] + k * grid["cell"]]
        if around == "surface_estimate":  # the .npy's geometry is the JSON's
            np.testing.assert_allclose(best, saved["surface_argmax_xy"], atol=1e-9)
    truth = np.array([saved["truth"]["x"], saved["truth"]["y"]])
    err = np.linalg.norm(np.array(saved["surface_argmax_xy"]) - truth)
    assert saved["surface_argmax_error_m"] == pytest.approx(err)
    assert 0.0 <= saved["residual_share_beyond_dmax"] < 0.5
    assert 0.0 < saved["surface_ms"] < 60_000
    return saved


@pytest.mark.slow
def test_inspect_writes_every_file_on_the_town(tmp_path, cache_root):
    out = tmp_path / "inspect"
    r = lidarloc("inspect", *TOWN, "--scan", 15, "--out", out, "--json", cache=cache_root)
    assert r.returncode == 0, r.stderr
    saved = check_outputs(out, r.stdout, 15)
    assert saved["localized"] and saved["surface_argmax_error_m"] <= 1.0


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_inspect_writes_every_file_on_the_real_drive(tmp_path, cache_root, kitti_raw_dir):
    out = tmp_path / "inspect-real"
    r = lidarloc("inspect", "--kitti-raw", kitti_raw_dir, *REAL, "--scan", 20, "--out", out, "--json", cache=cache_root)
    assert r.returncode == 0, r.stderr
    saved = check_outputs(out, r.stdout, 20)
    assert saved["localized"] and saved["surface_argmax_error_m"] <= 1.0


# the refusals by the entry point in this process: their output, without a child's start-up (the
# command runs as users start it above)
def test_inspect_refuses_a_scan_beyond_the_sequence(tmp_path, cache_root):
    r = cli_here("inspect", *TOWN, "--scan", 20, "--out", tmp_path / "o", cache=cache_root)
    assert_one_line_error(r, "--scan 20 is beyond")
    assert not (tmp_path / "o").exists()


def test_inspect_refuses_a_missing_path(tmp_path, cache_root):
    r = cli_here(
        "inspect", "--kitti-raw", tmp_path / "nowhere", *REAL, "--scan", 3, "--out", tmp_path / "o", cache=cache_root
    )
    assert_one_line_error(r, "nowhere")
