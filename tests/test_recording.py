"""A run's recording: every step's state appended as it happens, read back as it was."""

import json
from pathlib import Path

import numpy as np
import pytest
from lidarloc.core.config import Config
from lidarloc.core.runs import recording
from lidarloc.core.runs.recording import RecordingError, RecordingWriter, ResumePayload
from lidarloc.core.sequences.factory import SourceSpec


@pytest.fixture(scope="module")
def recorded(street, cache_root, tmp_path_factory):
    """Twelve recorded steps of the street, with the snapshots the localizer returned."""
    from helpers import make_localizer

    run = tmp_path_factory.mktemp("run")
    loc = make_localizer(street, cache_root)
    snaps = []
    try:
        w = RecordingWriter(run, SourceSpec(), loc.cfg, street)
        for _ in range(12):
            snap = loc.step()
            w.on_scan(loc, snap)
            snaps.append(snap)
        w.close({"scans": 12})
        events = list(loc.events)
    finally:
        loc.close()
    return run, snaps, events


def test_every_step_reads_back_as_the_localizer_reported_it(recorded):
    run, snaps, events = recorded
    rec = recording.open(run)
    assert rec.n == len(snaps) == 12
    assert rec.path == run / "recording" and rec.run_dir == run
    for i, snap in enumerate(snaps):
        assert rec.scan_index[i] == snap.scan_index
        assert np.array_equal(rec.mean_pose[i], snap.mean_pose)  # float64 kept exactly
        assert np.array_equal(rec.cov_xyz[i], snap.cov_xyz)
        assert rec.n_eff[i] == snap.n_eff and rec.localized[i] == snap.localized
        assert np.array_equal(rec.particles(i), snap.particles.astype(np.float32))
        assert np.allclose(rec.weights(i), snap.weights, atol=1e-6)
        assert (rec.error_m[i] == snap.error_m) if snap.error_m is not None else np.isnan(rec.error_m[i])
    # every event, in order, each after the step at which the localizer recorded it
    assert [ev for _, ev in rec.events] == events
    for step, ev in rec.events:
        assert step == -1 if ev.scan < 0 else rec.scan_index[step] == ev.scan
    assert rec.meta["seed"] == Config().seed and rec.meta["n_source_scans"] == 24
    assert rec.meta["summary"] == {"scans": 12}


def test_a_rebuilt_snapshot_is_the_step_the_viewer_saw(recorded, street):
    run, snaps, _ = recorded
    rec = recording.open(run / "recording")
    i = 7
    snap = rec.snapshot(i, street)
    live = snaps[i]
    assert snap.scan_index == live.scan_index and snap.best_index == live.best_index
    assert np.array_equal(snap.mean_pose, live.mean_pose)
    assert snap.ellipse_xy == pytest.approx(live.ellipse_xy)
    # the scan is recomputed from the source with the filter's own voxel and seed: the same points
    assert np.array_equal(snap.scan_world, live.scan_world)
    assert [e.kind for e in snap.events] == [e.kind for e in live.events]
    assert live.s2m is not None and rec.s2m_steps  # S2M matches landed by then: they are recorded
    if live.s2m is not None:
        view = rec.s2m(i)
        assert view.started_at == live.s2m.started_at and view.accepted == live.s2m.accepted
        assert np.array_equal(view.pose, live.s2m.pose) and view.region == pytest.approx(live.s2m.region)
        # its scan is kept at a display's precision (float16 in the match's frame)
        assert view.scan_world.shape == live.s2m.scan_world.shape
        assert np.abs(view.scan_world - live.s2m.scan_world).max() < 0.07


def test_a_recording_cut_short_opens_up_to_its_last_complete_step(recorded, tmp_path):
    import shutil

    run, snaps, _ = recorded
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    folder = copy / "recording"
    # a kill in the middle of step 12's particles: its commit row and part of its particles are there
    with open(folder / "particles.bin", "r+b") as f:
        f.truncate(f.seek(0, 2) - 100)
    rec = recording.open(copy)
    assert rec.n == 11
    assert np.array_equal(rec.mean_pose[10], snaps[10].mean_pose)
    # a kill while step 11 was being committed (its commit row half written)
    with open(folder / "steps.bin", "r+b") as f:
        f.truncate(f.seek(0, 2) - 8 - 3)  # step 11 not committed, step 10 half
    assert recording.open(copy).n == 10


def test_foreign_missing_and_corrupt_folders_get_one_line(tmp_path):
    with pytest.raises(RecordingError, match="no such run folder"):
        recording.open(tmp_path / "nowhere")
    (tmp_path / "plain").mkdir()
    with pytest.raises(RecordingError, match="not a recorded run"):
        recording.open(tmp_path / "plain")
    bad = tmp_path / "bad" / "recording"
    bad.mkdir(parents=True)
    (bad / "index.json").write_text("{ not json")
    with pytest.raises(RecordingError, match="unreadable recording index"):
        recording.open(bad.parent)
    (bad / "index.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(RecordingError, match="not a lidarloc recording"):
        recording.open(bad.parent)
    for err in (RecordingError,):
        assert "\n" not in str(err("x"))


class _FakeLocalizer:
    """Just enough of a Localizer for the writer: the resume payload's path through it."""

    def __init__(self, cfg):
        self.cfg, self.steps, self.events, self.records = cfg, 0, [], []

    def resume_payload(self, step):
        files = (
            {"checkpoint": {"states": np.full((3, 11), step, np.float64), "rng": np.array('{"a": 1}')}}
            if step % 2 == 0
            else {}
        )
        return ResumePayload(per_step={"odom_pose": np.eye(4) * (step + 1)}, files=files)


def _snap(k: int):
    from lidarloc.core.snapshot import Snapshot

    return Snapshot(
        scan_index=k,
        n_scans=5,
        timestamp=0.1 * k,
        particles=np.zeros((3, 11)),
        weights=np.ones(3) / 3,
        best_index=0,
        mean_pose=np.eye(4),
        cov_xyz=np.eye(3),
        std_xyz=np.ones(3),
        ellipse_xy=(1, 1, 0),
        n_eff=3.0,
        localized=False,
        localized_since=None,
        scan_world=np.zeros((0, 3), np.float32),
        gt_pose=None,
        error_m=None,
        pf_ms=1.0,
        s2m=None,
        s2m_running=False,
        s2m_acceptance=0.0,
    )


def test_the_resume_payload_is_stored_per_step_and_as_files(tmp_path):
    cfg = Config()
    loc = _FakeLocalizer(cfg)
    w = RecordingWriter(tmp_path, SourceSpec(), cfg, [0] * 5)
    for k in range(5):
        loc.steps += 1
        w.on_scan(loc, _snap(k))
    with pytest.raises(RecordingError, match="not a new step"):
        w.on_scan(loc, _snap(4))  # the same step again
    w.close()
    rec = recording.open(tmp_path)
    assert rec.n == 5
    assert np.array_equal(rec.field("odom_pose")[3], np.eye(4) * 4)
    assert rec.resume_steps("checkpoint") == [0, 2, 4]
    ck = rec.resume_file(2, "checkpoint")
    assert np.array_equal(ck["states"], np.full((3, 11), 2.0)) and json.loads(str(ck["rng"])) == {"a": 1}
    assert rec.resume_file(1, "checkpoint") is None
    assert np.isnan(rec.error_m).all() and (rec.inside_2sigma == -1).all()
    with pytest.raises(RecordingError, match="outside the recording"):
        rec.particles(5)


def test_the_source_round_trips_and_a_moved_source_is_named(tmp_path):
    cfg = Config()
    cfg.pf.sigma = 0.7
    data = tmp_path / "drive.bag"
    data.write_bytes(b"")
    spec = SourceSpec(bag=data, map=Path("relative-map.pcd"), topic="/points", scans=40)
    w = RecordingWriter(tmp_path / "run", spec, cfg, [0] * 40, preset="paper")
    w.close()
    rec = recording.open(tmp_path / "run")
    back = rec.source_spec()
    assert back.bag == data.resolve() and back.topic == "/points" and back.scans == 40
    assert back.map.is_absolute()  # relative paths are stored absolute: the run opens from anywhere
    assert rec.config().pf.sigma == 0.7 and rec.meta["preset"] == "paper"
    with pytest.raises(RecordingError, match="relative-map.pcd: the run's source is not there"):
        rec.check_source()
    with pytest.raises(RecordingError, match="already there"):
        RecordingWriter(tmp_path / "run", spec, cfg, [0] * 40)


def test_a_benchmark_run_records_itself_with_record(cache_root, tmp_path):
    """``lidarloc bench localize --record``: every run's folder gets its recording, which agrees
    with the run's own per-scan results."""
    import csv

    from helpers import MAPPING_SCANS
    from lidarloc.app.bench.localize import run_one

    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.localize.recorded_odometry = True
    cfg.town.n_scans = MAPPING_SCANS
    spec_d = {"scans": 12}
    summary = run_one(spec_d, cfg.to_dict(), 3, str(cache_root), str(tmp_path / "seed_003"), 0, record=True)
    rec = recording.open(tmp_path / "seed_003")
    assert rec.n == summary["scans"] == 12 and rec.meta["seed"] == 3
    rows = list(csv.DictReader(open(tmp_path / "seed_003" / "scans.csv")))
    assert [int(r["scan"]) for r in rows] == rec.scan_index.tolist()
    assert np.allclose([float(r["x"]) for r in rows], rec.mean_pose[:, 0, 3], atol=1e-6)
    assert rec.summary["scans"] == 12


def test_a_step_is_recorded_as_it_was_handed_over_and_seen_after_flush(tmp_path):
    """The writing thread writes copies: what the localizer changes after on_scan returned (its
    next step) is not what the recording holds; flush() makes every step handed over readable."""
    cfg = Config()
    loc = _FakeLocalizer(cfg)
    payload = ResumePayload(per_step={"odom_pose": np.eye(4)}, files={"checkpoint": {"states": np.zeros((3, 11))}})
    loc.resume_payload = lambda step: payload
    w = RecordingWriter(tmp_path, SourceSpec(), cfg, [0] * 5)
    snap = _snap(0)
    loc.steps = 1
    w.on_scan(loc, snap)
    snap.particles[:] = 7.0  # the filter moves on: the next step's state
    payload.per_step["odom_pose"][:] = 5.0
    w.flush()
    assert w.committed == w.n == 1 and recording.open(tmp_path).n == 1
    rec = recording.open(tmp_path)
    assert np.array_equal(rec.particles(0), np.zeros((3, 11), np.float32))
    assert np.array_equal(rec.field("odom_pose")[0], np.eye(4))
    w.close()
    assert w.writer_cpu_s > 0.0


def test_a_failure_to_write_is_one_line_at_the_next_step_and_at_close(tmp_path):
    import shutil

    cfg = Config()
    loc = _FakeLocalizer(cfg)  # its payload has a checkpoint file at step 0
    w = RecordingWriter(tmp_path, SourceSpec(), cfg, [0] * 5)
    shutil.rmtree(tmp_path / "recording" / "resume")  # the disk loses the folder
    loc.steps = 1
    w.on_scan(loc, _snap(0))
    with pytest.raises(RecordingError, match="cannot write the recording") as caught:
        w.flush()
    assert "\n" not in str(caught.value)
    loc.steps = 2
    with pytest.raises(RecordingError, match="cannot write the recording"):
        w.on_scan(loc, _snap(1))
    with pytest.raises(RecordingError, match="cannot write the recording"):
        w.close()
    assert recording.open(tmp_path).n == 0  # the failed step was never committed


def test_the_viewers_recorder_reports_a_write_that_failed_after_the_last_step(tmp_path):
    """The writing thread fails after the last step was handed over: closing says so through the
    viewer's message, it does not raise into the viewer's stop."""
    import shutil

    from lidarloc.app.viewer.recorder import Recorder

    cfg = Config()
    loc = _FakeLocalizer(cfg)
    loc.seq = [0] * 5
    snap = _snap(0)
    loc.snapshot = lambda: snap
    messages = []
    rec = Recorder(tmp_path / "runs", SourceSpec(), on_failure=messages.append)
    path = rec.start(loc)
    shutil.rmtree(path / "recording" / "resume")  # the checkpoint of step 0 cannot be written
    loc.steps = 1
    assert rec.on_scan(loc, snap)
    rec.close(None)
    assert len(messages) == 1 and "recording stopped" in messages[0] and "cannot write" in messages[0]


# ------------------------------------------------------------------------------ segments
def _segmented(folder):
    """A run written in three segments by the writer's ``next_segment`` (steps 0–3, 4–6, 7–9), as
    the viewer writes one under a size budget: an event per step, an S2M match landed at step 2
    (the later segments start with it), the fake's checkpoints every other row of a segment.
    Returns the live snapshots."""
    import dataclasses

    from lidarloc.core.snapshot import Event, S2MView

    cfg = Config()
    loc = _FakeLocalizer(cfg)
    view = S2MView(
        started_at=1,
        landed_at=2,
        accepted=True,
        score=1.0,
        start_score=0.5,
        pose=np.eye(4),
        scan_world=np.ones((5, 3), np.float32),
        region=(0.0, 0.0, 1.0, 1.0),
        ms=3.0,
    )
    w = RecordingWriter(folder, SourceSpec(), cfg, [0] * 12)
    snaps = []
    for k in range(10):
        if k in (4, 7):
            w = w.next_segment()
            assert w.first_step == k and w.path == folder / "recording" / "segments" / f"{k:09d}"
        loc.steps += 1
        loc.events.append(Event(k, "localized" if k == 5 else "s2m_accepted", f"at {k}"))
        snap = dataclasses.replace(_snap(k), s2m=view if k >= 2 else None, particles=np.full((3, 11), float(k)))
        w.on_scan(loc, snap)
        snaps.append(snap)
    w.flush()
    # the writer counts its bytes as it goes: the segment's size on disk
    assert abs(w.bytes - recording.segments.folder_bytes(w.path)) < 2048
    w.close({"scans": 10})
    return snaps


def test_a_run_in_segments_reads_as_one_recording(tmp_path):
    snaps = _segmented(tmp_path)
    rec = recording.open(tmp_path)
    assert rec.n == 10 and rec.first_step == 0 and rec.dropped == 0
    np.testing.assert_array_equal(rec.scan_index, np.arange(10))
    for i in (0, 3, 4, 9):
        np.testing.assert_array_equal(rec.particles(i), snaps[i].particles.astype(np.float32))
    assert [(s, e.scan) for s, e in rec.events] == [(k, k) for k in range(10)]
    # the match landed once; the later segments' first steps show it as the earlier one does
    assert rec.s2m_steps == [2] and rec.s2m(1) is None
    assert all(rec.s2m(i).landed_at == 2 for i in (2, 4, 7, 9))
    # every segment starts with a checkpoint: any step can be resumed from one at or before it
    assert rec.resume_steps("checkpoint") == [0, 2, 4, 6, 7, 9]
    assert rec.meta["summary"] == {"scans": 10} and rec.meta["first_step"] == 0
    assert recording.segments.window(tmp_path / "recording") == (0, 0, 10)


def test_a_dropped_segment_leaves_the_window_and_a_cut_at_any_moment_opens(tmp_path):
    import shutil

    from lidarloc.core.runs.recording import segments

    snaps = _segmented(tmp_path / "run")
    top = tmp_path / "run" / "recording"
    # the budget drops the first segment: its commit log first, then its files (its index stays)
    segments.drop_commit(top)
    rec = recording.open(tmp_path / "run")
    assert rec.n == 6 and rec.first_step == 4 and rec.dropped == 4 and rec.events_dropped == 4
    segments.remove_files(top, first=True)
    assert sorted(p.name for p in top.iterdir()) == ["index.json", "segments", "steps.bin"]
    rec = recording.open(tmp_path / "run")
    assert rec.n == 6 and rec.first_step == 4
    np.testing.assert_array_equal(rec.scan_index, np.arange(4, 10))
    np.testing.assert_array_equal(rec.particles(0), snaps[4].particles.astype(np.float32))
    assert [(s, e.scan) for s, e in rec.events] == [(k - 4, k) for k in range(4, 10)]
    assert rec.s2m_steps == [] and rec.s2m(0).landed_at == 2  # the view the window starts with
    assert rec.resume_steps("checkpoint")[0] == 0
    assert segments.window(top) == (0, 4, 10)
    with pytest.raises(RecordingError, match="already there"):  # no new recording over what is left
        RecordingWriter(tmp_path / "run", SourceSpec(), Config(), [0] * 12)

    def cut(name):
        case = tmp_path / name
        shutil.copytree(tmp_path / "run", case)
        return case / "recording" / "segments"

    # a drop cut short: the next segment's commit log emptied, its files still there
    seg = cut("drop-cut")
    segments.drop_commit(seg / "000000004")
    rec = recording.open(seg.parents[1])
    assert (rec.n, rec.first_step) == (3, 7)
    # a new segment cut before its index was written, or before its first step
    seg = cut("start-cut")
    (seg / "000000010").mkdir()
    assert (recording.open(seg.parents[1]).n, recording.open(seg.parents[1]).first_step) == (6, 4)
    shutil.copy(seg / "000000007" / "index.json", seg / "000000010" / "index.json")
    (seg / "000000010" / "steps.bin").write_bytes(b"")
    assert recording.open(seg.parents[1]).n == 6
    # a step cut short in the newest segment: the window ends at the step before it
    seg = cut("step-cut")
    with open(seg / "000000007" / "particles.bin", "r+b") as f:
        f.truncate(f.seek(0, 2) - 10)
    rec = recording.open(seg.parents[1])
    assert (rec.n, rec.first_step) == (5, 4)
    np.testing.assert_array_equal(rec.scan_index, np.arange(4, 9))


def test_a_source_spec_goes_to_a_dict_and_back(tmp_path):
    """What a run folder, a sweep or a corpus keeps of its source reads back as the same source;
    paths are strings in the dict (absolute ones when asked), and an option this version does not
    know is refused unless a recording from another version is being read."""
    from lidarloc.core.errors import DataError

    spec = SourceSpec(bag=Path("drive.mcap"), topic="/points", gt=tmp_path / "gt.tum", scans=7, init="1,2,30")
    d = spec.to_dict()
    assert d["bag"] == "drive.mcap" and d["scans"] == 7 and d["map"] is None
    assert json.loads(json.dumps(d)) == d
    assert SourceSpec.from_dict(d) == spec
    assert spec.to_dict(absolute=True)["bag"] == str(Path("drive.mcap").resolve())
    with pytest.raises(DataError, match="unknown source options: colour"):
        SourceSpec.from_dict({**d, "colour": "red"})
    assert SourceSpec.from_dict({**d, "colour": "red"}, ignore_unknown=True) == spec
