"""Hostile input for every reader: a valid file of each kind, then cut short, bytes flipped,
NaN/inf or huge numbers written in, lines dropped, repeated or swapped, emptied, wrong types.
Each case must end in a usable result (the reader's invariants hold: finite numbers, the right
shapes) or one :class:`~lidarloc.core.errors.LidarlocError` line; never another exception and
never a hang (a per-case timer). Seeded (``derandomize``), bounded in examples.

``LIDARLOC_FUZZ_EXAMPLES`` sets the examples per reader (default 30);
``LIDARLOC_FUZZ_REPORT=file.json`` writes how many cases each reader was fed and how they ended
(the hostile-input table of docs/benchmarks/faults.md)."""

from __future__ import annotations

import json
import os
import signal
import struct
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from lidarloc.core.errors import LidarlocError

EXAMPLES = int(os.environ.get("LIDARLOC_FUZZ_EXAMPLES", "30"))
CASE_TIMEOUT_S = 10.0  # a reader that takes longer on a small file hangs
FUZZ = settings(
    derandomize=True,
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
TALLY: dict[str, Counter] = defaultdict(Counter)


@pytest.fixture(scope="module", autouse=True)
def report():
    yield
    path = os.environ.get("LIDARLOC_FUZZ_REPORT")
    if path:
        Path(path).write_text(json.dumps({k: dict(v) for k, v in sorted(TALLY.items())}, indent=1))


class Hang(Exception):
    pass


def _alarm(*_):
    raise Hang


def feed(reader: str, read, path: Path, check) -> None:
    """Run ``read(path)`` as one fuzz case: ``check(result)`` must hold, or a one-line
    LidarlocError; anything else fails the test."""
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, CASE_TIMEOUT_S)
    try:
        result = read(path)
    except LidarlocError as exc:
        assert "\n" not in str(exc).strip(), str(exc)
        TALLY[reader]["one-line error"] += 1
        return
    except Hang:
        TALLY[reader]["hang"] += 1
        raise AssertionError(f"{reader}: no answer within {CASE_TIMEOUT_S} s") from None
    except Exception as exc:
        TALLY[reader]["other exception"] += 1
        raise AssertionError(f"{reader}: {type(exc).__name__}: {exc}") from exc
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    check(result)
    TALLY[reader]["read"] += 1


# ------------------------------------------------------------------------------- mutations
SPECIALS = [b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"", b"x", b"1e-320", b"0", b"-0"]
FLOAT_SPECIALS = [np.nan, np.inf, -np.inf, 3.0e38, -3.0e38, 1e-45]


@st.composite
def mutated_bytes(draw, seed: bytes, floats: bool = False) -> bytes:
    """``seed`` damaged: cut short, bytes changed, a float32 made special, a block repeated or
    garbage appended; or emptied."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["truncate", "flip", "special", "repeat", "append", "empty", "keep"]))
        if op == "truncate" and data:
            data = data[: draw(st.integers(0, len(data) - 1))]
        elif op == "flip" and data:
            for _ in range(draw(st.integers(1, 8))):
                data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        elif op == "special" and floats and len(data) >= 4:
            at = draw(st.integers(0, len(data) // 4 - 1)) * 4
            data[at : at + 4] = struct.pack("<f", draw(st.sampled_from(FLOAT_SPECIALS)))
        elif op == "repeat" and data:
            a = draw(st.integers(0, len(data) - 1))
            b = draw(st.integers(a, min(len(data), a + 64)))
            data[b:b] = data[a:b]
        elif op == "append":
            data += draw(st.binary(max_size=64))
        elif op == "empty":
            data = bytearray()
    return bytes(data)


@st.composite
def mutated_text(draw, seed: str) -> bytes:
    """``seed`` (lines of numbers or key = value) damaged line by line or token by token."""
    lines = seed.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["token", "drop", "dup", "swap", "cut", "garbage", "empty", "bytes"]))
        if op == "token" and lines:
            i = draw(st.integers(0, len(lines) - 1))
            tokens = lines[i].split(" ")
            j = draw(st.integers(0, len(tokens) - 1))
            tokens[j] = draw(st.sampled_from(SPECIALS)).decode()
            lines[i] = " ".join(tokens)
        elif op == "drop" and lines:
            del lines[draw(st.integers(0, len(lines) - 1))]
        elif op == "dup" and lines:
            i = draw(st.integers(0, len(lines) - 1))
            lines.insert(i, lines[i])
        elif op == "swap" and len(lines) > 1:
            i = draw(st.integers(0, len(lines) - 2))
            lines[i], lines[i + 1] = lines[i + 1], lines[i]
        elif op == "cut" and lines:
            i = draw(st.integers(0, len(lines) - 1))
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
        elif op == "garbage":
            lines.insert(draw(st.integers(0, len(lines))), draw(st.text(max_size=20)))
        elif op == "empty":
            lines = []
    text = "\n".join(lines).encode("utf-8", "surrogatepass")
    if draw(st.booleans()) and text:  # raw bytes too: invalid UTF-8, a cut mid-line
        text = draw(mutated_bytes(text))
    return text


def write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# ------------------------------------------------------------------------------- checks
def finite_points(columns: int):
    def check(points):
        points = np.asarray(points)
        assert points.ndim == 2 and points.shape[1] == columns and len(points) > 0, points.shape
        assert np.isfinite(points).all()

    return check


def usable_truth(truth):
    assert len(truth.poses) > 0 and np.isfinite(truth.poses).all()
    assert truth.times is None or np.isfinite(truth.times).all()


def _points(n: int = 40, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.zeros((n, 4), np.float32)
    pts[:, :3] = rng.uniform(-20, 20, (n, 3))
    pts[:, 3] = rng.uniform(0, 1, n)
    return pts


# ------------------------------------------------------------------------------- scans
def read_kitti_scan(path: Path):
    from lidarloc.core.sequences.base import validate_scan
    from lidarloc.core.sequences.kitti_io import read_velodyne_bin

    return validate_scan(read_velodyne_bin(path), str(path))


def read_npy_scan(path: Path):
    from lidarloc.core.sequences.base import validate_scan
    from lidarloc.core.sequences.scan_folder import read_scan_file

    return validate_scan(read_scan_file(path), str(path))


@FUZZ
@given(data=st.data())
def test_kitti_bin_scans(tmp_path, data):
    blob = data.draw(mutated_bytes(_points().tobytes(), floats=True))
    feed("KITTI .bin scan", read_kitti_scan, write(tmp_path / "000000.bin", blob), finite_points(4))


def _npy_bytes(array) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


NPY_SEEDS = [_points(), _points()[:, :3].astype(np.float64), np.arange(12).reshape(4, 3), np.array(["a", "b"])]


@FUZZ
@given(data=st.data())
def test_npy_scans(tmp_path, data):
    seed = data.draw(st.sampled_from(NPY_SEEDS))
    blob = data.draw(mutated_bytes(_npy_bytes(seed), floats=True))
    feed(".npy scan", read_npy_scan, write(tmp_path / "scan.npy", blob), finite_points(4))


# ------------------------------------------------------------------------------- maps
def _pcd(points: np.ndarray, binary: bool) -> bytes:
    head = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    ).encode()
    xyz = np.ascontiguousarray(points[:, :3], np.float32)
    body = xyz.tobytes() if binary else "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in xyz).encode()
    return head + body


def _ply(points: np.ndarray, binary: bool) -> bytes:
    fmt = "binary_little_endian" if binary else "ascii"
    head = (
        f"ply\nformat {fmt} 1.0\nelement vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    ).encode()
    xyz = np.ascontiguousarray(points[:, :3], np.float32)
    body = xyz.tobytes() if binary else "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in xyz).encode()
    return head + body


def _las(points: np.ndarray) -> bytes:
    import io

    import laspy

    las = laspy.create(point_format=0, file_version="1.2")
    las.header.scales = (0.001, 0.001, 0.001)
    las.x, las.y, las.z = (points[:, i].astype(np.float64) for i in range(3))
    buf = io.BytesIO()
    las.write(buf)
    return buf.getvalue()


MAP_SEEDS = {
    "las": (".las", _las(_points(60))),
    "pcd-binary": (".pcd", _pcd(_points(60), True)),
    "pcd-ascii": (".pcd", _pcd(_points(60), False)),
    "ply-binary": (".ply", _ply(_points(60), True)),
    "ply-ascii": (".ply", _ply(_points(60), False)),
    "npy": (".npy", _npy_bytes(_points(60)[:, :3])),
}


def read_map_points(path: Path):
    from lidarloc.core.maps.mapfile import read_map

    cloud = read_map(path)
    return np.asarray(cloud.points, np.float64) + np.asarray(cloud.origin, np.float64).reshape(1, 3)


@FUZZ
@given(data=st.data())
def test_map_files(tmp_path, data):
    kind = data.draw(st.sampled_from(sorted(MAP_SEEDS)))
    suffix, seed = MAP_SEEDS[kind]
    blob = data.draw(mutated_bytes(seed, floats=kind in ("pcd-binary", "ply-binary", "npy")))
    feed(f"map {suffix}", read_map_points, write(tmp_path / f"map{suffix}", blob), finite_points(3))


def test_huge_map_coordinates_keep_their_precision(tmp_path):
    """UTM-sized coordinates are no hostile input: the origin keeps them (never a silent loss)."""
    pts = _points(60).astype(np.float64)
    pts[:, :3] += (4.0e6, 5.0e5, 100.0)
    np.save(tmp_path / "utm.npy", pts[:, :3])
    points = read_map_points(tmp_path / "utm.npy")
    assert np.abs(points - pts[:, :3]).max() < 1e-3


# ------------------------------------------------------------------------------- truth, times
def _tum_text(n: int = 8) -> str:
    return "\n".join(f"{0.1 * i:.3f} {i:.2f} {0.5 * i:.2f} 0.0 0 0 0 1" for i in range(n))


def _kitti_text(n: int = 8) -> str:
    return "\n".join(" ".join(f"{v:.3f}" for v in np.hstack([np.eye(3), [[i], [0], [0]]]).ravel()) for i in range(n))


def _times_text(n: int = 8) -> str:
    return "\n".join(f"{0.1 * i:.6f}" for i in range(n))


def read_truth(path: Path):
    from lidarloc.core.sequences.groundtruth import load_truth

    return load_truth(path)


def read_truth_with_times(paths):
    from lidarloc.core.sequences.groundtruth import read_kitti

    return read_kitti(*paths)


@FUZZ
@given(data=st.data())
def test_truth_files(tmp_path, data):
    kind = data.draw(st.sampled_from(["tum", "kitti"]))
    seed = _tum_text() if kind == "tum" else _kitti_text()
    path = write(tmp_path / f"gt.{kind}", data.draw(mutated_text(seed)))
    feed(f"{kind.upper()} truth", read_truth, path, usable_truth)


@FUZZ
@given(data=st.data())
def test_times_files(tmp_path, data):
    """A times file beside KITTI poses: cut short, unsorted, repeated, NaN, a count that differs."""
    from lidarloc.core.sequences.groundtruth import match

    poses = write(tmp_path / "poses.txt", _kitti_text().encode())
    times = write(tmp_path / "times.txt", data.draw(mutated_text(_times_text())))

    def check(truth):
        usable_truth(truth)
        # matched to scan times, unsorted or repeated truth times still give finite poses
        ok, matched = match(np.arange(8) * 0.1, truth)
        assert np.isfinite(np.asarray(matched)).all()

    feed("times file", read_truth_with_times, (poses, times), check)


# ------------------------------------------------------------------------------- configuration
CONFIG_SEED = "seed = 3\n\n[pf]\nn_particles = 400\nsigma = 0.7\n\n[s2m]\nn_s2m = 2\n\n[localize]\nclock = 'replay'\n"


def read_config(path: Path):
    from lidarloc.core.config import load_config

    return load_config(path)


def usable_config(cfg):
    cfg.validate()
    assert cfg.pf.n_particles > 0 and np.isfinite(cfg.pf.sigma) and cfg.pf.sigma > 0


@FUZZ
@given(data=st.data())
def test_config_files(tmp_path, data):
    suffix = data.draw(st.sampled_from([".toml", ".yaml"]))
    seed = CONFIG_SEED
    if suffix == ".yaml":
        seed = "seed: 3\npf:\n  n_particles: 400\n  sigma: 0.7\ns2m:\n  n_s2m: 2\nlocalize:\n  clock: replay\n"
    path = write(tmp_path / f"config{suffix}", data.draw(mutated_text(seed)))
    feed(f"config {suffix}", read_config, path, usable_config)


# ------------------------------------------------------------------------------- ROS bags, MCAP
BAG_KINDS = {"ros1": "drive.bag", "mcap": "drive_mcap", "sqlite3": "drive_sqlite3"}


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """A small drive (5 scans) written as each bag kind: kind → (bag path, the file to damage)."""
    from bagfixtures import write_bag

    root = tmp_path_factory.mktemp("fuzz-bags")
    scans = [_points(300, seed=i) for i in range(5)]
    times = [1_700_000_000_000_000_000 + i * 100_000_000 for i in range(5)]
    out = {}
    for kind, name in BAG_KINDS.items():
        path = write_bag(root / name, kind, scans, times)
        data_file = path if path.is_file() else next(f for f in path.iterdir() if f.suffix in (".mcap", ".db3"))
        out[kind] = (path, data_file)
    return out


def read_bag(path: Path):
    from lidarloc.core.sequences.base import validate_scan
    from lidarloc.core.sequences.rosbag import BagSequence

    seq = BagSequence(path)
    try:
        return [validate_scan(seq.scan(i), f"{path} scan {i}") for i in range(len(seq))]
    finally:
        seq.close()


def usable_scans(scans):
    assert len(scans) > 0
    for scan in scans:
        finite_points(4)(scan)


@FUZZ
@given(data=st.data())
def test_bags(tmp_path, bags, data):
    import shutil

    kind = data.draw(st.sampled_from(sorted(BAG_KINDS)))
    path, data_file = bags[kind]
    case = tmp_path / "case"
    shutil.rmtree(case, ignore_errors=True)
    case.mkdir()
    copy = case / path.name
    if path.is_dir():
        shutil.copytree(path, copy)
    else:
        shutil.copy(path, copy)
    damaged = copy / data_file.name if path.is_dir() else copy
    damaged.write_bytes(data.draw(mutated_bytes(data_file.read_bytes(), floats=True)))
    feed(f"bag {kind}", read_bag, copy, usable_scans)


# ------------------------------------------------------------------------------- recordings
RECORDING_KEY_FILES = ["index.json", "events.jsonl", "steps.bin", "particle_rows.bin", "particles.bin", "mean_pose.bin"]


def read_recording(path: Path):
    from lidarloc.core.runs import recording

    rec = recording.open(path)
    out = {"n": rec.n, "events": rec.events}
    if rec.n:
        out["mean_pose"] = np.asarray(rec.mean_pose)
        out["particles"] = rec.particles(rec.n - 1)
        out["weights"] = rec.weights(rec.n - 1)
    return out


def usable_recording(out):
    assert out["n"] >= 0
    if out["n"]:
        assert out["mean_pose"].shape == (out["n"], 4, 4)
        assert out["particles"].ndim == 2 and out["particles"].shape[1] == 11
        assert len(out["weights"]) == len(out["particles"])


@FUZZ
@given(data=st.data())
def test_recordings(tmp_path, recorded_town_run, data):
    import shutil

    source = recorded_town_run[0] / "recording"
    files = sorted(p.name for p in source.iterdir() if p.is_file())
    # the files every reading needs, as often as all the per-step fields together
    name = data.draw(st.sampled_from(RECORDING_KEY_FILES) | st.sampled_from(files))
    case = tmp_path / "case"
    shutil.rmtree(case, ignore_errors=True)
    shutil.copytree(source, case / "recording")
    target = case / "recording" / name
    if name.endswith((".json", ".jsonl")):
        blob = data.draw(mutated_text(target.read_text()))
    else:
        blob = data.draw(mutated_bytes(target.read_bytes(), floats=True))
    target.write_bytes(blob)
    feed("recording", read_recording, case, usable_recording)
