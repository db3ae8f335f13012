"""``lidarloc export``: a recorded run as a ``.viser`` recording of its scene and a static web
folder that plays it with no server; what a reader must see (scan, localized, std, error, N_eff)
is in the scene itself, step by step. The browser half is tests/test_export_browser.py."""

from __future__ import annotations

import base64
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import record_run
from lidarloc.app.export import DATA_SCRIPT, PAGE, STEP_SECONDS, export_run
from lidarloc.app.export_scene import step_text
from lidarloc.core.errors import LidarlocError
from lidarloc.core.runs import recording
from rich.console import Console

SCANS = 14


def decode_viser(data: bytes) -> dict:
    """A .viser file's header and messages (viser's format: zstd of [msgpack length, msgpack,
    aligned binary buffers], prefixed by the uncompressed size)."""
    import msgspec
    import zstandard

    size = int.from_bytes(data[:8], "little")
    inner = zstandard.ZstdDecompressor().decompress(data[8:], max_output_size=size)
    n = int.from_bytes(inner[:8], "little")
    return msgspec.msgpack.decode(inner[8 : 8 + n])


@pytest.fixture(scope="module")
def run(cache_root, tmp_path_factory):
    d = tmp_path_factory.mktemp("export") / "run"
    record_run(d, cache_root, scans=SCANS)
    return d


@pytest.fixture(scope="module")
def exported(run, cache_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("shared") / "bug-report"
    result = export_run(run, out, console=Console(file=io.StringIO()), cache_root=cache_root)
    return out, result


def test_export_writes_the_recording_and_a_static_folder(run, exported):
    out, result = exported
    rec = recording.open(run)
    viser_file = out.with_name("bug-report.viser")
    assert result["viser"] == str(viser_file) and result["folder"] == str(out)
    assert sorted(p.name for p in out.iterdir()) == sorted([PAGE, DATA_SCRIPT])
    data = viser_file.read_bytes()
    assert result["viser_bytes"] == len(data) and result["steps"] == rec.n == SCANS
    print(f"\n.viser: {len(data) / 1e6:.2f} MB for {rec.n} steps; folder {result['folder_bytes'] / 1e6:.2f} MB")
    # the page loads its recording from a script (file:// allows scripts, not fetches): the same bytes
    page = (out / PAGE).read_text()
    assert f'<script src="{DATA_SCRIPT}"></script>' in page and page.index(DATA_SCRIPT) < page.index("</head>")
    assert f"<title>lidarloc · {rec.meta['sequence']} · run</title>" in page
    js = (out / DATA_SCRIPT).read_text()
    m = re.fullmatch(r'window\.__VISER_EMBED_DATA__="([A-Za-z0-9+/=]+)";\n', js)
    assert m and base64.b64decode(m.group(1)) == data


def test_the_recording_plays_each_step_with_its_figures(run, exported):
    out, _ = exported
    rec = recording.open(run)
    doc = decode_viser(out.with_name("bug-report.viser").read_bytes())
    assert doc["durationSeconds"] == pytest.approx(rec.n * STEP_SECONDS)
    msgs = doc["messages"]
    names = {m.get("name") for _, m in msgs}
    for node in (
        "/map",
        "/particles/positions",
        "/particles/headings",
        "/estimate/ellipse_2sigma",
        "/estimate/vehicle",
        "/truth/vehicle",
        "/estimate/scan",
        "/estimate/label",
    ):
        assert node in names, node
    # the overlay: one update per step, at that step's time, with that step's figures
    huds = [(t, m["source"]) for t, m in msgs if m["type"] == "RunJavascriptMessage" and "lidarloc-hud" in m["source"]]
    assert len(huds) == rec.n
    for i, (t, source) in enumerate(huds):
        assert t == pytest.approx(i * STEP_SECONDS)
        text = step_text(rec.snapshot(i), i, rec.n)
        assert json.dumps(text) in source
        assert f"scan {rec.scan_index[i]} (step {i + 1} of {rec.n})" in text
    # the particles change every step: one points update per step after the first
    updates = [
        t
        for t, m in msgs
        if m["type"] == "SceneNodeUpdateMessage"
        and m.get("name") == "/particles/positions"
        and "points" in m.get("updates", {})
    ]
    assert len(updates) >= rec.n - 1


def test_step_text_says_what_the_panel_would():
    from lidarloc.core.snapshot import Snapshot

    snap = Snapshot(
        scan_index=41,
        n_scans=100,
        timestamp=4.1,
        particles=np.zeros((200, 11)),
        weights=np.full(200, 1 / 200),
        best_index=0,
        mean_pose=np.eye(4),
        cov_xyz=np.eye(3),
        std_xyz=np.array([0.3, 0.5, 0.1]),
        ellipse_xy=(1.0, 0.6, 0.0),
        n_eff=50.0,
        localized=True,
        localized_since=30,
        scan_world=np.zeros((0, 3), np.float32),
        gt_pose=None,
        error_m=1.234,
        pf_ms=10.0,
        s2m=None,
        s2m_running=False,
        s2m_acceptance=0.0,
        n_particles=200,
    )
    text = step_text(snap, 7, 60)
    assert text.splitlines() == [
        "scan 41 (step 8 of 60) · localized",
        "std 0.50 m · error 1.23 m · N_eff 25.0 % of 200",
    ]
    unknown = step_text(Snapshot(**{**snap.__dict__, "error_m": None, "localized": False}), 0, 1)
    assert "error —" in unknown and "not localized" in unknown


def test_the_map_is_thinned_to_its_budget(run, cache_root, tmp_path):
    small = export_run(
        run,
        tmp_path / "small",
        console=Console(file=io.StringIO()),
        cache_root=cache_root,
        scans=False,
        max_map_points=5_000,
    )
    assert 0 < small["map_points"] <= 5_000 and small["map_voxel_m"] > 0.5
    doc = decode_viser(Path(small["viser"]).read_bytes())
    assert not any(m.get("name") == "/estimate/scan" for _, m in doc["messages"])


@pytest.mark.parametrize("case", ["missing", "foreign", "out_is_file", "source_moved"])
def test_bad_input_is_one_line(run, tmp_path, case):
    import shutil

    target, out = run, tmp_path / "out"
    if case == "missing":
        target, expect = tmp_path / "nope", "no such run folder"
    elif case == "foreign":
        target = tmp_path / "photos"
        target.mkdir()
        (target / "cat.jpg").write_bytes(b"\xff\xd8")
        expect = "not a recorded run"
    elif case == "out_is_file":
        out = tmp_path / "taken"
        out.write_text("mine")
        expect = "is not a folder"
    else:
        target = tmp_path / "moved"
        shutil.copytree(run, target)
        index_file = target / "recording" / "index.json"
        index = json.loads(index_file.read_text())
        index["meta"]["source"]["scans_dir"] = str(tmp_path / "gone")
        index_file.write_text(json.dumps(index))
        expect = str(tmp_path / "gone")
    with pytest.raises(LidarlocError) as exc:
        export_run(target, out, console=Console(file=io.StringIO()))
    assert expect in str(exc.value) and "\n" not in str(exc.value)
    assert out.is_file() if case == "out_is_file" else not out.exists()


def test_the_map_is_thinned_for_export_without_a_copy_of_it():
    """The Foxglove export and stream thin the map as the viewer thins a city's coarse layer: a
    whole float32 copy and a hash table sized by the map's points (tens of GB for a 4 km city;
    752 MB for this 96 MB map) are never made."""
    import tracemalloc

    from lidarloc.app.run_steps import display_map

    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 400.0, (4_000_000, 3))  # 96 MB: a ground and its heights, a surface
    points[:, 2] = 0.01 * points[:, 2]
    display_map(points[:1000], 100, map_voxel=0.1)  # numba's kernels loaded before measuring
    tracemalloc.start()
    try:
        thinned, voxel = display_map(points, 2000, map_voxel=0.1)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert 0 < len(thinned) <= 2000 and voxel >= 0.5 and thinned.dtype == np.float32
    assert (thinned >= 0).all() and (thinned[:, :2] <= 400).all()
    assert peak < 32e6, f"{peak / 1e6:.0f} MB held while thinning a 96 MB map"  # a float32 copy: 48
