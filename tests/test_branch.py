"""Branching a recorded run: the exact state after any recorded step, continued with or without
other parameters, recorded in a folder of its own."""

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from lidarloc.core.config import Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.runs import recording
from lidarloc.core.runs.branch import open_branch
from lidarloc.core.runs.recording import RecordingError
from lidarloc.core.runs.resume import CHECKPOINT_EVERY
from lidarloc.core.sequences.factory import SourceSpec
from rich.console import Console

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

N_SCANS = 40
BRANCH_AT = 23  # not a multiple of CHECKPOINT_EVERY: the branch replays steps 21…23


def quiet() -> Console:
    return Console(stderr=True, quiet=True)


def town_cfg() -> Config:
    from helpers import MAPPING_SCANS

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS  # as helpers.short_town: the map builds in seconds
    # S2M at the PF's priority: the replay clock waits for every match, and a niced S2M beside
    # busy processes gets a sliver of a core (the priority never changes a replay's result)
    cfg.s2m.replay_process_nice = 0
    return cfg


def folder_digest(folder: Path) -> dict[str, str]:
    return {
        str(f.relative_to(folder)): hashlib.sha256(f.read_bytes()).hexdigest()
        for f in sorted(folder.rglob("*"))
        if f.is_file()
    }


@pytest.fixture(scope="module")
def original(recorded_town_run_40) -> Path:
    """A replay-clock `lidarloc run` of 40 town scans with S2M on, recorded (the default): the
    session's, which the examples use too (conftest.recorded_town_run_40)."""
    assert recording.open(recorded_town_run_40).n == N_SCANS
    return recorded_town_run_40


def test_a_run_records_by_default_and_not_with_no_record(original, tmp_path, cache_root):
    from lidarloc.app.headless import run_headless

    rec = recording.open(original)
    assert rec.n == N_SCANS and rec.meta["clock"] == "replay" and rec.meta["branch_of"] is None
    assert rec.summary is not None and rec.summary["scans"] == N_SCANS
    # checkpoints every CHECKPOINT_EVERY steps, an outcome for every landed match, small per-step fields
    assert rec.resume_steps("checkpoint") == list(range(0, N_SCANS, CHECKPOINT_EVERY))
    landed = np.flatnonzero(rec.field("s2m_landed_started") >= 0).tolist()
    assert landed == rec.resume_steps("s2m_outcome") == rec.s2m_steps and len(landed) > 5
    per_step = sum(
        (rec.path / f"{name}.bin").stat().st_size
        for name in (
            "odom_pose",
            "odom_prev_pose",
            "odom_path_turned",
            "odom_prev_path_turned",
            "odom_origin",
            "odom_used",
            "s2m_landed_started",
        )
    )
    assert per_step / rec.n < 400
    # the recorded odometry is the one the filter used: consecutive steps chain up
    pose, prev = rec.field("odom_pose"), rec.field("odom_prev_pose")
    assert np.array_equal(pose[5], prev[6]) and np.all(np.isfinite(pose))

    out = tmp_path / "unrecorded"
    run_headless(
        SourceSpec(scans=N_SCANS), town_cfg(), out, cache_root=cache_root, console=quiet(), stop_after=2, record=False
    )
    assert (out / "summary.json").is_file() and not (out / "recording").exists()


def branch_to_the_end(rec, seq, k: int, out, cache_root, check=None) -> None:
    """Branch ``rec`` at step k with no change, record it into ``out`` to the end, and check it
    repeats the original bit for bit (``check(branch)`` first, on the fresh branch)."""
    from lidarloc.core.runs.branch import continue_recording, open_branch
    from lidarloc.core.runs.recording import RecordingWriter

    branch = open_branch(rec, k, seq=seq, cache_root=cache_root)
    try:
        if check is not None:
            check(branch)
        w = RecordingWriter(
            out, rec.source_spec(), branch.cfg, seq, branch_of={"run": str(rec.run_dir), "step": k}, first_step=k + 1
        )
        continue_recording(w, branch)
        while not branch.done:
            w.on_scan(branch, branch.step())
        w.close()
    finally:
        branch.close()
    branch_rows_equal_original(recording.open(out), rec, k)


def branch_rows_equal_original(branch: recording.Recording, rec: recording.Recording, k: int) -> None:
    """Every row of the branch equals the original's from step k + 1 on, bit for bit."""
    assert branch.n == rec.n - (k + 1) and branch.n > 0
    for j in range(branch.n):
        i = k + 1 + j
        assert branch.scan_index[j] == rec.scan_index[i]
        assert np.array_equal(branch.mean_pose[j], rec.mean_pose[i]), f"mean pose differs at step {i}"
        assert np.array_equal(branch.particles(j), rec.particles(i)), f"particles differ at step {i}"
        assert np.array_equal(branch.log_weights(j), rec.log_weights(i))
        assert branch.n_eff[j] == rec.n_eff[i] and branch.cov_xyz[j].tobytes() == rec.cov_xyz[i].tobytes()
        assert branch.localized[j] == rec.localized[i]
        assert np.array_equal(branch.field("odom_pose")[j], rec.field("odom_pose")[i])
    assert [(s + k + 1, e) for s, e in branch.events] == [(s, e) for s, e in rec.events if s > k]
    assert [s + k + 1 for s in branch.s2m_steps] == [s for s in rec.s2m_steps if s > k]
    for s in branch.s2m_steps:
        a, b = branch.s2m(s), rec.s2m(s + k + 1)
        assert np.array_equal(a.pose, b.pose) and a.accepted == b.accepted and a.started_at == b.started_at


def test_a_branch_without_a_change_repeats_the_run_bit_for_bit(original, tmp_path, cache_root):
    from lidarloc.app.branch import run_branch

    before = folder_digest(original)
    out = tmp_path / "same"
    summary, _ = run_branch(original, BRANCH_AT, None, out, cache_root=cache_root, console=quiet())
    rec, branch = recording.open(original), recording.open(out)
    assert branch.meta["branch_of"] == {"run": str(original), "step": BRANCH_AT}
    assert branch.meta["first_step"] == BRANCH_AT + 1
    branch_rows_equal_original(branch, rec, BRANCH_AT)
    # the results folder covers the whole run: the recorded steps, then the branch's
    assert summary["scans"] == N_SCANS and summary["branch_of"]["step"] == BRANCH_AT
    assert summary["localized_at_scan"] == rec.summary["localized_at_scan"]
    assert len((out / "trajectory_kitti.txt").read_text().splitlines()) == N_SCANS
    # a branch of the branch: its recording holds its own steps, the history comes from its parents
    again = tmp_path / "again"
    summary, _ = run_branch(out, 5, None, again, cache_root=cache_root, console=quiet())
    branch_rows_equal_original(recording.open(again), rec, BRANCH_AT + 1 + 5)
    assert summary["scans"] == N_SCANS and summary["localized_at_scan"] == rec.summary["localized_at_scan"]
    assert folder_digest(original) == before


def test_a_branch_with_another_sigma_diverges_into_its_own_folder(original, tmp_path, cache_root):
    from lidarloc.app.branch import run_branch

    before = folder_digest(original)
    out = tmp_path / "sigma"
    run_branch(
        original, BRANCH_AT, ["pf.sigma=0.7"], out, cache_root=cache_root, console=quiet(), stop_after=BRANCH_AT + 1 + 6
    )
    rec, branch = recording.open(original), recording.open(out)
    assert branch.n == 6 and branch.meta["config"]["pf"]["sigma"] == 0.7
    assert rec.meta["config"]["pf"]["sigma"] == 0.5
    # with the paper's likelihood the weights collapse onto a few particles whatever σ, so the
    # estimate moves only where another particle wins
    rows = range(BRANCH_AT + 1, BRANCH_AT + 7)
    assert not np.array_equal(branch.n_eff, rec.n_eff[rows])
    assert not np.array_equal(branch.mean_pose, rec.mean_pose[rows])
    # … but it is still localized where the original was (σ 0.7 is a sane value)
    err = np.linalg.norm(branch.mean_pose[:, :3, 3] - rec.mean_pose[BRANCH_AT + 1 : BRANCH_AT + 7, :3, 3], axis=1)
    assert np.all(err < 2.0)
    assert folder_digest(original) == before
    with pytest.raises(LidarlocError, match="folder of its own"):
        run_branch(original, BRANCH_AT, None, original / "inside", cache_root=cache_root, console=quiet())


def test_a_branch_across_a_kidnap_in_the_original(tmp_path, cache_root):
    """The kidnap is a control between two steps: the step after it is checkpointed, so a branch
    after it restores the restarted odometry and repeats the run from there bit for bit."""
    from helpers import short_town
    from lidarloc.core.localizer import Localizer
    from lidarloc.core.runs.recording import RecordingWriter

    seq = short_town(24)
    run = tmp_path / "kidnapped"
    loc = Localizer(seq, town_cfg(), cache_root)
    try:
        w = RecordingWriter(run, SourceSpec(scans=24), loc.cfg, seq)
        while not loc.done:
            if loc.steps == 6:
                loc.kidnap(3)  # scans 6…8 are skipped
            w.on_scan(loc, loc.step())
        w.close()
    finally:
        loc.close()
    rec = recording.open(run)
    assert any(e.kind == "kidnap" for _, e in rec.events) and rec.scan_index[6] == 9
    assert 6 in rec.resume_steps("checkpoint")  # the first step after the kidnap
    k = 8  # replays steps 7 and 8

    def after_the_kidnap(branch):
        assert branch.odometry.origin == 9 and branch.k == rec.scan_index[k] + 1

    branch_to_the_end(rec, seq, k, tmp_path / "branch", cache_root, after_the_kidnap)
    # before the kidnap: a branch repeats the original up to it, then drives on without it (the
    # kidnap was a control, not part of the recorded run's state)
    before = open_branch(rec, 4, seq=seq, cache_root=cache_root)
    try:
        assert np.array_equal(before.step().mean_pose, rec.mean_pose[5])
        assert [before.step().scan_index for _ in range(2)] == [6, 7]
    finally:
        before.close()


def test_s2m_joining_late_joins_the_replay_at_the_same_scan(tmp_path, cache_root):
    """A viewer's first start on an empty cache plays without S2M until its tables are built in
    the background, at a scan timing chose: a replay from before it holds S2M back until then."""
    from helpers import short_town
    from lidarloc.core.localizer import S2M_READY_DETAIL, Localizer
    from lidarloc.core.matching.pending import S2MNotReady
    from lidarloc.core.runs.recording import RecordingWriter
    from lidarloc.core.runs.resume import checkpoint_state

    seq = short_town(20)
    run = tmp_path / "late"
    loc = Localizer(seq, town_cfg(), cache_root)
    try:
        real, loc.s2m = loc.s2m, S2MNotReady()  # as Localizer(defer_s2m=True) starts
        w = RecordingWriter(run, SourceSpec(scans=20), loc.cfg, seq)
        while not loc.done:
            if loc.steps == 12:  # as Localizer._join_s2m
                loc.s2m = real
                loc._event(loc.k, "s2m_ready", S2M_READY_DETAIL)
            w.on_scan(loc, loc.step())
        w.close()
    finally:
        loc.close()
    rec = recording.open(run)
    assert checkpoint_state(rec.resume_file(10, "checkpoint"))["s2m"]["pending"]
    assert rec.s2m_steps and rec.s2m_steps[0] > 12
    branch_to_the_end(rec, seq, 11, tmp_path / "branch", cache_root)


def test_a_recording_cut_short_branches_at_its_last_complete_step(original, tmp_path, cache_root):
    """A killed run: the last step's commit row and half its particle rows are missing. It still
    branches at its last complete step, and the branch goes on past it (live odometry warmed up
    on the scans before, the match in flight run for real)."""
    cut = tmp_path / "killed"
    shutil.copytree(original, cut)
    steps = cut / "recording" / "steps.bin"
    steps.write_bytes(steps.read_bytes()[: -8 * 6])  # the last six steps did not commit …
    particles = cut / "recording" / "particles.bin"
    particles.write_bytes(particles.read_bytes()[: -44 * 500])  # … and the last is half written
    (cut / "summary.json").unlink()
    rec, full = recording.open(cut), recording.open(original)
    last = rec.n - 1
    assert rec.n == N_SCANS - 6
    loc = open_branch(rec, last, cache_root=cache_root)
    try:
        assert np.array_equal(loc.snapshot().mean_pose, full.mean_pose[last])
        reused, landed = loc.s2m.recorded.reused, loc.s2m.n_landed
        for i in range(last + 1, last + 4):  # scans the recording has no pose for
            snap = loc.step()
            assert snap.scan_index == full.scan_index[i]
            assert np.linalg.norm(snap.mean_pose[:3, 3] - full.mean_pose[i][:3, 3]) < 1.0
        assert loc.odometry.live_from == full.scan_index[last + 1]
        assert loc.s2m.n_landed > landed and loc.s2m.recorded.reused == reused  # the matcher ran
    finally:
        loc.close()


def test_a_real_time_original_branches_from_its_recorded_state(tmp_path, cache_root):
    """In real time the landings and the odometry the rules read depended on timing: the replay
    repeats them as recorded and comes back to the recorded state; after it the branch keeps its
    own time."""
    from lidarloc.app.headless import run_headless

    cfg = town_cfg()
    cfg.localize.clock = "realtime"
    out = tmp_path / "realtime"
    run_headless(SourceSpec(scans=24), cfg, out, cache_root=cache_root, console=quiet())
    rec = recording.open(out)
    k = rec.resume_steps("checkpoint")[-1] - CHECKPOINT_EVERY + 3  # replays three steps
    assert rec.meta["clock"] == "realtime" and 0 < k < rec.n - 1 and k not in rec.resume_steps("checkpoint")
    loc = open_branch(rec, k, cache_root=cache_root)
    try:
        snap = loc.snapshot()
        assert snap.scan_index == rec.scan_index[k] and np.array_equal(snap.mean_pose, rec.mean_pose[k])
        assert np.array_equal(snap.particles.astype(np.float32), rec.particles(k))
        while not loc.done:
            snap = loc.step()
            assert np.all(np.isfinite(snap.mean_pose))
        assert snap.scan_index == rec.scan_index[rec.n - 1]
    finally:
        loc.close()


def test_bad_branches_get_one_line_errors(original, tmp_path, cache_root):
    rec = recording.open(original)
    for step in (rec.n, -1):
        with pytest.raises(LidarlocError, match="outside the recording"):
            open_branch(rec, step, cache_root=cache_root)
    with pytest.raises(LidarlocError, match="map.voxel_size cannot change in a branch .the map would differ"):
        open_branch(rec, 5, ["map.voxel_size=0.3"], cache_root=cache_root)
    with pytest.raises(LidarlocError, match="unknown key"):
        open_branch(rec, 5, ["pf.nonsense=1"], cache_root=cache_root)
    with pytest.raises(LidarlocError, match="sigma"):
        open_branch(rec, 5, {"sigma": -1.0}, cache_root=cache_root)
    # a foreign folder, a corrupt index
    (tmp_path / "foreign").mkdir()
    with pytest.raises(RecordingError, match="not a recorded run"):
        open_branch(tmp_path / "foreign", 0)
    corrupt = tmp_path / "corrupt"
    shutil.copytree(original / "recording", corrupt / "recording")
    (corrupt / "recording" / "index.json").write_text("{not json")
    with pytest.raises(RecordingError, match="unreadable recording index"):
        open_branch(corrupt, 0)
    # a checkpoint that is not one
    broken = tmp_path / "broken"
    shutil.copytree(original / "recording", broken / "recording")
    (broken / "recording" / "resume" / "000000-checkpoint.npz").write_bytes(b"not an npz")
    with pytest.raises(RecordingError, match="000000-checkpoint.npz: unreadable"):
        open_branch(broken, 3, cache_root=cache_root)
    # a source that moved: the error names the path the run expected
    moved = tmp_path / "moved"
    shutil.copytree(original / "recording", moved / "recording")
    index = json.loads((moved / "recording" / "index.json").read_text())
    index["meta"]["source"]["scans_dir"] = str(tmp_path / "gone" / "scans")
    (moved / "recording" / "index.json").write_text(json.dumps(index))
    with pytest.raises(RecordingError, match=str(tmp_path / "gone" / "scans")):
        open_branch(moved, 3, cache_root=cache_root)
    from lidarloc.app.branch import parse_branch

    assert parse_branch("out/run0:412") == (Path("out/run0"), 412)
    with pytest.raises(LidarlocError, match="RUN_DIR:STEP"):
        parse_branch("out/run0")


def test_bench_branch_times_every_replay_length_and_sizes_the_payload(original, cache_root):
    from lidarloc.app.bench.branch import BUDGET_MB_PER_1000, run

    result = run(None, None, None, cache_root=cache_root, run_dir=original, repeats=1)
    assert set(result["branch_start_s_by_replayed_steps"]) == {str(r) for r in range(CHECKPOINT_EVERY)}
    assert 0 < result["branch_start_s_median"] < 30 and result["recorded_steps"] == N_SCANS
    assert 0 < result["checkpoints_and_per_step_mb_per_1000"] < BUDGET_MB_PER_1000
    # scaled to 1000 particles: at least the run's own (the same where the run kept 1000 throughout)
    at_1000 = result["checkpoints_and_per_step_mb_per_1000_at_1000_particles"]
    assert at_1000 >= result["checkpoints_and_per_step_mb_per_1000"] - 0.01  # both rounded to 0.01 MB
    assert result["s2m_outcomes_mb_per_1000"] > 0


def test_catching_up_after_a_checkpoint_registers_only_the_scans_after_its_newest():
    """A checkpoint keeps the odometry buffer's last scans, not every scan since the run's first:
    resuming at scan 1000 must not read and register the 990 scans before the buffer again."""
    from concurrent.futures import ThreadPoolExecutor

    from lidarloc.core.config import Config
    from lidarloc.core.geometry import pose_matrix
    from lidarloc.core.odometry.feed import OdometryFeed

    recorded = np.stack([pose_matrix(1.0 * k, 0, 0, 0, 0, 0) for k in range(20)])
    with ThreadPoolExecutor(1) as pool:
        feed = OdometryFeed(Config(), recorded, pool, lambda fut, what, k: fut.result())
        feed.restart(origin=0)
        for k in range(12):
            feed.submit(k, np.zeros((1, 3)), 0.1 * k)
        for k in range(12):
            feed.wait_registered(k)
        saved = feed.checkpoint()
        keep = slice(len(saved["scans"]) - 3, None)  # a buffer holding only scans 9–11
        saved = {
            **saved,
            "scans": saved["scans"][keep],
            "poses": saved["poses"][keep],
            "times_path_turned": saved["times_path_turned"][keep],
        }
        read = []
        feed.restore(saved)
        feed.catch_up(14, lambda k: read.append(k) or np.zeros((1, 3)), lambda k: 0.1 * k)
        assert read == [12, 13]
        for k in (12, 13):
            feed.wait_registered(k)


def test_a_replay_hears_an_early_agreement_where_the_recorded_run_did():
    """Real time: a match that agreed with the estimate before it could land (an ``s2m_agrees``
    event) is heard at the same scan in a replay of the recording, if that step is replayed with
    the recorded timing."""
    from types import SimpleNamespace

    from lidarloc.core.runs.branch import RecordedMatches
    from lidarloc.core.snapshot import Event

    agrees = "agrees with the estimate before it lands; the odometry is at scan 40"
    events = [
        (41, Event(41, "s2m_started", "particle 3")),
        (44, Event(44, "s2m_agrees", f"started 41: {agrees}")),
        (61, Event(61, "s2m_agrees", f"started 60: {agrees}")),
    ]
    rec = SimpleNamespace(n=80, field_names=[], events=events)
    matches = RecordedMatches(rec)
    assert matches.agreed_early_scan(41) == 44 and matches.agreed_early_scan(60) == 61
    assert matches.agreed_early_scan(50) is None
    assert RecordedMatches(rec, timing_until=50).agreed_early_scan(60) is None  # after the recorded timing
