"""The localizer's S2M scheduling: when a scan-to-map match starts, over which region, when its
result lands in the particle filter, and when it is cancelled.

One match is in flight at a time. It starts at scan k₀ from a particle's pose, runs on the S2M
thread (RS and S2M, in the S2M child process by default, see :mod:`lidarloc.core.matching.worker`),
and lands at a later scan k: an accepted match for scan k₀ is carried forward to scan k with the
RPE relative pose and written into the particle it started from, which is then re-weighted
(with ``s2m.reject_if_weight_drops``, the paper's rule, it is taken back if that lowered the
particle's log-likelihood: see :func:`~.landing.write_unless_weight_drops`).
``replay`` lands it exactly ``n_s2m`` scans after it started (the step waits for it);
``realtime`` lands it at the first scan after it finished whose odometry is ready, or nearly
(see :func:`lidarloc.core.matching.realtime_landing.landing_scan`).

Every ``s2m_started`` event ends in exactly one of ``s2m_accepted``, ``s2m_rejected`` or
``s2m_cancelled`` (:meth:`S2MScheduler.cancel`: the match can no longer land: re-initialised or
resized particles, a kidnap, S2M switched off, a clock change, a rebuilt pyramid, or the
localizer's ``close()``). In real time a finished match that agrees with the estimate but must
wait for the odometry to land says so at once with an ``s2m_agrees`` event
(:meth:`S2MScheduler._agree_early`), before its landing.

A dead S2M child (killed, out of memory) is found at the start of the next step
(:meth:`S2MScheduler.check_matcher`) or by the landing of the match it was running, whichever
comes first: the match in flight is cancelled, a new child starts (its set-up runs in the
background, and the next match waits for it), and a ``restarted`` event says so. Only the
localizer's thread restarts it, at those two points, so in the replay clock a child killed
between the same two scans gives the same run every time.

Resuming a recorded run (:mod:`lidarloc.core.runs.branch`): ``recorded(started_at, start_pose, s2m_cfg,
level)`` may return the outcome a recorded run's matcher gave for exactly that match; it then
stands in for running the matcher. The matcher is a deterministic function of the scan (fixed by
``started_at`` and the source), the start pose, the S2M settings and ``level``, so this changes no
number; anything that differs runs the matcher for real. In real time such a match lands at the
scan the recorded run landed it at, carried through the scan it was carried through (there its
timing chose both). ``last_landing`` is the raw
outcome of the last match that landed, with the job it belonged to, for the recording.

The last match that landed is kept as an :class:`~lidarloc.core.snapshot.S2MView` for the viewer's
inspection: the verdict and, for a rejection, why (the search, GICP, the odometry or the particle's
weight); whether it searched the whole map; the start pose; the best poses the branch and bound
scored and the nodes it expanded per level; the 2D match, what GICP made of it and how far it
moved it; and the pose carried forward to the landing scan.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config, S2MConfig
from ..geometry import pose_matrix, pose_to_xyz_ypr
from ..odometry.feed import OdometryFeed
from ..rules.integrity import VERDICT_TEXT, Verdict, judge
from ..snapshot import S2MView
from ..worker_process import WorkerDied
from .carry import carry_forward, carry_forward_poses
from .job import S2MJob
from .landing import landed_view, write_unless_weight_drops
from .matchers import MatcherMixin
from .realtime_landing import landing_scan
from .worker import S2MProcess


def early_agreement_detail(started_at: int, newest: int | None) -> str:
    """An ``s2m_agrees`` event's detail; :func:`early_agreement_start` reads the match's start back."""
    behind = "" if newest is None else f"; the odometry is at scan {newest}"
    return f"started {started_at}: agrees with the estimate before it lands{behind}"


def early_agreement_start(detail: str) -> int | None:
    """The start scan of the match an ``s2m_agrees`` event's detail names (None: not one)."""
    k0 = detail.split(":", 1)[0].removeprefix("started ")
    return int(k0) if k0.isdigit() else None


class S2MScheduler(MatcherMixin):
    """Starts, lands and cancels the localizer's S2M matches.

    ``cfg`` is the localizer's live configuration (read at every decision). Matches run on
    ``pool`` (one thread). ``wait(future, block, k)`` is the localizer's wait for a block: it
    gives up on ``interrupt()`` and turns a block's failure into a clear error. ``event(k, kind,
    detail)`` records an event."""

    def __init__(
        self,
        cfg: Config,
        prior_map,
        pyramid,
        map_dir: Path,
        bounds: tuple,
        pool: ThreadPoolExecutor,
        wait: Callable[..., Any],
        event: Callable[[int, str, str], None],
        start_matcher: bool = True,
    ):
        """``start_matcher`` False: the matcher starts at the first match that needs it, or at
        :meth:`start_matcher` (a resumed run replays recorded matches first: its set-up would
        only take the CPU from the replay)."""
        self.cfg = cfg
        self._prior_map = prior_map
        self._pyramid = pyramid
        self._map_dir = map_dir
        self._bounds = bounds
        self._pool = pool
        self._wait = wait
        self._event = event
        self.matcher = None
        if start_matcher:
            self.start_matcher()
        self._retired_matchers: list = []  # S2M processes replaced by a clock change
        self.job: S2MJob | None = None
        # resuming a recorded run: its matcher's outcomes (module docstring)
        self.recorded: Callable[[int, np.ndarray, Any, bool], Any] | None = None
        self.last_landing: tuple[int, S2MJob, Any] | None = None  # (scan, job, raw outcome)
        self.verdict: Verdict | None = None  # what the match that landed at the last step said
        self._restarts_seen = 0  # the matcher's restarts already reported (check_matcher)
        self.restart()

    def restart(self) -> None:
        """A fresh run: the match in flight is dropped without an event, the counts start over."""
        if self.job is not None:
            self.job.future.cancel()  # if already running it finishes, and its result is ignored
        self.job = None
        self._generation = 0
        self._last_start: int | None = None
        self.n_landed = 0
        self.n_accepted = 0
        self.last: S2MView | None = None  # the last match that landed
        self.last_landing = None
        self.verdict = None

    @property
    def acceptance(self) -> float:
        """Accepted / landed so far (0 before the first landing)."""
        return self.n_accepted / max(self.n_landed, 1)

    @property
    def protected_particle(self) -> int | None:
        """The particle slot the match in flight started from: resampling must keep it."""
        return self.job.particle if self.job is not None else None

    def follow_particle(self, index: int | None) -> None:
        """The match in flight lands on the particle at ``index`` from now on: a resampling that
        changes the particle count (KLD-sampling) may move the protected particle to another
        slot (the filter's ``protected_index``). The match itself is not affected."""
        if self.job is not None and index is not None:
            self.job.particle = int(index)

    # ------------------------------------------------------------------------ starting
    def searches_whole_map(self, localized: bool) -> bool:
        """Whether a match started now searches the whole map (not localized yet, and so configured)."""
        return not localized and self.cfg.s2m.global_until_localized

    def job_config(self, state: np.ndarray, localized: bool, check: bool = False):
        """The S2M settings for a job from a particle's ``state``: the whole map until localized
        (if so configured) and for a second-opinion ``check``, the tracking region while
        tracking, else the configured local region."""
        cfg = replace(self.cfg.s2m)
        if check or self.searches_whole_map(localized):
            x, y = state[:2]
            (x0, y0, _), (x1, y1, _) = self._bounds
            cfg.region_x = max(cfg.region_x, x - x0, x1 - x)
            cfg.region_y = max(cfg.region_y, y - y0, y1 - y)
        elif localized and self.cfg.localize.tracking:
            cfg.region_x = min(cfg.region_x, self.cfg.localize.tracking_region)
            cfg.region_y = min(cfg.region_y, self.cfg.localize.tracking_region)
        return cfg

    def held_back(self, k: int) -> bool:
        """Whether S2M is held back at scan k (``s2m.join_at_scan``)."""
        return k < self.cfg.s2m.join_at_scan

    def due(self, k: int, localized: bool, check: bool = False) -> bool:
        """Whether a match should start at scan k: S2M is on, not held back, and none is in
        flight. Back to back, except in real time once localized: then every
        ``s2m.realtime_interval_localized`` scans at most (CPU for the PF and the RPE first) —
        but a second-opinion ``check`` goes out at once."""
        if not self.cfg.s2m.enabled or self.job is not None or self.held_back(k):
            return False
        if check:
            return True
        every = self.cfg.s2m.realtime_interval_localized
        if self.cfg.localize.clock != "realtime" or not localized or every <= 0:
            return True
        return self._last_start is None or k - self._last_start >= every

    def start(
        self,
        k: int,
        j: int,
        state: np.ndarray,
        scan: np.ndarray,
        localized: bool,
        check: str | None = None,
        estimate_pose: np.ndarray | None = None,
    ) -> None:
        """Start a match of scan k from particle j (whose ``state`` it is) in the background.
        ``check``: why this match is a whole-map second opinion (None: it is not);
        ``estimate_pose``: the filter's estimate at scan k, which the match's verdict compares
        with (None: the start pose)."""
        start_pose = pose_matrix(*state[:6])
        self._generation += 1
        # Before localization the particle's z, pitch and roll are as random as its position. A
        # check's best pose may lie anywhere: its height and attitude come from the map there.
        level = not localized or check is not None
        cfg = self.job_config(state, localized, check is not None)
        mode = "check" if check is not None else ("global" if self.searches_whole_map(localized) else "local")
        self.job = S2MJob(
            k,
            j,
            self._generation,
            start_pose,
            self.submit(k, scan, start_pose, cfg, level),
            mode=mode,
            cfg=cfg,
            level=level,
            estimate_pose=start_pose if estimate_pose is None else np.asarray(estimate_pose, float),
        )
        self._last_start = k
        self._event(k, "s2m_started", f"particle {j}" + ("" if check is None else f", whole-map check ({check})"))

    def submit(self, k: int, scan, start_pose: np.ndarray, cfg, level: bool) -> Future:
        """The match of scan k from ``start_pose``: a recorded run's outcome of exactly this match if
        there is one (``recorded``), else the matcher's, in the background. ``scan``: the scan, or
        a function returning it (called only if the matcher runs)."""
        outcome = self.recorded(k, start_pose, cfg, level) if self.recorded is not None else None
        if outcome is not None:
            done: Future = Future()
            done.set_result(outcome)
            # real time: the recorded run landed it at a scan its timing chose; so does the replay
            done.landing = getattr(self.recorded, "landing_scan", lambda k0: None)(k)
            done.through = getattr(self.recorded, "landing_through", lambda k0: None)(k)
            done.agreed_at = getattr(self.recorded, "agreed_early_scan", lambda k0: None)(k)
            return done
        if callable(scan):
            scan = scan()
        self.start_matcher()
        return self._pool.submit(self._run, self.matcher, scan, start_pose, cfg, level)

    @staticmethod
    def _run(matcher, scan: np.ndarray, start_pose: np.ndarray, s2m_cfg, level: bool):
        if isinstance(matcher, S2MProcess):  # the child process: it takes the live settings along
            return matcher.match_local(scan, start_pose, s2m_cfg, level=level)
        matcher.cfg = s2m_cfg
        return matcher.match_local(scan, start_pose, level=level)

    # ------------------------------------------------------------------------ resuming
    def checkpoint(self) -> tuple[dict, dict[str, np.ndarray]]:
        """What a checkpoint keeps of the scheduling: JSON-ready counts and the match in flight,
        and the arrays of the latter (its start pose and the estimate it is judged against)."""
        job = self.job
        state = {
            "pending": False,
            "generation": self._generation,
            "last_start": self._last_start,
            "n_landed": self.n_landed,
            "n_accepted": self.n_accepted,
            "job": None
            if job is None
            else {
                "started_at": job.started_at,
                "particle": job.particle,
                "generation": job.generation,
                "deferrals": job.deferrals,
                "mode": job.mode,
                "level": bool(job.level),
                "cfg": None if job.cfg is None else dataclasses.asdict(job.cfg),
            },
        }
        arrays = (
            {}
            if job is None
            else {
                "s2m_job_start_pose": np.asarray(job.start_pose, np.float64),
                "s2m_job_estimate_pose": np.asarray(job.estimate_pose, np.float64),
            }
        )
        return state, arrays

    def restore(self, state: dict, arrays, scan_of: Callable[[int], np.ndarray]) -> None:
        """Back to a :meth:`checkpoint`; the match in flight is submitted again (a recorded
        outcome of exactly it stands in, see :attr:`recorded`). ``scan_of(k)``: scan k as S2M
        is given it."""
        self.restart()
        self._generation, self._last_start = int(state["generation"]), state["last_start"]
        self.n_landed, self.n_accepted = int(state["n_landed"]), int(state["n_accepted"])
        job = state["job"]
        if job is None:
            return
        cfg = S2MConfig(**job["cfg"]) if job["cfg"] is not None else self.cfg.s2m
        start_pose = np.array(arrays["s2m_job_start_pose"], np.float64)
        k0 = int(job["started_at"])
        future = self.submit(k0, lambda: scan_of(k0), start_pose, cfg, bool(job["level"]))
        estimate = arrays["s2m_job_estimate_pose"] if "s2m_job_estimate_pose" in arrays else start_pose
        self.job = S2MJob(
            k0,
            int(job["particle"]),
            int(job["generation"]),
            start_pose,
            future,
            deferrals=int(job["deferrals"]),
            mode=str(job["mode"]),
            cfg=cfg,
            level=bool(job["level"]),
            estimate_pose=np.array(estimate, np.float64),
        )

    # ------------------------------------------------------------------------ cancelling
    def cancel(self, k: int, why: str) -> None:
        """Drop the match in flight (running, or finished and waiting to land); an
        ``s2m_cancelled`` event at scan k says why."""
        job, self.job = self.job, None
        if job is not None:
            job.future.cancel()  # if already running it finishes, and its result is ignored
            self._event(k, "s2m_cancelled", f"started {job.started_at} ({why})")

    # ------------------------------------------------------------------------ landing
    def land(
        self,
        k: int,
        prepared: np.ndarray,
        pf,
        odometry: OdometryFeed,
        fits_better: Callable[[np.ndarray, np.ndarray], tuple[bool, str]] | None = None,
        land_by: float | None = None,
    ) -> float | None:
        """Land the match in flight at scan k if it is due: an accepted one is carried forward
        to k with the ``odometry`` and written into its particle of ``pf``, which is then
        re-weighted with the ``prepared`` scan. Returns the match's time in ms if one landed;
        :attr:`verdict` says what it said about the estimate. ``fits_better(pose, prepared)``:
        whether the scan fits the map clearly better in 3D at a far whole-map check's pose than at
        the estimate, and why (a "relocalize" verdict needs it; None: the BEV score decides).
        ``land_by``: real time, the ``time.perf_counter()`` after which waiting for the odometry
        would make the next scan late (see :mod:`lidarloc.core.localizer.deadline`)."""
        self.verdict = None
        job = self.job
        if job is None:
            return None
        planned = getattr(job.future, "landing", None)
        through = k  # the scan whose odometry carries an accepted match to scan k
        if self.cfg.localize.clock == "replay":
            if k < job.started_at + self.cfg.s2m.n_s2m:
                return None
        elif planned is not None:
            if k < planned:
                if k == getattr(job.future, "agreed_at", None):  # where the recorded run heard it
                    self._agree_early(k, job, odometry)
                return None
            recorded_through = getattr(job.future, "through", None)  # as the recorded run carried it
            through = k if recorded_through is None else int(recorded_through)
        elif not job.future.done():
            return None  # real time: land at a scan after the match finished
        else:
            through = landing_scan(job, k, odometry, land_by)
            if through is None:  # its odometry is behind: try again at the next scan (see there) …
                self._agree_early(k, job, odometry)  # … but an agreement needs no odometry
                return None
        self.job = None
        what = f"the S2M match started at scan {job.started_at}"
        try:
            outcome = self._wait(job.future, "S2M", k, what, recover=(WorkerDied,))
        except WorkerDied as exc:  # its child died after this step's check_matcher
            self.job = job
            self._matcher_died(k, exc.worker)
            return None
        self.last_landing = (k, job, outcome)
        self.n_landed += 1
        accepted = bool(outcome.accepted)
        pose_k = outcome.pose
        reason = outcome.reason
        verdict = self._judge(job, outcome)
        if accepted:
            # Carry the match for scan k₀ forward to scan k with the RPE relative pose (through
            # the newest registered scan, and on at its last motion, if scan k's is not done).
            odometry.wait_registered(through)
            if job.started_at < odometry.origin:
                accepted, reason = False, "odometry restarted since the match started"
            else:
                try:
                    if through == k:
                        pose_k = carry_forward(outcome.pose, odometry.rpe, job.started_at, k)
                    else:
                        odom_k = odometry.rpe.predicted(through, odometry.timestamp(k))
                        pose_k = carry_forward_poses(outcome.pose, odometry.rpe.odom_pose(job.started_at), odom_k)
                except KeyError:  # the odometry no longer holds scan k₀ (restarted meanwhile)
                    accepted, reason = False, f"odometry no longer holds scan {job.started_at}"
            if not accepted and verdict.kind == "relocalize":  # nowhere to move the filter to
                verdict = dataclasses.replace(verdict, kind="look_alike")
            elif accepted:
                verdict = dataclasses.replace(verdict, pose=pose_k)
        fit_words = ""
        if verdict.kind == "relocalize" and fits_better is not None:
            better, fit_words = fits_better(pose_k, prepared)
            if not better:
                verdict = dataclasses.replace(verdict, kind="look_alike")
        self.verdict = verdict
        if job.mode == "check" and accepted and verdict.kind != "agrees":
            # a second opinion far from the estimate is never written into a particle: either the
            # filter re-localizes there (the localizer's call) or it is a look-alike
            accepted = False
            reason = (
                "whole-map check: a clearly better pose far from the estimate, " + verdict.describe()
                if verdict.kind == "relocalize"
                else "whole-map check: a pose far from the estimate, not clearly better (BEV score "
                f"≥ {self.cfg.s2m.relocalize_score_ratio:g}× and a clearly better 3D fit needed): " + verdict.describe()
            )
            if fit_words:
                reason += f"; {fit_words}"
        if accepted:
            state = pf.states[job.particle].copy()
            state[:6] = pose_to_xyz_ypr(pose_k)
            state[6] = odometry.rpe.speed(through)
            state[7:10] = odometry.rpe.rates(through)
            if self.cfg.s2m.reject_if_weight_drops:
                accepted, reason = write_unless_weight_drops(pf, job.particle, state, prepared)
            else:
                pf.set_particle(job.particle, state)
                pf.reweight(job.particle, prepared)
        if accepted:
            self.n_accepted += 1
        elif not reason:
            reason = "the matcher gave no reason"
        self._event(
            k,
            "s2m_accepted" if accepted else "s2m_rejected",
            f"started {job.started_at}, score {outcome.score:.0f} vs {outcome.start_score:.0f}"
            + (f" ({reason})" if reason and not accepted else "")
            + ("" if job.mode == "local" else f"; {job.mode} search: {VERDICT_TEXT[verdict.kind]}")
            + (f"; odometry to scan {through}, then {k - through} scan(s) at its last motion" if through != k else ""),
        )
        self.last = landed_view(job, k, outcome, accepted, pose_k, reason, through)
        return float(outcome.ms)

    def _judge(self, job: S2MJob, outcome) -> Verdict:
        """The match's word on the estimate, judged at scan k₀ against the estimate the filter had
        then: independent of the match (after the landing the particle it is written into would
        agree with itself), and no odometry is needed to judge it."""
        accepted = bool(outcome.accepted)
        # A search that nothing in its region beat: the start itself is the best place the
        # matcher sees there (its word on the estimate, see core/rules/integrity.py).
        match = getattr(outcome, "match", None)
        unbeaten = (
            not accepted
            and match is not None
            and not np.isfinite(getattr(match, "x", 0.0))
            and np.isfinite(outcome.start_score)
        )
        return judge(
            job.mode,
            accepted,
            unbeaten,
            outcome.pose,
            job.estimate_pose,
            float(outcome.score),
            float(outcome.start_score),
            self.cfg,
        )

    def _agree_early(self, k: int, job: S2MJob, odometry: OdometryFeed) -> None:
        """Real time: a finished match waiting for the odometry to land may already say that the
        estimate it started from was right (its verdict needs no odometry). An agreement is reported
        at once as this step's :attr:`verdict` and an ``s2m_agrees`` event, once per match; any other
        verdict waits for the landing (a far pose is of use only carried to the current scan). Under
        a KISS-ICP behind the clock, matches that agreed but could not land for 50 scans made the
        estimate's confirmation go stale (core/rules/integrity.py) while the filter was right."""
        if job.agreed_early or job.future.exception() is not None:
            return
        verdict = self._judge(job, job.future.result())
        if verdict.kind != "agrees":
            return
        job.agreed_early = True
        self.verdict = replace(verdict, judged_at=job.started_at)
        self._event(k, "s2m_agrees", early_agreement_detail(job.started_at, odometry.newest_registered()))
