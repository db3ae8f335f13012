"""``lidarloc corpus staleness``: on a corpus of short lived-in town drives (localized at the
truth, so that what is judged is the map, not the filter) a known change is flagged and the
traffic that one drive met is not; bad folders are one line; the viewer's layer loads."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import MAPPING_SCANS, run_cli
from lidarloc.core.errors import LidarlocError

SCANS = 80  # the short town's drive up to its first turn, judged every 2nd scan
EVERY = "2"
# two drives through the changed town, with other sensors; only the first meets traffic
DRIVES = {
    "hdl64e-traffic": ["town.sensor=hdl64e"],
    "vlp32c": ["town.sensor=vlp32c", "town.traffic=false"],
}


def truth_run(folder: Path, drives: dict[str, list[str]]) -> Path:
    """A corpus run's folder as ``lidarloc corpus run`` writes it, each drive localized at the
    truth in every scan: corpus.json, drives/NAME/drive.json and scans.csv."""
    from lidarloc.core.config import load_config
    from lidarloc.core.geometry import pose_to_xyz_ypr
    from lidarloc.core.sequences.factory import SourceSpec, open_sequence

    spec = SourceSpec(scans=SCANS)
    for name, overrides in drives.items():
        cfg = load_config(None, [f"town.n_scans={MAPPING_SCANS}", *overrides], world="lived-in")
        seq = open_sequence(spec, cfg)
        drive_dir = folder / "drives" / name
        drive_dir.mkdir(parents=True)
        ident = {"source": spec.to_dict(), "config": cfg.to_dict(), "seed": 0, "preset": None, "code": ""}
        (drive_dir / "drive.json").write_text(json.dumps(ident, default=str))
        rows = ["scan,time,x,y,z,yaw,pitch,roll,localized"]
        for i in range(len(seq)):
            state = pose_to_xyz_ypr(seq.pose(i))
            rows.append(",".join([str(i), f"{seq.timestamp(i):.3f}", *(f"{v:.6f}" for v in state), "1"]))
        (drive_dir / "scans.csv").write_text("\n".join(rows) + "\n")
    (folder / "corpus.json").write_text(json.dumps({"drives": {name: {"health": {}} for name in drives}}))
    return folder


@pytest.fixture(scope="module")
def staleness(town_cache, tmp_path_factory):
    """The command run once on the three drives: (run folder, its output folder, the summary)."""
    run = truth_run(tmp_path_factory.mktemp("corpus"), DRIVES)
    out = run / "stale"
    r = run_cli("corpus", "staleness", run, "--out", out, "--every", EVERY, "--json", cache=town_cache)
    assert r.returncode == 0, r.stderr
    return run, out, json.loads(r.stdout)


def test_a_planted_change_is_flagged_and_one_drive_s_traffic_is_not(staleness):
    _, out, summary = staleness
    (entry,) = summary["maps"]
    known = entry["known_changes"]
    # the short drive passes a few of the town's changes (7); the stale places find some, and
    # lie on changes (measured: 3 found, every place on a change)
    assert known["changes_in_range"] >= 3
    assert known["changes_found"] >= 2 and summary["recall"] >= 0.4, known
    assert summary["precision"] >= 0.6, known
    # only one drive met traffic: one drive is never enough for a place to be stale
    assert summary["traffic_flagged"] is False and known["traffic_places"] == []
    assert entry["cells_stale"] > 0 and entry["stale_points"] > 0 and entry["drives"] == list(DRIVES)
    folder = out / entry["map"]
    with np.load(folder / "staleness.npz") as grid:
        assert grid["stale"].sum() == entry["cells_stale"]
        assert (grid["drives_disagree"][grid["stale"]] >= 2).all()
        assert grid["drives_observed"].max() == len(DRIVES)
    assert (folder / "staleness.png").stat().st_size > 10_000
    assert json.loads((out / "staleness.json").read_text())["recall"] == summary["recall"]


def test_one_drive_flags_nothing(staleness, town_cache, tmp_path):
    """The same changes in a single drive are not yet a recurring disagreement."""
    from lidarloc.app.corpus.staleness import Settings
    from lidarloc.app.corpus.staleness_run import corpus_staleness

    run, _, _ = staleness
    (tmp_path / "drives").mkdir()
    (tmp_path / "drives" / "vlp32c").symlink_to(run / "drives" / "vlp32c")  # its scans are cached
    (tmp_path / "corpus.json").write_text(json.dumps({"drives": {"vlp32c": {"health": {}}}}))
    (result,) = corpus_staleness(tmp_path, Settings(every=int(EVERY)), town_cache)
    assert result["grid"].drives_disagree.max() == 1 and result["places"] == []


@pytest.mark.parametrize(
    "make, expected",
    [
        (lambda p: p / "missing", "no such folder"),
        (lambda p: p, "no corpus.json"),
        (lambda p: (p / "corpus.json").write_text("[1, 2]") and p, "not a corpus.json"),
    ],
)
def test_a_folder_that_is_not_a_corpus_run_is_one_line(tmp_path, make, expected):
    r = run_cli("corpus", "staleness", make(tmp_path), cache=tmp_path / "cache")
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], r.stderr


def test_the_viewer_shows_the_stale_places_as_a_layer(staleness):
    import viser
    from lidarloc.app.viewer.panel import build_panel
    from lidarloc.app.viewer.scene import SceneView
    from lidarloc.app.viewer.staleness_layer import show_staleness, stale_layer_points

    _, out, summary = staleness
    points = stale_layer_points(out)
    assert len(points) == summary["maps"][0]["stale_points"]
    server = viser.ViserServer(port=0, verbose=False)
    try:
        scene = SceneView(server.scene)
        controls = build_panel(server.gui, speed="10", layers=scene.layers)
        box = controls.layers["staleness"]
        assert not box.visible  # nothing to show before a staleness output is given
        node = show_staleness(SimpleNamespace(controls=controls, scene=scene), out)
        assert box.visible and node.visible and len(node.points) == len(points)
        box.value = False
        assert not node.visible
    finally:
        server.stop()
    with pytest.raises(LidarlocError, match="no staleness.npz"):
        stale_layer_points(out.parent)


def test_view_takes_the_staleness_layer_with_a_run_only(monkeypatch, tmp_path):
    from lidarloc.app import cli
    from lidarloc.app.viewer import runs
    from typer.testing import CliRunner

    seen: dict = {}
    monkeypatch.setattr(runs, "serve_runs", lambda run_dirs, **kwargs: seen.update(kwargs))
    r = CliRunner().invoke(cli.app, ["view", "--run", str(tmp_path / "a"), "--staleness", str(tmp_path / "s")])
    assert r.exit_code == 0, r.output
    assert seen["staleness"] == tmp_path / "s"
    r = CliRunner().invoke(cli.app, ["view", "--staleness", str(tmp_path / "s")])
    assert r.exit_code != 0 and "--staleness" in str(r.exception or r.output)
