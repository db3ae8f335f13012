"""Atomic writes (core/cache.py, core/runs/results.py): a result file is complete or absent whenever
its writer is killed; a write that fails (file too large, disk full, a real full tmpfs under a run)
is one line naming the file and leaves earlier files intact; an unreadable cache entry is built
again and the user told."""

import json
import logging
import resource
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from lidarloc.core.cache import atomic_write_file, cache_rebuilt
from lidarloc.core.errors import LidarlocError
from lidarloc.core.runs.results import write_events, write_json, write_kitti


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "summary.json"
    write_json(target, {"scans": 1})

    def half_then_crash(tmp):
        tmp.write_text('{"scans": ')
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError):
        atomic_write_file(target, half_then_crash)
    assert json.loads(target.read_text()) == {"scans": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_a_result_file_is_readable_by_others(tmp_path):
    write_json(tmp_path / "summary.json", {})
    assert (tmp_path / "summary.json").stat().st_mode & 0o044  # not mkstemp's 0600


def test_a_writer_killed_at_any_moment_leaves_complete_files(tmp_path):
    """A child rewrites a large summary.json and trajectory in a loop; killed at several moments,
    each file it leaves parses whole."""
    script = textwrap.dedent(
        f"""
        import sys, numpy as np
        from pathlib import Path
        from lidarloc.core.runs.results import write_json, write_kitti
        out = Path({str(tmp_path)!r})
        poses = np.tile(np.eye(4), (5000, 1, 1))
        i = 0
        while True:
            write_json(out / "summary.json", {{"i": i, "pad": list(range(20000))}})
            write_kitti(out / "trajectory_kitti.txt", poses)
            i += 1
            if i == 1:
                print("written", flush=True)
        """
    )
    rng = np.random.default_rng(0)
    for delay in rng.uniform(0.0, 0.3, size=3):
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None and proc.stdout.readline().strip() == "written"
        try:
            proc.wait(timeout=float(delay))
        except subprocess.TimeoutExpired:
            pass
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert len(json.loads((tmp_path / "summary.json").read_text())["pad"]) == 20000
        assert len((tmp_path / "trajectory_kitti.txt").read_text().splitlines()) == 5000


def test_a_write_beyond_the_file_size_limit_is_one_line_and_earlier_files_stay(tmp_path):
    """As on a full disk: the file-size limit makes the write fail (EFBIG, like ENOSPC)."""
    write_events(tmp_path / "events.json", [])
    previous_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))
    try:
        with pytest.raises(LidarlocError) as err:
            write_kitti(tmp_path / "trajectory_kitti.txt", np.tile(np.eye(4), (1000, 1, 1)))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous_handler)
    message = str(err.value)
    assert "\n" not in message and message.startswith(str(tmp_path / "trajectory_kitti.txt"))
    assert "cannot write it: File too large" in message
    assert json.loads((tmp_path / "events.json").read_text()) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["events.json"]  # no partial file


def test_a_disk_full_error_is_one_line(tmp_path, monkeypatch):
    import errno

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("lidarloc.core.runs.results.atomic_write_file", full)
    with pytest.raises(LidarlocError, match=r"summary.json: cannot write it: No space left on device \(files written"):
        write_json(tmp_path / "summary.json", {})


def test_an_unreadable_cache_entry_is_reported(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="lidarloc.cache"):
        cache_rebuilt(tmp_path / "lookup-r0.2-d5", "truncated")
    assert "lookup-r0.2-d5: unreadable cache entry (truncated); building it again" in caplog.text


@pytest.mark.parametrize("damage", ["truncate", "foreign"])
def test_a_damaged_odometry_cache_is_rebuilt(tmp_path, caplog, damage, monkeypatch):
    """The recorded odometry's cache (poses.npy) cut short or replaced by another array: found,
    recomputed and reported (the other caches are covered by the map tests)."""
    from lidarloc.core.odometry import rpe

    class Seq:
        def __len__(self):
            return 3

        def scan(self, k):
            return np.zeros((10, 3))

        def timestamp(self, k):
            return 0.1 * k

    class FakeICP:
        def __init__(self):
            pass

        def close(self):
            pass

    class FakeRPE:
        def __init__(self, **kwargs):
            pass

        def add(self, k, scan, t):
            return np.eye(4)

    monkeypatch.setattr(rpe, "KissICPProcess", FakeICP)
    monkeypatch.setattr(rpe, "RelativePoseEstimator", FakeRPE)
    first = rpe.load_or_build_odometry(Seq(), tmp_path)
    assert not first.cached and first.directory is not None
    path = first.directory / "poses.npy"
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[:100])
    else:
        np.save(path, np.zeros((5, 2)))
    with caplog.at_level(logging.WARNING, logger="lidarloc.cache"):
        again = rpe.load_or_build_odometry(Seq(), tmp_path)
    assert not again.cached and again.value.shape == (3, 4, 4)
    assert "unreadable cache entry" in caplog.text
    assert rpe.load_or_build_odometry(Seq(), tmp_path).cached


@pytest.mark.parametrize("damage", ["truncate", "foreign"])
def test_a_damaged_map_cache_is_rebuilt_and_the_user_told(tmp_path, caplog, damage):
    """The prior map's points and its road-removed copy, cut short or replaced by another array:
    found, built again from the drive, reported, and the same map as before."""
    from lidarloc.core.config import load_config
    from lidarloc.core.maps.world import open_world
    from lidarloc.core.sim.town import TownSequence

    seq = TownSequence(seed=3, extent_m=150.0, n_scans=8)  # a few scans: the map is built three times
    cfg = load_config()
    first = open_world(seq.map_source, cfg, tmp_path, lookup=False, pyramid=False).prior_map
    (directory,) = [d for d in tmp_path.iterdir() if (d / "map_points.npy").is_file()]
    for name in ("map_points.npy", "map_points_bev.npy"):
        path = directory / name
        if damage == "truncate":
            path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        else:
            np.save(path, np.zeros((5, 2)))  # a readable array of the wrong shape
    with caplog.at_level(logging.WARNING, logger="lidarloc.cache"):
        again = open_world(seq.map_source, cfg, tmp_path, lookup=False, pyramid=False).prior_map
    assert "unreadable cache entry" in caplog.text and directory.name in caplog.text
    assert np.array_equal(again.points, first.points) and np.array_equal(again.points_bev, first.points_bev)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="lidarloc.cache"):  # rewritten whole: read as it is
        third = open_world(seq.map_source, cfg, tmp_path, lookup=False, pyramid=False).prior_map
    assert "unreadable" not in caplog.text and np.array_equal(third.points, first.points)


@pytest.fixture
def small_disk(tmp_path):
    """A real full disk: a 256 kB tmpfs (mounting one needs root; elsewhere the test skips)."""
    import os
    import shutil

    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a tmpfs needs root and mount(8)")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.decode().strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


@pytest.mark.slow
def test_a_run_that_fills_a_real_disk_is_one_line_and_keeps_what_it_wrote(small_disk, cache_root):
    """``lidarloc run`` onto a 256 kB tmpfs: its recording fills the disk a few scans in. The run
    stops with one line naming the file and the cause (exit 2), no traceback, no temporary file
    left, a file there before untouched, and the steps recorded so far readable."""
    import os

    from lidarloc.core.runs import recording

    earlier = small_disk / "earlier.txt"
    earlier.write_text("written before the run\n")
    out = small_disk / "run"
    env = dict(os.environ, LIDARLOC_CACHE=str(cache_root))
    r = subprocess.run(
        [sys.executable, "-m", "lidarloc.app.cli", "run", "--out", str(out), "--scans", "20"]
        + ["--set", "pf.n_particles=300", "--set", "town.n_scans=150", "--set", "s2m.replay_process_nice=0"],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert r.returncode == 2, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("lidarloc: error:")]
    assert len(errors) == 1 and "No space left on device" in errors[0] and str(out) in errors[0], r.stderr[-2000:]
    assert earlier.read_text() == "written before the run\n"
    assert not [p for p in small_disk.rglob("*") if ".tmp" in p.name]
    rec = recording.open(out / "recording")
    assert rec.n >= 1 and list(rec.scan_index) == list(range(rec.n))
