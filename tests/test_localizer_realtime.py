"""The localizer on the real-time clock (core/matching/schedule.py, core/odometry/feed.py): the
rules read the newest finished odometry, S2M is spaced once localized, a match lands through the
newest registered scan without waiting for lagging odometry, and never later than its deadline."""

import time
from functools import partial

import numpy as np
import pytest
from helpers import instant_matcher, make_localizer, scripted_std, short_town
from lidarloc.core.config import Config

N_SCANS = 60


@pytest.fixture(scope="module")
def town(cache_root):
    return short_town(N_SCANS)


# 500 particles, and the S2M process at the PF's priority: the replay clock waits for every match,
# and a niced S2M beside busy processes gets a sliver of a core (the priority never changes a
# replay's result)
make = partial(make_localizer, n_particles=500, s2m_nice=0)


def test_realtime_clock_counts_odometry_once(town, cache_root):
    """In real time the rules take the newest finished odometry instead of waiting for scan k's:
    every metre the odometry measured is still counted exactly once."""
    with make(town, cache_root, s2m__enabled=False, localize__clock="realtime") as loc:
        steps = []
        real = loc.rules.update

        def update(k, std_xyz, step_distance, yaw_odom, confirmed=None):
            steps.append(step_distance)
            return real(k, std_xyz, step_distance, yaw_odom, confirmed)

        loc.rules.update = update
        loc.run(25)  # as fast as possible: the odometry may fall behind …
        for k in range(25):
            loc.odometry.futures[k].result(timeout=60)
        loc.run(1)  # … and scan 25's rules see all of it, however slow the machine
        assert len(steps) == 26 and loc.odometry.used is not None and loc.odometry.used >= 24
        assert sum(steps) == pytest.approx(loc.odometry.rpe.moved_since(0, loc.odometry.used), abs=1e-9)
        assert sum(steps) > 10.0, "the town drives ~1 m per scan"


def test_realtime_s2m_spaced_once_localized(town, cache_root):
    """Real time, once localized: S2M starts at most every s2m.realtime_interval_localized scans
    (before localization, and in replay, back to back).

    Only the scheduling is under test, so nothing here depends on how fast the machine is: the
    match is an instant rejection (it lands at the next scan), and each scan's odometry is
    awaited before the next step, so the rules see the motion they would at 10 Hz. Before, a real
    whole-map match from a cold S2M process landed 17–33 scans late when the steps ran as fast as
    possible, and a slow CI machine left room for one start after localization. (The instant
    rejections would ask for the whole-map second opinion, which goes out at once; it is off here.)"""
    with make(
        town,
        cache_root,
        localize__clock="realtime",
        localize__s2m_process=False,
        s2m__realtime_interval_localized=6,
        localize__require_s2m_confirmation=False,
        s2m__global_check_interval=0,
    ) as loc:
        instant_matcher(loc)
        scripted_std(loc, [3.0] * 40)
        for _ in range(40):
            loc.step()
            loc.odometry.futures[loc.k - 1].result(timeout=60)
        since = loc.rules.localized_since
        assert since is not None and since <= 15, "the town drives ~1 m per scan: 10 m by scan ~10"
        starts = [e.scan for e in loc.events if e.kind == "s2m_started"]
        before = [k for k in starts if k <= since]
        after = [k for k in starts if k > since]
        assert len(before) >= since // 2, "before localization a landed match is followed by the next"
        assert len(after) >= 3
        assert all(b - a >= 6 for a, b in zip(starts, starts[1:]) if b > since)


def test_realtime_landing_does_not_wait_for_lagging_odometry(town, cache_root, monkeypatch):
    """Real time: an accepted match whose scan's odometry is not ready lands at a later scan
    (its particle still protected) instead of stalling the PF behind KISS-ICP; after
    REALTIME_LAND_MAX_DEFERRALS tries it waits a little longer each scan (never a scan period),
    and after REALTIME_LAND_FORCE_AFTER tries it waits for the odometry (a landing is never lost)."""
    import threading
    import time

    from lidarloc.core.matching import realtime_landing

    gate = threading.Event()  # KISS-ICP "stalls" on scans ≥ 3 until the gate opens
    loc = make(town, cache_root, localize__clock="realtime", localize__s2m_process=False)
    try:
        loc.wait_ready()
        real_add = loc.odometry.rpe.add

        def add(k, scan, t):  # the RPE thread registers scan k (in the KISS-ICP child)
            if k >= 3:
                gate.wait()
            real_add(k, scan, t)

        loc.odometry.rpe.add = add
        instant_matcher(loc, accepted=True)
        monkeypatch.setattr(realtime_landing, "REALTIME_LAND_WAIT_S", 60.0)  # scans 0–2: always land
        monkeypatch.setattr(realtime_landing, "REALTIME_LAND_AHEAD_SCANS", 0)  # on their own scans; the waits alone
        loc.run(3)
        job = loc.s2m.job  # started at scan 1 or 2, whichever match was last
        assert job is not None and job.started_at <= 2
        job.future.result(timeout=60)
        monkeypatch.setattr(realtime_landing, "REALTIME_LAND_WAIT_S", 0.03)
        monkeypatch.setattr(realtime_landing, "REALTIME_LAND_MAX_DEFERRALS", 2)
        monkeypatch.setattr(realtime_landing, "REALTIME_LAND_PATIENT_WAIT_S", 0.2)
        monkeypatch.setattr(realtime_landing, "REALTIME_LAND_FORCE_AFTER", 4)
        # from here on: note when a step blocks on an unfinished registration (before, scan 0's
        # rules may legitimately wait for the very first one)
        landing_waits = threading.Event()
        real_wait_registered = loc.odometry.wait_registered

        def wait_registered(k):
            if not loc.odometry.futures[k].done():
                landing_waits.set()
            return real_wait_registered(k)

        loc.odometry.wait_registered = wait_registered

        def step_in_thread():  # a landing that blocked on the gate would hang here
            worker = threading.Thread(target=loc.run, args=(1,))
            worker.start()
            return worker

        took = []
        for _ in (3, 4, 5, 6):  # the match is done but its odometry is not: no landing
            t0 = time.perf_counter()
            worker = step_in_thread()
            worker.join(timeout=60)
            took.append(time.perf_counter() - t0)
            assert not worker.is_alive(), "the step waited for the stalled odometry"
        assert loc.s2m.job is job and job.deferrals == 4 and not landing_waits.is_set()
        # scans 5 and 6 waited the patient 0.2 s for the odometry, behind a backlog too
        assert min(took[2:]) >= 0.2, took
        started = f"started {job.started_at}"
        assert not [e for e in loc.events if e.kind in ("s2m_accepted", "s2m_rejected") and started in e.detail]
        worker = step_in_thread()  # scan 7: four tries are the limit, so it waits …
        assert landing_waits.wait(timeout=60)
        gate.set()  # … until the odometry catches up, then lands
        worker.join(timeout=60)
        assert not worker.is_alive()
        landed = [e for e in loc.events if e.kind == "s2m_accepted" and started in e.detail]
        assert [e.scan for e in landed] == [7]
        assert loc.s2m.last.started_at == job.started_at and loc.s2m.last.landed_at == 7
    finally:
        gate.set()
        loc.close()


def test_realtime_landing_goes_through_the_newest_registered_scan_when_close():
    """Real time: a finished accepted match lands through its own scan's odometry when that is
    registered; else through the newest registered scan, without waiting, if that is at most
    REALTIME_LAND_AHEAD_SCANS behind and not before the match's start; else it waits (as
    before) or tries again later. A rejection needs no odometry."""
    from concurrent.futures import Future
    from types import SimpleNamespace

    from lidarloc.core.matching.realtime_landing import REALTIME_LAND_AHEAD_SCANS, landing_scan

    class Odometry:
        def __init__(self, newest):
            self.newest, self.asked = newest, []

        def registered(self, k):
            return self.newest is not None and k <= self.newest

        def newest_registered(self):
            return self.newest

        def registered_within(self, k, timeout, behind_too=False):
            self.asked.append(k)
            return self.registered(k)

    def through(k, newest, started_at=3, accepted=True):
        future = Future()
        future.set_result(SimpleNamespace(accepted=accepted))
        job = SimpleNamespace(future=future, deferrals=0, started_at=started_at)
        odometry = Odometry(newest)
        got = landing_scan(job, k, odometry, None)
        return got, odometry.asked, job.deferrals

    assert REALTIME_LAND_AHEAD_SCANS >= 1
    assert through(10, 10) == (10, [], 0)  # registered: its own scan
    assert through(10, 9) == (9, [], 0)  # one behind: through it, no wait
    assert through(10, 10 - REALTIME_LAND_AHEAD_SCANS) == (10 - REALTIME_LAND_AHEAD_SCANS, [], 0)
    assert through(10, 9 - REALTIME_LAND_AHEAD_SCANS) == (None, [10], 1)  # farther: the waits, then later
    assert through(10, 9, started_at=10) == (None, [10], 1)  # not before the match's own scan
    assert through(10, None) == (None, [10], 1)
    assert through(10, None, accepted=False) == (10, [], 0)


def test_a_finished_match_that_must_wait_to_land_reports_its_agreement_at_once():
    """Real time: a finished match whose scan's odometry is too far behind to land still says at
    once (its verdict, an ``s2m_agrees`` event) that the estimate it started from was right, once
    per match; a far pose says nothing until it lands."""
    from concurrent.futures import Future
    from types import SimpleNamespace

    from lidarloc.core.geometry import pose_matrix
    from lidarloc.core.matching.job import S2MJob
    from lidarloc.core.matching.schedule import S2MScheduler

    events = []
    sched = SimpleNamespace(cfg=Config(), verdict=None)
    sched._event = lambda k, kind, detail: events.append((k, kind, detail))
    sched._judge = lambda job, outcome: S2MScheduler._judge(sched, job, outcome)
    odometry = SimpleNamespace(newest_registered=lambda: 12)

    def job_for(x):
        future = Future()
        future.set_result(
            SimpleNamespace(
                accepted=True, pose=pose_matrix(x, 0, 0, 0, 0, 0), score=300.0, start_score=200.0, match=None
            )
        )
        return S2MJob(10, 3, 0, np.eye(4), future, estimate_pose=np.eye(4))

    near = job_for(0.5)
    S2MScheduler._agree_early(sched, 20, near, odometry)
    assert sched.verdict.kind == "agrees" and near.agreed_early
    assert events == [
        (20, "s2m_agrees", "started 10: agrees with the estimate before it lands; the odometry is at scan 12")
    ]
    sched.verdict = None
    S2MScheduler._agree_early(sched, 21, near, odometry)  # once per match
    assert sched.verdict is None and len(events) == 1
    far = job_for(30.0)
    S2MScheduler._agree_early(sched, 22, far, odometry)
    assert sched.verdict is None and not far.agreed_early and len(events) == 1


def test_realtime_landing_waits_no_longer_than_its_deadline_allows():
    """Real time: the time a finished match waits for its scan's odometry, before and after
    REALTIME_LAND_MAX_DEFERRALS tries, is cut to what is left before ``land_by`` (none once it
    has passed), so a wait never makes the next scan late; without ``land_by`` the fixed bounds
    hold. Checked on the scheduler's decision alone: which wait it asks the odometry for."""
    from concurrent.futures import Future
    from types import SimpleNamespace

    from lidarloc.core.matching import realtime_landing
    from lidarloc.core.matching.realtime_landing import landing_scan

    newest = 6 - realtime_landing.REALTIME_LAND_AHEAD_SCANS  # one scan too far behind scan 7 to land through it

    class Odometry:  # never registered in time: records the wait it was asked for
        def __init__(self):
            self.asked = []

        def registered(self, k):
            return False

        def newest_registered(self):
            return newest

        def registered_within(self, k, timeout, behind_too=False):
            self.asked.append((round(timeout, 3), behind_too))
            return False

    def asked(deferrals, land_by):
        future = Future()
        future.set_result(SimpleNamespace(accepted=True))
        job = SimpleNamespace(future=future, deferrals=deferrals, started_at=0)
        odometry = Odometry()
        through = landing_scan(job, 7, odometry, land_by)
        assert through is None and job.deferrals == deferrals + 1
        return odometry.asked[0]

    short, patient = realtime_landing.REALTIME_LAND_WAIT_S, realtime_landing.REALTIME_LAND_PATIENT_WAIT_S
    late_tries = realtime_landing.REALTIME_LAND_MAX_DEFERRALS
    now = time.perf_counter
    assert asked(0, None) == (short, False)
    assert asked(late_tries, None) == (patient, True)
    assert asked(0, now() + 10.0) == (short, False)  # time enough: the fixed bounds
    assert asked(late_tries, now() + 10.0) == (patient, True)
    assert asked(0, now() - 0.01) == (0.0, False)  # the deadline has passed: no wait at all
    assert asked(late_tries, now() - 0.01) == (0.0, True)
    left = asked(late_tries, now() + 0.02)[0]  # 20 ms left: at most those
    assert 0.0 < left <= 0.02
