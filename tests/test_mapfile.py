"""Prior maps from point-cloud files: every format round-trips, the real KITTI map gives the same
voxel map from .pcd, .ply and .las, UTM-sized coordinates keep millimetres through a float64
origin, every bad input is one line naming the file, the file's map is cached by path, size and
time, and ``map info`` / ``map export`` / ``bench mapfile`` work from the command line."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from helpers import cli_here, make_odometry, run_cli
from lidarloc.core.config import MapConfig
from lidarloc.core.errors import DataError
from lidarloc.core.maps.map_source import MapFileSource
from lidarloc.core.maps.mapfile import read_map
from lidarloc.core.maps.mapfile_write import write_map, write_map_chunks
from lidarloc.core.maps.mapping import load_or_build_map
from scipy.spatial import cKDTree

UTM_SHIFT = np.array([500_000.0, 4_000_000.0, 100.0])


def cloud(n=5000, seed=0, scale=80.0) -> np.ndarray:
    return (np.random.default_rng(seed).random((n, 3)) * scale - scale / 2).astype(np.float32)


def write_las(path: Path, world: np.ndarray, scale: float = 0.001) -> None:
    """``world`` (float64) as a LAS/LAZ at ``scale`` m (offsets at the minimum, as survey tools
    write them, so UTM coordinates fit the int32 records)."""
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, scale)
    header.offsets = np.floor(world.min(axis=0)) if len(world) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = world[:, 0], world[:, 1], world[:, 2]
    las.write(path)


# ------------------------------------------------------------------------------ formats
@pytest.mark.parametrize("suffix", [".pcd", ".ply", ".npy", ".npz"])
def test_each_format_round_trips_and_drops_non_finite_points(tmp_path, suffix):
    pts = cloud()
    pts[[3, 77]] = np.nan
    pts[500, 2] = np.inf
    path = tmp_path / f"map{suffix}"
    if suffix == ".npy":
        np.save(path, np.concatenate([pts, np.ones((len(pts), 1), np.float32)], axis=1))  # an extra column
    elif suffix == ".npz":
        np.savez(path, points=pts, colours=np.zeros((len(pts), 3), np.uint8))
    else:
        write_map(path, pts)
    got = read_map(path, chunk_points=1234)  # several chunks, the last one partial
    finite = np.isfinite(pts).all(axis=1)
    assert (got.n_read, got.n_dropped_nonfinite) == (len(pts), 3)
    assert got.points.dtype == np.float32 and got.points.flags.c_contiguous
    np.testing.assert_array_equal(got.origin, np.zeros(3))
    np.testing.assert_array_equal(got.points, pts[finite])


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_and_laz_read_within_their_scale(tmp_path, suffix):
    pts = cloud().astype(np.float64)
    write_las(tmp_path / f"map{suffix}", pts)
    got = read_map(tmp_path / f"map{suffix}", chunk_points=999)
    assert got.n_read == len(pts) and got.n_dropped_nonfinite == 0
    assert np.abs(got.points + got.origin - pts).max() <= 0.0005 + 1e-6  # half the 1 mm scale


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_written_maps_read_in_open3d_too(tmp_path, suffix):
    from lidarloc.core.o3d import open3d

    pts = cloud(500)
    # open3d reads a PCD's float64 fields as zeros: its georeferenced maps are PLY-only
    for origin in (None, UTM_SHIFT) if suffix == ".ply" else (None,):
        path = tmp_path / f"map{suffix}"
        write_map(path, pts, origin=origin)
        theirs = np.asarray(open3d().io.read_point_cloud(str(path)).points)
        want = pts.astype(np.float64) + (0.0 if origin is None else origin)
        np.testing.assert_allclose(theirs, want, rtol=0, atol=1e-9)


def test_ascii_pcd_and_ply_with_extra_fields(tmp_path):
    (tmp_path / "a.pcd").write_text(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS intensity x y z normal\nSIZE 4 4 4 4 4\nTYPE F F F F F\n"
        "COUNT 1 1 1 1 3\nWIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n"
        "7 1 2 3 0 0 1\n7 nan nan nan 0 0 1\n7 4.5 5.5 6.5 0 0 1\n"
    )
    (tmp_path / "a.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty uchar red\nproperty float x\nproperty float y\n"
        "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n9 1 2 3\n9 4.5 5.5 6.5\n"
    )
    for name in ("a.pcd", "a.ply"):
        got = read_map(tmp_path / name)
        np.testing.assert_array_equal(got.points, np.array([[1, 2, 3], [4.5, 5.5, 6.5]], np.float32))


def test_binary_pcd_with_padding_and_float64_fields(tmp_path):
    """A PCL-style binary PCD: float64 x/y/z between an intensity and a padding field named ``_``,
    read without open3d."""
    rec = np.dtype([("intensity", "<f4"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("_", "u1", (4,)), ("__", "<u2")])
    data = np.zeros(4, rec)
    world = cloud(4).astype(np.float64) + UTM_SHIFT
    data["x"], data["y"], data["z"] = world.T
    header = (
        "VERSION 0.7\nFIELDS intensity x y z _ _\nSIZE 4 8 8 8 1 2\nTYPE F F F F U U\nCOUNT 1 1 1 1 4 1\n"
        "WIDTH 2\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA binary\n"
    )
    path = tmp_path / "pcl.pcd"
    path.write_bytes(header.encode() + data.tobytes())
    got = read_map(path)
    assert np.abs(got.points + got.origin - world).max() < 1e-3


# ----------------------------------------------------------------------- georeferenced maps
@pytest.mark.parametrize("suffix", [".pcd", ".ply", ".las"])
def test_utm_coordinates_read_with_an_origin_and_millimetre_local_points(tmp_path, suffix):
    pts = cloud(20000, scale=300.0)
    path = tmp_path / f"utm{suffix}"
    if suffix == ".las":
        write_las(path, pts.astype(np.float64) + UTM_SHIFT)
    else:
        write_map(path, pts, origin=UTM_SHIFT)
    got = read_map(path)
    assert got.origin[0] != 0 and got.origin[1] != 0
    assert got.origin[2] == 0, "heights of 100 m keep their frame"
    np.testing.assert_array_equal(got.origin % 1000.0, np.zeros(3))
    assert np.abs(got.points).max() < 1000.0, "local coordinates are small"
    back = got.points.astype(np.float64) + got.origin - UTM_SHIFT
    assert np.abs(back - pts).max() <= 0.001


def test_origin_of_a_local_map_is_zero(tmp_path):
    write_map(tmp_path / "m.pcd", cloud() + np.float32(5000.0))
    assert not read_map(tmp_path / "m.pcd").origin.any()


# ------------------------------------------------------------------------------ bad input
def _bad_files(tmp_path: Path) -> dict:
    files = {}
    files["unknown extension"] = (tmp_path / "map.xyz", "supported: .pcd, .ply, .las, .laz, .npy, .npz")
    files["unknown extension"][0].write_text("1 2 3\n")
    files["missing file"] = (tmp_path / "missing.pcd", "no such map file")
    p = tmp_path / "empty.pcd"
    write_map(p, np.zeros((0, 3), np.float32))
    files["empty pcd"] = (p, "no points")
    p = tmp_path / "allnan.ply"
    write_map(p, np.full((10, 3), np.nan, np.float32))
    files["all-NaN ply"] = (p, "no finite point")
    p = tmp_path / "allnan.npy"
    np.save(p, np.full((10, 3), np.nan))
    files["all-NaN npy"] = (p, "no finite point")
    p = tmp_path / "truncated.pcd"
    write_map(p, cloud(100))
    p.write_bytes(p.read_bytes()[:-7])
    files["truncated pcd"] = (p, "truncated")
    p = tmp_path / "garbage.pcd"
    p.write_bytes(b"\x00\x01garbage" * 20)
    files["garbage pcd"] = (p, "not a")
    p = tmp_path / "noxyz.pcd"
    p.write_text(
        "VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n"
    )
    files["no x/y/z"] = (p, "no x/y/z")
    p = tmp_path / "notply.ply"
    p.write_text("hello\n")
    files["not a ply"] = (p, "not a PLY")
    p = tmp_path / "garbage.las"
    p.write_bytes(b"nothing like a LAS header" * 10)
    files["garbage las"] = (p, "not a valid LAS")
    p = tmp_path / "nopoints.las"
    write_las(p, np.zeros((0, 3)))
    files["las with no points"] = (p, "no points")
    p = tmp_path / "truncated.laz"
    write_las(p, cloud(20000).astype(np.float64))
    p.write_bytes(p.read_bytes()[:40000])
    files["truncated laz"] = (p, "corrupt or truncated")
    p = tmp_path / "shape.npy"
    np.save(p, np.zeros((10, 2)))
    files["npy of 2 columns"] = (p, "(N, ≥3)")
    p = tmp_path / "two.npz"
    np.savez(p, a=np.zeros((3, 3)), b=np.zeros((3, 3)))
    files["npz without points"] = (p, "'points'")
    return files


BAD = [
    "unknown extension",
    "missing file",
    "empty pcd",
    "all-NaN ply",
    "all-NaN npy",
    "truncated pcd",
    "garbage pcd",
    "no x/y/z",
    "not a ply",
    "garbage las",
    "las with no points",
    "truncated laz",
    "npy of 2 columns",
    "npz without points",
]


@pytest.mark.parametrize("case", BAD)
def test_bad_map_files_give_one_line_naming_the_file(tmp_path, case):
    path, needle = _bad_files(tmp_path)[case]
    with pytest.raises(DataError) as info:
        read_map(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    assert needle in message, message


def test_writing_an_unknown_format_or_a_short_stream_leaves_no_file(tmp_path):
    with pytest.raises(DataError, match="supported: .pcd, .ply"):
        write_map(tmp_path / "m.las", cloud(10))
    with pytest.raises(ValueError):
        write_map_chunks(tmp_path / "m.pcd", 20, iter([cloud(10)]))
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------- the map-from-file source
def test_a_map_file_builds_a_cached_prior_map_with_its_origin(tmp_path):
    pts = cloud(20000, scale=60.0)
    path = tmp_path / "utm.pcd"
    write_map(path, pts, origin=UTM_SHIFT)
    cfg = MapConfig()
    built = load_or_build_map(MapFileSource(path), cfg, tmp_path / "cache")
    prior = built.value
    assert not built.cached and prior.source == "utm.pcd"
    assert prior.origin[0] != 0 and prior.points_bev is not None
    # one point per occupied voxel: fewer points, none closer than a voxel's size could allow
    keys = np.floor(prior.points / cfg.voxel_size).astype(np.int64)
    assert len(np.unique(keys, axis=0)) == len(prior.points) < len(pts)
    meta = json.loads((built.directory / "meta.json").read_text())
    assert meta["origin"] == list(prior.origin)
    again = load_or_build_map(MapFileSource(path), cfg, tmp_path / "cache")
    assert again.cached and again.directory == built.directory
    np.testing.assert_array_equal(again.value.points, prior.points)
    np.testing.assert_array_equal(again.value.origin, prior.origin)
    # another file at the same path (size or time changed) is another map
    write_map(path, pts[:10000], origin=UTM_SHIFT)
    os.utime(path, ns=(0, 10**18))
    other = load_or_build_map(MapFileSource(path), cfg, tmp_path / "cache")
    assert not other.cached and other.directory != built.directory


def test_road_removal_added_later_keeps_the_origin(tmp_path):
    from lidarloc.core.maps.mapping import load_or_build_road_removed

    path = tmp_path / "utm.ply"
    write_map(path, cloud(5000, scale=40.0), origin=UTM_SHIFT)
    prior, directory, _ = load_or_build_map(MapFileSource(path), MapConfig(), tmp_path / "cache", road_removal=False)
    assert prior.points_bev is None
    done = load_or_build_road_removed(prior, directory, MapConfig())
    assert done.points_bev is not None
    np.testing.assert_array_equal(done.origin, prior.origin)


def test_map_file_source_rejects_a_missing_or_unknown_file(tmp_path):
    for name, needle in (("nothing.pcd", "no such map file"), ("map.txt", "supported")):
        with pytest.raises(DataError, match=needle):
            MapFileSource(tmp_path / name)


# ------------------------------------------------------------------------ the real KITTI map
def test_real_kitti_map_gives_the_same_voxel_map_from_pcd_ply_and_las(tmp_path, kitti_raw_map):
    _, kitti_prior, _ = kitti_raw_map
    pts = kitti_prior.points
    cfg = MapConfig()
    np.save(tmp_path / "map.npy", pts)
    write_map(tmp_path / "map.pcd", pts)
    write_map(tmp_path / "map.ply", pts)
    write_las(tmp_path / "map.las", pts.astype(np.float64))

    def voxel_map(name):
        return load_or_build_map(MapFileSource(tmp_path / name), cfg, tmp_path / "cache", road_removal=False).value

    reference = voxel_map("map.npy")
    # the fused map is already one centroid per voxel: voxelizing it again keeps it, but for the
    # few centroids that float32 rounding put on a voxel face (4 of 0.87 M on drive 0013)
    assert len(pts) - 50 <= len(reference.points) <= len(pts)
    for name in ("map.pcd", "map.ply"):
        got = voxel_map(name)
        np.testing.assert_array_equal(np.sort(got.points, axis=0), np.sort(reference.points, axis=0), err_msg=name)
    # LAS keeps millimetres: its map is the voxel map of the points rounded to 1 mm (as LAS
    # rounds them) ...
    offset = np.floor(pts.astype(np.float64).min(axis=0))
    rounded = np.round((pts.astype(np.float64) - offset) / 0.001) * 0.001 + offset
    np.save(tmp_path / "rounded.npy", rounded)
    got, want = voxel_map("map.las"), voxel_map("rounded.npy")
    assert len(got.points) == len(want.points)
    assert cKDTree(want.points).query(got.points)[0].max() <= 1e-6
    # ... which is the map's within 1 mm, but where rounding moved a centroid across a voxel face
    # into an occupied voxel (0.2 % of drive 0013's voxels: they merge)
    assert len(got.points) == pytest.approx(len(reference.points), rel=0.005)
    assert np.quantile(cKDTree(got.points).query(reference.points)[0], 0.99) <= 0.001


def test_real_kitti_map_shifted_to_utm_keeps_its_local_points(tmp_path, kitti_raw_map):
    _, kitti_prior, _ = kitti_raw_map
    pts = kitti_prior.points
    write_map(tmp_path / "utm.pcd", pts, origin=UTM_SHIFT)
    got = read_map(tmp_path / "utm.pcd")
    assert got.origin[:2].all()
    back = got.points.astype(np.float64) + (got.origin - UTM_SHIFT)
    assert np.abs(back - pts).max() <= 0.001


# ----------------------------------------------------------------------------- command line
def cli(*args, cache):
    return run_cli(*args, cache=cache)


def assert_one_line_error(result, *needles):
    assert result.returncode == 2, result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_map_info_reports_points_extent_origin_and_density(tmp_path):
    # a 20 × 10 m grid at 0.1 m spacing, shifted to UTM
    gx, gy = np.meshgrid(np.arange(200) * 0.1, np.arange(100) * 0.1, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1).astype(np.float32)
    pts[0] = np.nan
    write_map(tmp_path / "grid.pcd", pts, origin=UTM_SHIFT)
    r = cli("map", "info", str(tmp_path / "grid.pcd"), "--json", cache=tmp_path / "cache")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert (info["points"], info["points_in_file"], info["dropped_nonfinite"]) == (19999, 20000, 1)
    finite = pts[1:].astype(np.float64) + UTM_SHIFT
    np.testing.assert_allclose(info["extent_min_m"], finite.min(axis=0), atol=1e-3)
    np.testing.assert_allclose(info["extent_max_m"], finite.max(axis=0), atol=1e-3)
    assert info["origin_m"][:2] == [500_000.0, 4_000_000.0]
    assert info["points_per_m2"] == pytest.approx(19999 / (19.9 * 9.9), rel=1e-3)
    assert info["median_spacing_m"] == pytest.approx(0.1, abs=1e-3)
    readable = cli("map", "info", str(tmp_path / "grid.pcd"), cache=tmp_path / "cache")
    assert readable.returncode == 0, readable.stderr
    assert "x: 500000.000 … 500019.900 m" in readable.stderr and "spacing 0.100 m" in readable.stderr


def test_map_info_on_a_bad_file_is_one_line(tmp_path):
    (tmp_path / "bad.ply").write_text("nope\n")
    assert_one_line_error(
        # by the entry point in this process (`map info` runs as users start it above)
        cli_here("map", "info", str(tmp_path / "bad.ply"), cache=tmp_path / "cache"),
        "bad.ply",
        "not a PLY",
    )


def test_map_export_writes_a_sources_map_and_refuses_a_bad_name(tmp_path):
    root = make_odometry(tmp_path / "kitti", n_scans=3, n_points=2000)
    source = ["--kitti-odometry", str(root), "--sequence", "00"]
    cache = tmp_path / "cache"
    bad = cli("map", "export", *source, "--out", str(tmp_path / "map.las"), cache=cache)
    assert_one_line_error(bad, "map.las", "supported: .pcd, .ply")
    assert not (tmp_path / "map.las").exists() and not cache.exists(), "refused before building anything"
    for suffix in (".pcd", ".ply"):
        out = tmp_path / f"map{suffix}"
        r = cli("map", "export", *source, "--out", str(out), "--json", cache=cache)
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["points"] > 0
        from lidarloc.core.sequences.kitti_odometry import KittiOdometry

        built = load_or_build_map(KittiOdometry(root, "00"), MapConfig(), cache, road_removal=False)
        assert built.cached, "the export used (and filled) the map cache"
        np.testing.assert_array_equal(read_map(out).points, built.value.points)
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == ["map.pcd", "map.ply"], "no temporary left"


@pytest.mark.slow
def test_bench_mapfile_at_200k_points(tmp_path):
    r = cli("bench", "mapfile", "--points", "200000", "--json", cache=tmp_path / "cache")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["points"] == 200_000 and res["file_mb"] == pytest.approx(2.4, abs=0.01)
    assert 0 < res["map_points"] < 200_000 and res["map_points_road_removed"] < res["map_points"]
    assert res["lookup_mb"] > 0 and res["total_s"] > 0
    assert res["peak_rss_mb"] >= res["read_peak_rss_mb"] > 0
