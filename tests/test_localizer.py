"""The localizer (core/localizer.py, core/matching/schedule.py, core/odometry/feed.py): blocks in threads and
child processes, replay determinism, S2M sample update, rules → re-init, kidnap, failing blocks,
interrupting a step (the real-time clock: test_localizer_realtime.py)."""

import os
import time
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from helpers import instant_matcher, make_localizer, process_gone, scripted_std, short_town, wait_for
from lidarloc.core.config import Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.localizer import BlockError

N_SCANS = 60
# A block that fails or dies must stop the run at once instead of hanging; these bounds only
# catch a hang (the failure itself comes within a scan or two), with room for a loaded machine.
HANG_BOUND_S = 30


@pytest.fixture(scope="module")
def town(cache_root):
    return short_town(N_SCANS)


# 500 particles, and the S2M process at the PF's priority: the replay clock waits for every match,
# and a niced S2M beside busy processes gets a sliver of a core (the priority never changes a
# replay's result)
make = partial(make_localizer, n_particles=500, s2m_nice=0)


def replay_12(seq, cache_root, check=None, **overrides):
    """12 scans of ``seq`` on the replay clock (then ``check(localizer)``, if given): the
    particles, the records and the events."""
    with make(seq, cache_root, **overrides) as loc:
        loc.run(12)
        if check is not None:
            check(loc)
        return (
            loc.pf.states.copy(),
            [(r.x, r.y, r.z, r.yaw, r.n_eff) for r in loc.records],
            [(e.scan, e.kind) for e in loc.events],
        )


@pytest.fixture(scope="module")
def live_replay(town, cache_root):
    """The default run (live KISS-ICP odometry) of 12 scans, which the determinism and the
    recorded-odometry tests each compare a run of their own with."""
    return replay_12(town, cache_root)


@pytest.mark.slow
def test_replay_is_deterministic(town, cache_root, live_replay):
    again = replay_12(town, cache_root)
    assert np.array_equal(live_replay[0], again[0])
    assert live_replay[1] == again[1]
    assert live_replay[2] == again[2]
    assert any(kind == "s2m_started" for _, kind in live_replay[2])


def test_s2m_particle_survives_and_is_updated(town, cache_root):
    """Started at k, landed at k + n_s2m: the particle it started from is still there, and holds
    the match carried forward to k' (close to the truth when started near the truth)."""
    with make(town, cache_root) as loc:
        gt0 = town.poses[0]
        loc.reset(pose=gt0)
        loc.step()  # scan 0: a job starts on the best particle
        job = loc.s2m.job
        assert job is not None and job.started_at == 0
        j = job.particle
        written = []
        real_set = loc.pf.set_particle
        loc.pf.set_particle = lambda idx, state: (written.append((idx, np.array(state))), real_set(idx, state))[1]
        landed = None
        for _ in range(loc.cfg.s2m.n_s2m):
            loc.step()
            kinds = [e for e in loc.events if e.kind in ("s2m_accepted", "s2m_rejected")]
            if kinds:
                landed = kinds[-1]
        assert landed is not None and landed.scan == loc.cfg.s2m.n_s2m
        assert landed.kind == "s2m_accepted", landed.detail
        k_prime = landed.scan
        # exactly the slot the job started from received the carried pose, close to the truth at k'
        assert len(written) == 1 and written[0][0] == j
        carried = loc.snapshot().s2m.pose
        assert np.allclose(written[0][1][:3], carried[:3, 3])
        assert np.linalg.norm(carried[:3, 3] - town.poses[k_prime][:3, 3]) < 1.0


def test_false_positive_triggers_reinit(town, cache_root):
    with make(town, cache_root, s2m__enabled=False) as loc:
        scripted_std(loc, [100.0, 3.0, 3.0, 3.0, 100.0])
        spread_calls = []
        real_init = loc.pf.initialize
        loc.pf.initialize = lambda *a, **k: (spread_calls.append((a, k)), real_init(*a, **k))[1]
        loc.run(5)
        kinds = [(e.scan, e.kind) for e in loc.events]
        assert (4, "false_positive") in kinds
        assert spread_calls == [((), {"region": None, "pose": None})], (
            "a false positive re-initialises over the whole map"
        )
        assert loc.records[4].reinit


def test_a_cancelled_match_is_reported(town, cache_root):
    """A match in flight when the particles are re-initialised (or kidnapped) can no longer land:
    an s2m_cancelled event says so, and every s2m_started ends in exactly one outcome, also
    the match in flight when the run ends."""
    loc = make(town, cache_root, localize__s2m_process=False, s2m__n_s2m=3)
    try:
        instant_matcher(loc)
        scripted_std(loc, [100.0, 3.0, 3.0, 3.0, 100.0])
        loc.run(5)  # starts at 0, lands and restarts at 3, false positive at 4
        kinds = [(e.scan, e.kind) for e in loc.events]
        assert (3, "s2m_started") in kinds and (4, "false_positive") in kinds
        cancelled = [e for e in loc.events if e.kind == "s2m_cancelled"]
        assert [(e.scan, e.detail) for e in cancelled] == [(4, "started 3 (re-initialised after a false positive)")]
        assert loc.s2m.job is None
        loc.run(1)  # a new job starts at 5 …
        assert loc.s2m.job is not None
        loc.kidnap(10)  # … and the kidnap cancels it
        assert [e.kind for e in loc.events][-2:] == ["s2m_cancelled", "kidnap"]
        loc.run(1)  # one more starts, and is in flight when the run ends
        assert loc.s2m.job is not None
    finally:
        loc.close()
    assert loc.events[-1].kind == "s2m_cancelled" and loc.events[-1].detail.endswith("(localizer closed)")
    counts = {
        kind: sum(e.kind == kind for e in loc.events)
        for kind in ("s2m_started", "s2m_accepted", "s2m_rejected", "s2m_cancelled")
    }
    assert counts["s2m_started"] == counts["s2m_accepted"] + counts["s2m_rejected"] + counts["s2m_cancelled"]


def test_loss_triggers_reinit(town, cache_root):
    with make(town, cache_root, s2m__enabled=False, localize__require_s2m_confirmation=False) as loc:
        scripted_std(loc, [3.0] * 20 + [60.0])
        loc.run(21)
        kinds = [e.kind for e in loc.events]
        assert "localized" in kinds and kinds.index("localized") < kinds.index("loss")
        loss = next(e for e in loc.events if e.kind == "loss")
        assert loss.scan == 20 and loc.records[20].reinit and not loc.rules.localized


def test_failing_block_stops_cleanly(town, cache_root):
    loc = make(town, cache_root, localize__s2m_process=False)

    def boom(*a, **k):
        raise RuntimeError("matcher exploded")

    loc.s2m.matcher.match_local = boom
    t0 = time.perf_counter()
    with pytest.raises(BlockError, match="S2M block failed at scan 2: RuntimeError: matcher exploded"):
        loc.run(10)
    # the half-done step is not silently repeated: further steps refuse until a restart
    with pytest.raises(LidarlocError, match="restart to continue"):
        loc.step()
    loc.close()
    assert time.perf_counter() - t0 < HANG_BOUND_S
    assert any(e.kind == "error" for e in loc.events)


@pytest.mark.slow
def test_s2m_process_priority_follows_the_clock(town, cache_root):
    """In replay the S2M child lowers its nice value and, where the kernel groups sessions for
    scheduling (autogroups), its group's too (otherwise it competes with the PF as an equal
    group). Switching to real time replaces it with a child at normal priority, which still
    matches."""

    def nice_of(pid):
        value = os.getpriority(os.PRIO_PROCESS, pid)
        group = Path(f"/proc/{pid}/autogroup")
        enabled = Path("/proc/sys/kernel/sched_autogroup_enabled")
        grouped = enabled.exists() and enabled.read_text().strip() == "1" and group.exists()
        return value, (int(group.read_text().split()[-1]) if grouped else None)

    own = os.getpriority(os.PRIO_PROCESS, 0)
    with make(town, cache_root, s2m__replay_process_nice=Config().s2m.replay_process_nice) as loc:
        want = loc.cfg.s2m.replay_process_nice
        assert want > 0
        loc.run(3)  # the first match landed at scan 2: the child is set up
        assert any(e.kind in ("s2m_accepted", "s2m_rejected") for e in loc.events)
        first = loc.s2m.matcher
        value, group = nice_of(first.pid)
        assert value == min(19, own + want)
        assert group in (None, want)
        loc.set_params(clock="realtime")
        assert loc.s2m.matcher is not first and loc.s2m.matcher.pid != first.pid
        loc.run(3)
        value, group = nice_of(loc.s2m.matcher.pid)
        assert value == own and group in (None, 0)
        wait_for(lambda: process_gone(first.pid), timeout=30, what="the replaced S2M process to be closed")
        job = loc.s2m.job  # real time lands a match at the first scan after it is done
        assert job is not None and job.started_at >= 3
        job.future.result(timeout=120)
        # An accepted match waits (at most REALTIME_LAND_FORCE_AFTER scans) for the odometry
        # of the scan it lands at; a rejected one lands at once.
        from lidarloc.core.matching.realtime_landing import REALTIME_LAND_FORCE_AFTER

        for _ in range(REALTIME_LAND_FORCE_AFTER + 1):
            loc.run(1)
            if loc.s2m.job is not job:
                break
        assert any(e.kind in ("s2m_accepted", "s2m_rejected") for e in loc.events if e.scan >= 4)


def test_s2m_process_matches_thread(town, cache_root):
    """The S2M block gives the same trajectory in its child process as on a thread."""
    trajectories = []
    for in_process in (True, False):
        with make(town, cache_root, localize__s2m_process=in_process) as loc:
            loc.run(8)
            trajectories.append(np.array([r.x for r in loc.records] + [r.y for r in loc.records]))
            assert any(e.kind in ("s2m_accepted", "s2m_rejected") for e in loc.events)
    np.testing.assert_array_equal(trajectories[0], trajectories[1])


def test_live_parameters_validated(town, cache_root):
    with make(town, cache_root) as loc:
        for bad in (
            {"sigma": 0.0},
            {"sigma": -1},
            {"d_max": float("nan")},
            {"q_std": (1.0,) * 3},
            {"n_particles": 0},
            {"clock": "warp"},
            {"nonsense": 1},
        ):
            with pytest.raises(LidarlocError):
                loc.set_params(**bad)
        loc.set_params(sigma=0.8, d_max=3.0, region_x=10.0, n_particles=200)
        loc.step()
        assert loc.pf.states.shape == (200, 11) and loc.cfg.pf.sigma == 0.8 and loc.cfg.s2m.region_x == 10.0


def test_reset_in_region_and_kidnap(town, cache_root):
    with make(town, cache_root) as loc:
        loc.reset(region=(10.0, -5.0, 30.0, 5.0))
        xy = loc.pf.states[:, :2]
        assert (xy[:, 0] >= 10).all() and (xy[:, 0] <= 30).all() and (xy[:, 1] >= -5).all() and (xy[:, 1] <= 5).all()
        loc.step()
        new_k = loc.kidnap(20)
        assert new_k == 21 and loc.k == 21
        snap = loc.step()
        assert snap.scan_index == 21


def test_interrupt_stops_a_step_waiting_for_a_block(town, cache_root):
    """interrupt() makes a step that waits for its match give up at once: the scan is not
    recorded, earlier ones stay, and further steps refuse until restart()."""
    import threading

    from lidarloc.core.localizer import Interrupted

    gate = threading.Event()  # the match never finishes until the gate opens
    with make(town, cache_root, localize__s2m_process=False) as loc:
        instant_matcher(loc, before=gate.wait)
        loc.run(loc.cfg.s2m.n_s2m)  # the match started at scan 0 is due at scan n_s2m …
        events = list(loc.events)
        raised = []

        def step():
            try:
                loc.step()
            except Interrupted as exc:
                raised.append(exc)

        worker = threading.Thread(target=step)
        worker.start()  # … so this step waits for it
        loc.interrupt()
        worker.join(timeout=30)
        gate.set()
        assert not worker.is_alive() and len(raised) == 1, "the step did not give up"
        assert len(loc.records) == loc.cfg.s2m.n_s2m and loc.k == loc.cfg.s2m.n_s2m
        assert loc.events == events, "the dropped scan's events are dropped with it"
        assert loc.s2m.job is not None and loc.s2m.job.started_at == 0, "still in flight, to be cancelled"
        with pytest.raises(Interrupted):
            loc.step()
        loc.restart()
        loc.run(1)
        assert len(loc.records) == 1


@pytest.mark.slow
def test_kidnap_mid_run_is_recovered(kitti_raw_seq, cache_root):
    """Tracking on the real drive, the vehicle is moved ~18 m ahead without telling the filter;
    the local S2M around the (now wrong) best particle finds it again within a few scans."""
    seq = kitti_raw_seq
    with make(seq, cache_root) as loc:
        loc.reset(pose=seq.poses[0])
        loc.run(15)
        assert loc.snapshot().error_m < 1.0
        target = loc.kidnap(15)
        jump = np.linalg.norm(seq.poses[target][:3, 3] - seq.poses[14][:3, 3])
        first = loc.step()
        assert first.error_m > 10.0, f"the kidnap must put the estimate far off (jump {jump:.1f} m)"
        errors = [loc.step().error_m for _ in range(15)]
        recovered_at = next(i for i, e in enumerate(errors) if e < 1.0)
        assert recovered_at <= 8, errors
        assert max(errors[recovered_at:]) < 1.0, errors


@pytest.mark.slow
def test_recorded_odometry_changes_nothing(town, cache_root, live_replay):
    """Replaying the cached KISS-ICP poses gives the live run's trajectory bit for bit (what lets
    ``bench localize`` compute the odometry once per sequence instead of once per run)."""

    def check(loc):
        assert loc.odometry.process is None, "no KISS-ICP process when the odometry is recorded"
        with pytest.raises(LidarlocError, match="live odometry"):
            loc.set_params(clock="realtime")

    recorded = replay_12(town, cache_root, check=check, localize__recorded_odometry=True)
    np.testing.assert_array_equal(np.array(live_replay[1]), np.array(recorded[1]))


def test_tracking_mode_and_search_regions(town, cache_root):
    """Until localized S2M searches the whole map; tracking mode then shrinks the filter and the
    S2M region, and a loss brings the full filter back."""
    with make(town, cache_root, localize__tracking=True, localize__tracking_particles=100) as loc:
        (x0, y0, _), (x1, y1, _) = loc.prior_map.bounds
        whole = loc.s2m.job_config(loc.pf.states[0], loc.rules.localized)
        x, y = loc.pf.states[0, :2]
        assert x - whole.region_x <= x0 and x + whole.region_x >= x1
        assert y - whole.region_y <= y0 and y + whole.region_y >= y1
        scripted_std(loc, [3.0] * 20 + [60.0])
        loc.run(20)
        assert [e.kind for e in loc.events].count("tracking") == 1 and loc.rules.localized
        assert loc.pf.n == 100 and loc.pf.states.shape == (100, 11)
        tracking = loc.s2m.job_config(loc.pf.states[0], loc.rules.localized)
        assert tracking.region_x == tracking.region_y == 10.0
        loc.run(1)
        assert any(e.kind == "loss" for e in loc.events) and not loc.rules.localized
        assert loc.pf.n == 500, "a loss leaves tracking mode: the full particle count comes back"


def test_wait_ready_reports_a_failed_set_up(town, cache_root, tmp_path):
    """wait_ready() blocks until the child processes are set up, and a set-up failure is a clear
    one-line error there, before the real-time clock starts."""
    from lidarloc.core.matching.worker import S2MProcess

    with make(town, cache_root) as loc:
        loc.wait_ready()  # the normal case: returns once everything is up
        good = loc.s2m.matcher
        loc.s2m.matcher = S2MProcess(tmp_path / "no-such-map", loc.cfg.map, loc.cfg.s2m)
        try:
            with pytest.raises(BlockError, match="set-up failed: FileNotFoundError"):
                loc.wait_ready()
        finally:
            loc.s2m.matcher.close()
            loc.s2m.matcher = good
