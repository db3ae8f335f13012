"""The localizer: the paper's blocks (PF, RPE, RS, S2M+SU) wired together, in threads.

Data flow for scan k (paper, Fig. "block diagram"):

- RPE (KISS-ICP relative poses, in a child process because it holds the GIL) gets scan k as soon
  as it is read; the PF runs on the caller's thread meanwhile.
- PF: predict (11-state model), weight (lookup-table likelihood), estimate.
- SU: when an S2M job started at scan k₀ is due, its match (for scan k₀) is carried forward to
  scan k with the RPE relative pose, written into the particle it started from, and that
  particle is re-weighted. A failed or rejected match changes nothing.
- PF resamples when N_eff < 50 %, protecting the S2M particle while a job is in flight.
- S2M: if no job is in flight, the highest-weight particle's pose at k and scan k start a new
  match: over the whole map until the localization rule is met (``s2m.global_until_localized``),
  then in the paper's ±(L_x, L_y) region (±``tracking_region`` in tracking mode). RS (road removal) and S2M (M3RSM + GICP) run one after the other in a child process
  (:mod:`lidarloc.core.matching.worker`; small_gicp and the normal estimation hold the GIL, which
  stalled the PF by ~4× on threads), driven from the S2M thread. Only the scans S2M matches are
  road-segmented: nothing else uses them. ``localize.s2m_process = False`` runs both on the S2M
  thread instead (same results, for debugging).

Two clocks (``localize.clock``): ``replay`` lands every S2M result exactly ``n_s2m`` scans after
it started (the step blocks until it is ready), so a seed fixes the whole trajectory; ``realtime``
lands it once its odometry is ready (:mod:`lidarloc.core.matching.schedule`) and the rules read
the newest finished odometry instead of waiting for scan k's, so KISS-ICP and the PF overlap.

Choice where the paper is vague: the paper suspends resampling between k and k'. We resample as
usual but protect the S2M particle (the PF's ``protect`` argument), which keeps the particle
intact without starving the filter of resampling while S2M runs back to back. With KLD-sampling
(``pf.kld``) a resampling may change the particle count and move the protected particle to
another slot: the match in flight follows it (``pf.protected_index``) instead of being cancelled.

This module is the scan loop: construction, restart, one step. Its parts: the blocks' feeds
(:class:`~lidarloc.core.odometry.feed.OdometryFeed`, :class:`~lidarloc.core.matching.schedule.S2MScheduler`)
and the modules beside this one, each saying what it holds (de-skewing: :mod:`.blocks`; kidnap:
:mod:`.controls`; the scan's fit: :mod:`.outputs`; resuming: :mod:`.state`; stopping: :mod:`.processes`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import LidarlocError
from ..filter.scanprep import prepare_scan
from ..maps.world import World, open_world
from ..matching.pending import S2MNotReady, in_daemon_thread
from ..odometry.deskew import sweep_period
from ..odometry.feed import OdometryFeed
from ..odometry.rpe import load_or_build_odometry
from ..rules.checks import ConfidenceWatch, ScanFrameCheck, initial_pose_on_map
from ..rules.integrity import Integrity
from ..rules.paper import LocalizationRules
from ..snapshot import Event, ScanRecord, Snapshot
from . import processes
from .blocks import BlocksMixin, Interrupted
from .controls import ControlsMixin
from .deadline import LANDING_MARGIN_S, RecentPeak
from .outputs import OutputsMixin
from .state import StateMixin
from .tables import TablesMixin


class Localizer(BlocksMixin, ControlsMixin, OutputsMixin, StateMixin, TablesMixin):
    def __init__(
        self,
        seq,
        cfg: Config,
        cache_root: Path | None = None,
        progress: Callable[[str, float], None] | None = None,
        on_map: Callable[[object], None] | None = None,
        defer_s2m: bool = False,
        known_odometry: dict | None = None,
        lazy_s2m: bool = False,
        world: World | None = None,
    ):
        from ..filter.pf import ParticleFilter

        self.seq, self.cfg = seq, cfg
        self.n_scans = len(seq)
        self._progress = progress or (lambda stage, frac: None)
        early_rpe = processes.start_rpe_early(cfg, defer_s2m)  # closed by __del__ if the construction fails
        # The prior map comes from the sequence's mapping drive (core/maps/world.py).
        # ``defer_s2m``: what only S2M needs (road removal, BEV pyramid, its process) is built in
        # the background after construction, and S2M joins at the first scan after it is ready —
        # a scan that depends on timing, so only for a viewer's first start on an empty cache.
        # ``world``: the map opened beforehand with ``open_world(seq.map_source, cfg)`` and
        # ``cfg``'s settings; the localizer owns it from then on (a tiled map's window follows
        # its particles).
        if world is None:
            world = open_world(
                seq.map_source,
                cfg,
                cache_root,
                road_removal=not defer_s2m,
                progress=self._progress,
                on_map=lambda prior: self._map_ready(prior, on_map),
            )
        else:
            self._map_ready(world.prior_map, on_map)
        self.world = world
        self.prior_map, self.map_dir = self.world.prior_map, self.world.map_dir
        self.lookup, self.pyramid = self.world.lookup, self.world.pyramid
        recorded_odometry = None
        if cfg.localize.recorded_odometry:
            self._progress("odometry", 0.0)
            recorded_odometry = load_or_build_odometry(
                seq, self.odometry_cache_dir, progress=lambda f: self._progress("odometry", f)
            ).value
        self._PF = ParticleFilter
        self._sweep_period = sweep_period(seq.timestamps, cfg.pf.dt)
        bmin, bmax = self.prior_map.bounds
        self._bounds = (np.asarray(bmin, float), np.asarray(bmax, float))
        self._lock = threading.RLock()
        self._rpe_pool, self._s2m_pool, self._rebuild_pool = processes.block_threads()
        self.rebuild_progress: float | None = None
        self._pending_lookup: Future | None = None
        self._pending_pyramid: Future | None = None
        self._closed = False
        self._interrupt = threading.Event()  # set by interrupt(): a waiting step gives up
        self._waiting: tuple[str, float] | None = None  # what a step waits for, since when
        self._failed: str | None = None  # a block's failure: steps refuse until restart()
        self.odometry = OdometryFeed(cfg, recorded_odometry, self._rpe_pool, wait=self._wait)
        self.odometry.process = early_rpe
        self.odometry.known = known_odometry
        self.odometry.scan_source = self._odometry_scan
        # controls that change the state between or inside steps (a recording checkpoints after
        # each: see core/runs/resume.py); events before this index belong to an earlier recording
        self.controls = 0
        self.recorded_events_base = 0
        self._controls_checkpointed: int | None = None  # controls count at the last checkpoint
        self.branch_of: dict | None = None  # {"run", "step"} of a branch (core/runs/branch.py)
        self._lazy_s2m = lazy_s2m  # the S2M matcher starts when first needed
        self._pending_s2m: Future | None = None
        self._road_removal = None  # its child process while it runs (defer_s2m)
        if self.pyramid is not None:
            self.s2m = self._s2m_scheduler()
        else:
            self.s2m = S2MNotReady()
            # road removal runs in a niced child process: the first scans play at full speed
            self._pending_s2m = in_daemon_thread(self._build_s2m_tables, "lidarloc-road-removal")
        self._progress("ready", 1.0)
        self.restart(cfg.seed)

    def _map_ready(self, prior_map, on_map) -> None:
        """The map is there, its tables not yet: a map file's sequence learns the map's origin
        (its truth goes to the map's local frame), ``--init`` is checked against the map (a bad
        one fails before the tables are built), and a viewer shows the map meanwhile."""
        use_origin = getattr(self.seq, "use_map_origin", None)
        if use_origin is not None:
            use_origin(prior_map.origin)
        self._init_pose = initial_pose_on_map(
            getattr(self.seq, "initial_guess", None), prior_map, self.cfg.pf.sensor_height
        )
        if on_map is not None:
            on_map(prior_map)

    # ------------------------------------------------------------------------ lifecycle
    def restart(self, seed: int | None = None) -> None:
        """Back to scan 0 with a fresh filter (same map, lookup table and pyramid)."""
        with self._lock:
            if seed is not None:
                self.cfg.seed = int(seed)
            self.s2m.restart()
            self._interrupt.clear()
            self.controls += 1
            self.recorded_events_base = 0
            # a branch replayed a recorded run's real-time choices; a run from scan 0 makes its own
            self.odometry.used_plan = None
            if getattr(self.s2m, "recorded", None) is not None:
                self.s2m.recorded.timing_until = -1
            self.pf = self._PF(
                self.cfg.pf,
                self.lookup,
                self._bounds[0],
                self._bounds[1],
                seed=self.cfg.seed,
                map_points=self.prior_map.points,
            )
            if self._init_pose is None:
                self.pf.initialize()
            else:
                self.pf.initialize(pose=self._init_pose[0], pose_std=self._init_pose[1])
            self.odometry.restart(origin=0)
            self.rules = LocalizationRules(self.cfg.localize)
            self.integrity = Integrity(self.cfg)
            self._alarm_on = False  # the truth alarm is raised (see _truth_check)
            self._failed = None
            self.k = 0  # index of the next scan to process
            self.steps = 0  # scans processed since the start (kidnap skips don't count)
            self.events: list[Event] = []
            self.records: list[ScanRecord] = []
            self.est_trajectory: list[np.ndarray] = []
            self._prev_t: float | None = None
            self._tail_after_landing = RecentPeak()  # real time: what a step does after its landing (s)
            self._confidence = ConfidenceWatch()
            self._frame_check = ScanFrameCheck()
            if self._init_pose is not None:
                g = self.seq.initial_guess
                self._event(
                    -1,
                    "initial_guess",
                    f"particles around x {g.x:.2f} m, y {g.y:.2f} m, yaw "
                    f"{np.degrees(g.yaw):.1f}° (σ {g.sigma_xy:g} m, {np.degrees(g.sigma_yaw):g}°)",
                )
            self._check_truth_frame()
            self._snapshot: Snapshot | None = None
            self._snapshot = self._make_snapshot(-1, None, 0.0, None)

    def interrupt(self) -> None:
        """Stop stepping without waiting for the blocks (Ctrl-C, closing the viewer).

        A step waiting for the odometry or for a match due now gives up within
        ``INTERRUPT_POLL_S`` and raises :class:`Interrupted`; its scan is not recorded, nor are
        its events. From then on ``step()`` raises :class:`Interrupted` until ``restart()`` (the
        PF may already have weighted the dropped scan). Everything recorded before stays.
        Without this, Ctrl-C in the first scans waited for the first whole-map match behind the
        S2M process's set-up: 2.4 s (``lidarloc bench stop``). Safe from any thread (a signal
        handler too); it does not take the step's lock."""
        self._interrupt.set()

    def close(self) -> None:
        self._interrupt.set()  # a step in progress gives up instead of holding the lock
        self._closed = True
        if self._road_removal is not None:
            self._road_removal.kill()
        with self._lock:
            self.s2m.cancel(self.k - 1, "localizer closed")
        processes.close_threads_and_children(
            (self._rpe_pool, self._s2m_pool, self._rebuild_pool), self.odometry, self.s2m
        )

    def kill_processes(self) -> None:
        """Kill every child process at once, without waiting for them or for the threads: for a
        process about to exit whose :meth:`close` did not finish in time (a busy machine), so
        that no child outlives it. Safe from any thread, also while :meth:`close` runs."""
        self._interrupt.set()
        self._closed = True
        if self._road_removal is not None:
            self._road_removal.kill(wait=False)
        self.odometry.kill_process()
        self.s2m.kill_processes()

    def wait_ready(self) -> None:
        """Block until every block is ready to work at full speed: the child processes (S2M's map,
        pyramid, GICP target and warm-up match; KISS-ICP) have finished their set-up, and the PF's
        kernels (scan down-sampling, likelihood) are loaded in this process.

        The real-time clock calls this before its first scan is due: a sensor's scans start
        arriving once the system is up, and set-up still running would take the CPU from the first
        scans (measured on the real drive in real time: without this the first whole-map match,
        started at scan 0, landed at scan 11–12; with it, at scan 3)."""
        processes.load_kernels(self.prior_map.points, self.cfg.pf, self.pf.states, self.lookup, self.effective_d_max)
        processes.wait_for_children(
            (self.s2m.matcher, self.odometry.process), lambda why: self._event(self.k, "restarted", why)
        )

    def cpu_seconds(self) -> dict:
        """CPU time used so far by the blocks' processes, in seconds: ``main`` (this process: the
        PF, and the threads that feed the child processes), ``rpe`` (the KISS-ICP child) and
        ``s2m`` (the RS + S2M child). None where a block runs inside this process (then its time
        is in ``main``) or the platform cannot tell. Differences of two readings give what a run
        cost per block (``lidarloc run`` puts them in summary.json)."""
        return processes.cpu_seconds(self.odometry.process, self.s2m.matcher)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def done(self) -> bool:
        return self.k >= self.n_scans

    @property
    def closed(self) -> bool:
        """Whether ``close()`` was called: the localizer steps no more."""
        return self._closed

    # ------------------------------------------------------------------------ derived
    @property
    def odometry_cache_dir(self) -> Path:
        """Where the localized drive's recorded odometry is cached: a sibling of the map's
        directory named after the drive (several drives share one map; a map rebuild, which
        replaces its own directory, leaves it alone)."""
        return self.map_dir.with_name(f"{self.map_dir.name}-drive-{self.seq.cache_key()}")

    @property
    def effective_d_max(self) -> float:
        """The likelihood's distance cap: the configured d_max, clamped to the one the lookup
        table was built for (a larger one is being rebuilt in the background meanwhile)."""
        return self.lookup.capped(self.cfg.pf.d_max)

    # ------------------------------------------------------------------------ one scan
    def step(self, deadline: float | None = None) -> Snapshot:
        """Process the next scan and return the new snapshot. ``deadline``: real time, the
        ``time.perf_counter()`` by which the step should be over for the next scan to start on
        time (see :mod:`.deadline`); it bounds the step's waits, never its work."""
        with self._lock:
            if self._closed:
                raise LidarlocError("localizer is closed")
            if self._failed is not None:
                raise LidarlocError(f"{self._failed} (restart to continue)")
            if self._interrupt.is_set():
                raise Interrupted("interrupted (restart to continue)")
            if self.done:
                return self._snapshot
            events_before, job_before = len(self.events), self.s2m.job
            try:
                return self._process_next_scan(deadline)
            except Interrupted:
                # The scan is not recorded, so neither are its events; a match that landed in
                # it counts as still in flight (close() or restart() reports it cancelled).
                del self.events[events_before:]
                self.s2m.job = job_before
                raise
            except Exception as exc:
                error = self._step_failed(exc)
                if error is exc:
                    raise
                raise error from exc

    def _process_next_scan(self, deadline: float | None = None) -> Snapshot:
        """The body of step(), with the lock held."""
        self._swap_rebuilt_tables()
        k = self.k
        if hasattr(self.s2m, "check_matcher"):  # a dead S2M child: cancel its match, start another
            self.s2m.check_matcher(k)
        scan = self.seq.scan(k)
        t = self.seq.timestamp(k)
        dt = self.cfg.pf.dt if self._prev_t is None else max(t - self._prev_t, 1e-3)
        self._prev_t = t
        if self.cfg.localize.deskew:
            scan = self._deskew(k, scan)
        # RPE starts now and overlaps with the PF work below; the odometry keeps every scan from
        # the match in flight's start on, however long ago: its landing carries it from there.
        job = getattr(self.s2m, "job", None)
        self.odometry.keep_from(None if job is None else job.started_at)
        self.odometry.submit(k, scan, t)

        # PF time excludes waiting for S2M (in replay the step blocks until the match is due).
        t0 = time.perf_counter()
        rng = np.random.default_rng([self.cfg.seed, k, 1])
        prepared = prepare_scan(scan, self.cfg.pf, rng)
        self.pf.predict(dt)
        if self.world.tiles is not None:  # a tiled map: the tiles under the particles and their scan
            reach = float(np.linalg.norm(prepared[:, :3], axis=1).max()) if len(prepared) else 0.0
            table = self.world.tiles.follow(self.pf.states, reach)
            if table is not self.lookup:
                # the world's too: the first window (the whole map, for a spread start) goes
                self.lookup = self.world.lookup = table
                self.pf.set_lookup(table)
        self.pf.update(prepared)
        pf_s = time.perf_counter() - t0
        land_by = None if deadline is None else deadline - self._tail_after_landing.value - LANDING_MARGIN_S
        s2m_ms = self.s2m.land(k, prepared, self.pf, self.odometry, self._fits_better_there, land_by)
        landed_at = time.perf_counter()
        verdict = self.s2m.verdict
        relocalized = verdict is not None and verdict.kind == "relocalize"
        withdrawn = None if verdict is None else self.integrity.note_verdict(k, verdict)
        if relocalized:
            self._relocalize(k, verdict)
        elif withdrawn is not None and self.rules.localized:
            self._withdraw(k, withdrawn)
        t1 = time.perf_counter()
        # Estimate from the weighted posterior, before resampling adds Monte Carlo noise.
        est = self.pf.estimate()
        n_weighed = self.pf.n
        pf_s += time.perf_counter() - t1
        self._check_scan_frame(k, est, prepared)  # before resampling: best_index names a particle

        if self.s2m_status(k)[0] == "ready" and k == self.cfg.s2m.join_at_scan > 0:
            self._event(k, "s2m_ready", f"held back until scan {k} (s2m.join_at_scan)")
        step_dist, yaw_odom = self.odometry.motion(k)
        for j, words in self.odometry.take_notices():  # KISS-ICP's child restarted (feed.py)
            self._event(j, "restarted", f"RPE: {words}")
        confirmed = (lambda k0: self.integrity.confirms_first_fix(k0, k)) if self.integrity.required else None
        outcome = self.rules.update(k, est.std_xyz, step_dist, yaw_odom, confirmed)
        reinit = relocalized
        if outcome.event is not None:
            detail = f"max std {float(np.max(est.std_xyz)):.1f} m"
            if outcome.event == "localized" and self.integrity.required:
                detail += f", confirmed by the S2M match that agreed at scan {self.integrity.confirmed_at}"
            self._event(k, outcome.event, detail)
        if outcome.event == "localized":
            self.integrity.on_localized(k)
        # how well the scan fits the map at the estimate: a poor fit asks for the second opinion
        # at the match starting below, and a long one is a loss
        fit = self._scan_fit(k, est, prepared)
        lost = None if outcome.reinit else self.integrity.note_fit(k, self.rules.localized, *fit)
        if lost is not None:
            self._event(k, "loss", lost)
            self.rules.reset()
        elif not outcome.reinit and self.rules.localized:
            undecided = self.integrity.undecided_doubt(k) or self.integrity.stale_word(k)
            if undecided is not None and self._withdraw(k, undecided):
                est = self.pf.estimate()  # tracking mode ended: the full filter's particles
                n_weighed = self.pf.n
        if outcome.reinit or lost is not None:
            self.integrity.reset()
            why = "a loss" if lost is not None else f"a {outcome.event.replace('_', ' ')}"
            self._reinitialize(k=k, why=f"re-initialised after {why}")
            reinit = True
            est = self.pf.estimate()
            n_weighed = self.pf.n
        else:
            entering_tracking = outcome.event == "localized" and self.cfg.localize.tracking
            if entering_tracking:  # resamples down: est.best_index no longer names a particle
                self._enter_tracking(k)
            # S2M starts from the highest-weight particle of this posterior; that slot is
            # then protected through every resampling until the match lands.
            check = self.integrity.check_due(k, self.rules.localized)
            if not entering_tracking and self.s2m.due(k, self.rules.localized, check is not None):
                j = est.best_index
                self.s2m.start(k, j, self.pf.states[j], scan, self.rules.localized, check, est.pose)
                if check is not None:
                    self.integrity.check_started(k)
            t2 = time.perf_counter()
            self.pf.resample_if_needed(protect=self.s2m.protected_particle)
            # KLD-sampling may shrink the count below the protected slot: the filter moves that
            # particle, and the match lands where it went
            self.s2m.follow_particle(self.pf.protected_index)
            pf_s += time.perf_counter() - t2
        pf_ms = pf_s * 1000.0
        self._truth_check(k, est)

        self.k += 1
        self.steps += 1
        snap = self._make_snapshot(k, prepared, pf_ms, est, n_weighed, fit)
        self.est_trajectory.append(est.pose)
        self.records.append(ScanRecord.from_snapshot(snap, s2m_ms, reinit))
        self._snapshot = snap
        self._tail_after_landing.add(time.perf_counter() - landed_at)
        return snap

    def _withdraw(self, k: int, why: str) -> bool:
        """Green means both blocks agree: not any more (see core/rules/integrity.py). The
        particles stay; S2M searches the whole map again and the rule must fire again with its
        word. Returns whether the particle count changed (tracking mode ended)."""
        self._event(k, "unconfirmed", f"no longer localized: {why}")
        self.rules.reset()
        if self.pf.n == self.cfg.pf.n_particles:
            return False
        self.s2m.cancel(k, "no longer localized: particle indices change")  # tracking mode ends
        self.pf.set_n_particles(self.cfg.pf.n_particles)
        return True

    def run(self, n: int | None = None, should_stop: Callable[[], bool] | None = None) -> Snapshot:
        """Process up to ``n`` scans (all remaining if None)."""
        remaining = self.n_scans - self.k if n is None else n
        for _ in range(remaining):
            if self.done or (should_stop is not None and should_stop()):
                break
            self.step()
        return self._snapshot
