"""Real time: through which scan a finished S2M match lands, and how long it may wait for its
scan's odometry (KISS-ICP registers scan k while the PF weighs it): :func:`landing_scan`, which
the scheduler asks at every scan while a match waits to land."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..odometry.feed import OdometryFeed
    from .job import S2MJob

# Real time: how long a finished S2M match waits for its scan's odometry before it tries again at
# the next scan. Typical waits are ~10 ms (KISS-ICP registers scan k while the PF weighs it).
REALTIME_LAND_WAIT_S = 0.03
# … after how many such tries it waits longer, even behind a backlog, but still less than a scan
# period: KISS-ICP takes ~50 ms a town scan on 2 cores, so 30 ms after the PF is often not enough
# and tries run out in steady state; an unbounded wait then met the drive's few slow
# registrations (0.3–0.8 s at the same scans every loop) and made scans late …
REALTIME_LAND_MAX_DEFERRALS = 20
REALTIME_LAND_PATIENT_WAIT_S = 0.05
# (Neither wait runs past the step's deadline when whoever paces the scans gives one: see
# lidarloc.core.localizer.deadline.)
# … and after how many tries in all it waits for the odometry however long it takes: under a
# sustained backlog the landing still happens and the RPE queue stays bounded (the odometry
# keeps every scan from the match's start on, so such a landing can still carry it forward).
REALTIME_LAND_FORCE_AFTER = 100
# Before any wait: a match whose scan is not registered yet lands through the newest scan that
# is, if that is at most this many scans behind: carried forward by the odometry to that scan,
# then on to its own scan at the odometry's last motion (RelativePoseEstimator.predicted, exact
# for a constant twist). KISS-ICP registers scan k while the PF weighs it, so scan k is rarely
# done when the landing looks: waiting for it cost the step up to 30–50 ms a try, and under a
# backlog matches waited tens of scans (one in five more than 20, on a quiet machine). Five
# scans: at the town drive's true motion, holding the last scan-to-scan motion for 5 scans is
# off by 0.14 m on average (95 % within 0.38 m; 0.5 / 1.4 m for 10 scans). With two, a KISS-ICP
# 4–20 scans behind for ten seconds (~100 ms a scan beside a whole-map search) kept every
# finished match waiting to land until the filter, uncorrected, had drifted 20 m.
REALTIME_LAND_AHEAD_SCANS = 5


def landing_scan(job: S2MJob, k: int, odometry: OdometryFeed, land_by: float | None = None) -> int | None:
    """Real time: the scan whose odometry carries a finished match forward to scan k (k
    itself, or the newest registered scan), or None: it tries again at the next scan, its
    particle still protected. Scan k if it is registered; else the newest registered scan
    if it is at most ``REALTIME_LAND_AHEAD_SCANS`` behind (and not before the match's start);
    else scan k if KISS-ICP registers it within ``REALTIME_LAND_WAIT_S`` (no wait at all
    while scan k−1 is still pending: the odometry is then behind). After ``REALTIME_LAND_MAX_DEFERRALS``
    tries it waits ``REALTIME_LAND_PATIENT_WAIT_S`` a scan, backlog or not (still within a
    scan period), and after ``REALTIME_LAND_FORCE_AFTER`` tries it waits for the odometry
    however long it takes. Always blocking until the odometry was done stalled the PF behind
    KISS-ICP's backlog: one town scan takes KISS-ICP 0.65 s (``lidarloc bench rpe``), and the
    landing that waited for it made 16 scans late. With ``land_by`` (the step's deadline
    less its tail) neither wait runs past it: 50 ms a scan added to a step that already took
    most of its period made a run of scans late behind one slow registration. A failed or
    rejected match needs no odometry and lands at once."""
    if job.future.exception() is not None or not job.future.result().accepted:
        return k  # a failure (the landing reports it) or a rejection: no odometry needed
    if job.deferrals >= REALTIME_LAND_FORCE_AFTER:
        return k  # the landing waits for the odometry
    if odometry.registered(k):
        return k  # registered (or failed: the landing reports it)
    newest = odometry.newest_registered()
    if newest is not None and job.started_at <= newest and k - newest <= REALTIME_LAND_AHEAD_SCANS:
        return newest
    patient = job.deferrals >= REALTIME_LAND_MAX_DEFERRALS
    wait = REALTIME_LAND_PATIENT_WAIT_S if patient else REALTIME_LAND_WAIT_S
    if land_by is not None:
        wait = max(0.0, min(wait, land_by - time.perf_counter()))
    if odometry.registered_within(k, wait, behind_too=patient):
        return k
    job.deferrals += 1
    return None
