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
  (:mod:`lidarloc.core.s2m_worker`; small_gicp and the normal estimation hold the GIL, which
  stalled the PF by ~4× on threads), driven from the S2M thread. Only the scans S2M matches are
  road-segmented: nothing else uses them. ``localize.s2m_process = False`` runs both on the S2M
  thread instead (same results, for debugging).

Two clocks: ``replay`` lands every S2M result exactly ``n_s2m`` scans after it started (the
step blocks until it is ready), so a seed fixes the whole trajectory; ``realtime`` lands a
result at the first scan after it finished whose odometry is ready (an accepted match is carried
forward with it; see :mod:`lidarloc.core.s2m_schedule`), and the rules read the newest finished
odometry instead of waiting for scan k's, so KISS-ICP and the PF overlap across scans.

The blocks around the scan loop: :class:`~lidarloc.core.odometry.OdometryFeed` feeds the RPE,
:class:`~lidarloc.core.s2m_schedule.S2MScheduler` starts, lands and cancels the S2M matches.

The prior map is built from the sequence's ``map_source`` (the whole mapping drive: ``--scans N``
plays N scans inside it, and the generated town's drive with changes, traffic or another sensor
is localized in the town as it was mapped), never from the scans being localized alone. A map
file (``--map``) is the map source of a :class:`~lidarloc.core.sequences.framed.MapFramed`
sequence, which learns the map's origin from the localizer to put its truth in the map's frame.

Start, frames and confidence: :mod:`lidarloc.core.checks` (``--init``'s start around a guess,
``frame_mismatch`` when map, truth and scans look to be in different frames, ``confidence_low``).

Confidence: after each scan the localizer measures how well the scan fits the map at the
estimate (the share of prepared scan points within d_max of the map and their mean distance,
:func:`~lidarloc.core.likelihood.residual_stats`, one pose: well under a millisecond) and, with
the particles' spread and N_eff, reports it in the snapshot and the per-scan record (see
:mod:`lidarloc.core.snapshot`). A ``confidence_low`` event marks the scan at which, while
localized, the inlier share drops below ``localize.min_inlier_share``; it fires once and is
re-armed when the share recovers or localization ends.

De-skew (``localize.deskew``): a spinning LiDAR measures its points over a whole sweep while the
car moves. Each scan is moved into its mid-sweep frame (:mod:`lidarloc.core.deskew`) before the
PF, the RPE and S2M see it, assuming the motion of the newest known odometry step (constant
velocity over one sweep; the scan's own odometry is not known yet when it arrives). The first two
scans after a (re)start of the odometry have no such step and are used as they come. Recorded
odometry (``localize.recorded_odometry``) is KISS-ICP's over the scans as they come, so with
de-skewing it differs slightly from the live odometry, which registers the de-skewed scans.

Choice where the paper is vague: the paper suspends resampling between k and k'. We resample as
usual but protect the S2M particle (the PF's ``protect`` argument), which keeps the particle
intact without starving the filter of resampling while S2M runs back to back. With KLD-sampling
(``pf.kld``) a resampling may change the particle count and move the protected particle to
another slot: the match in flight follows it (``pf.protected_index``) instead of being cancelled.

Kidnap (viewer feature): the data index jumps ahead without telling the filter. The RPE's
KISS-ICP cannot register across a jump, so it is restarted at the new scan (a real system would
detect the failed registration the same way); the filter itself learns nothing.

Resuming (:mod:`lidarloc.core.resume`, :mod:`lidarloc.core.branch`): after each step a recording
asks :meth:`Localizer.resume_payload` for what resuming from that step needs (checkpoints of the
exact state, the odometry, the raw S2M outcomes); ``known_odometry`` makes the odometry use a
recorded run's poses instead of registering those scans again, and ``lazy_s2m`` starts the S2M
matcher only when a match needs it (a resumed run replays recorded matches first).

Every ``s2m_started`` event ends in exactly one of ``s2m_accepted``, ``s2m_rejected`` or
``s2m_cancelled`` (the match could no longer land: re-initialised or resized particles, a kidnap,
S2M switched off, a clock change, a rebuilt pyramid, or ``close()``). Stopping: ``interrupt()``
(Ctrl-C, closing the viewer) makes a step that waits for a block give up without recording its
scan, and ``close()`` kills child processes that are busy or still setting up.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from .checks import ConfidenceWatch, ScanFrameCheck, initial_pose_on_map, truth_outside_map
from .integrity import Integrity, fits_clearly_better, truth_alarm
from .config import LIVE_PARAMS, Config, check_live_changes
from .errors import LidarlocError
from .geometry import transform_points
from .mapping import load_or_build_map
from .metrics import inside_2sigma
from .odometry import OdometryFeed
from .rpe import load_or_build_odometry
from .rules import LocalizationRules
from .s2m_pending import S2MNotReady, in_daemon_thread
from .s2m_schedule import S2MScheduler
from .scanprep import prepare_scan, voxel_downsample_random
from .snapshot import Event, ScanRecord, Snapshot
from .worker_process import WorkerProxy


class BlockError(LidarlocError):
    """A localizer block (thread) raised; the run stops with this one-line message."""


class Interrupted(LidarlocError):
    """``interrupt()`` stopped a step that was waiting for a block; that scan is not recorded."""


#: The ``s2m_ready`` event's detail: S2M joins once its tables are built (``defer_s2m``).
S2M_READY_DETAIL = "road-removed map and BEV pyramid built in the background"

#: How often a step waiting for a block checks for ``interrupt()`` (seconds).
INTERRUPT_POLL_S = 0.05


class Localizer:
    def __init__(self, seq, cfg: Config, cache_root: Path | None = None,
                 progress: Callable[[str, float], None] | None = None,
                 on_map: Callable[[object], None] | None = None, defer_s2m: bool = False,
                 known_odometry: dict | None = None, lazy_s2m: bool = False):
        from .bev import load_or_build_pyramid
        from .lookup import load_or_build_lookup
        from .pf import ParticleFilter

        self.seq, self.cfg = seq, cfg
        self.n_scans = len(seq)
        self._progress = progress or (lambda stage, frac: None)
        # A viewer's start: KISS-ICP's child process sets up (~3 s of imports) while the map and
        # tables are built, instead of in front of the first scan. Closed by __del__ if the
        # construction fails.
        early_rpe = None
        if defer_s2m and cfg.localize.rpe_process and not cfg.localize.recorded_odometry:
            from .rpe_worker import KissICPProcess

            early_rpe = KissICPProcess()
        # The prior map comes from the sequence's mapping drive, not from the scans being
        # localized (``--scans N`` plays N scans inside the whole drive's map; the town's drive
        # with changes, traffic or another sensor inside the town as it was mapped).
        # ``defer_s2m``: what only S2M needs (road removal, BEV pyramid, its process) is built in
        # the background after construction, and S2M joins at the first scan after it is ready —
        # a scan that depends on timing, so only for a viewer's first start on an empty cache
        self.prior_map, self.map_dir, _ = load_or_build_map(
            seq.map_source, cfg.map, cache_root, progress=lambda i, n: self._progress("map", i / n),
            road_removal=not defer_s2m)
        use_origin = getattr(seq, "use_map_origin", None)
        if use_origin is not None:   # a map file's sequence: its truth goes to the map's local frame
            use_origin(self.prior_map.origin)
        self._init_pose = initial_pose_on_map(getattr(seq, "initial_guess", None), self.prior_map,
                                              cfg.pf.sensor_height)
        if on_map is not None:       # a viewer shows the map while the tables are still being built
            on_map(self.prior_map)
        self._progress("lookup", 0.0)
        self.lookup = load_or_build_lookup(self.prior_map, self.map_dir, cfg.pf.lookup_resolution, cfg.pf.d_max,
                                           progress=lambda f: self._progress("lookup", f)).value
        self.pyramid = None
        if self.prior_map.points_bev is not None:
            self._progress("pyramid", 0.0)
            self.pyramid = load_or_build_pyramid(self.prior_map, self.map_dir, cfg.s2m).value
        recorded_odometry = None
        if cfg.localize.recorded_odometry:
            self._progress("odometry", 0.0)
            recorded_odometry = load_or_build_odometry(
                seq, self.odometry_cache_dir, progress=lambda f: self._progress("odometry", f)).value
        self._PF = ParticleFilter
        # one LiDAR sweep lasts one scan interval (a spinning sensor reports a scan per turn)
        gaps = np.diff(np.asarray(seq.timestamps, dtype=np.float64))
        gaps = gaps[gaps > 0]
        self._sweep_period = float(np.median(gaps)) if gaps.size else float(cfg.pf.dt)
        bmin, bmax = self.prior_map.bounds
        self._bounds = (np.asarray(bmin, float), np.asarray(bmax, float))
        self._lock = threading.RLock()
        self._rpe_pool = ThreadPoolExecutor(1, thread_name_prefix="lidarloc-RPE")
        self._s2m_pool = ThreadPoolExecutor(1, thread_name_prefix="lidarloc-S2M")
        self._rebuild_pool = ThreadPoolExecutor(1, thread_name_prefix="lidarloc-rebuild")
        self.rebuild_progress: float | None = None
        self._pending_lookup: Future | None = None
        self._pending_pyramid: Future | None = None
        self._closed = False
        self._interrupt = threading.Event()   # set by interrupt(): a waiting step gives up
        self._waiting: tuple[str, float] | None = None   # what a step waits for, since when
        self._failed: str | None = None      # a block's failure: steps refuse until restart()
        self.odometry = OdometryFeed(cfg, recorded_odometry, self._rpe_pool, wait=self._wait)
        self.odometry.process = early_rpe
        self.odometry.known = known_odometry
        self.odometry.scan_source = self._odometry_scan
        # controls that change the state between or inside steps (a recording checkpoints after
        # each: see core/resume.py); events before this index belong to an earlier recording
        self.controls = 0
        self.recorded_events_base = 0
        self.branch_of: dict | None = None     # {"run", "step"} of a branch (core/branch.py)
        self._lazy_s2m = lazy_s2m             # the S2M matcher starts when first needed
        self._pending_s2m: Future | None = None
        self._road_removal = None            # its child process while it runs (defer_s2m)
        if self.pyramid is not None:
            self.s2m = self._s2m_scheduler()
        else:
            self.s2m = S2MNotReady()
            # road removal runs in a niced child process: the first scans play at full speed
            self._pending_s2m = in_daemon_thread(self._build_s2m_tables, "lidarloc-road-removal")
        self._progress("ready", 1.0)
        self.restart(cfg.seed)

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
            self.pf = self._PF(self.cfg.pf, self.lookup, self._bounds[0], self._bounds[1], seed=self.cfg.seed,
                               map_points=self.prior_map.points)
            if self._init_pose is None:
                self.pf.initialize()
            else:
                self.pf.initialize(pose=self._init_pose[0], pose_std=self._init_pose[1])
            self.odometry.restart(origin=0)
            self.rules = LocalizationRules(self.cfg.localize)
            self.integrity = Integrity(self.cfg)
            self._alarm_on = False          # the truth alarm is raised (see _truth_check)
            self._failed = None
            self.k = 0                      # index of the next scan to process
            self.steps = 0                  # scans processed since the start (kidnap skips don't count)
            self.events: list[Event] = []
            self.records: list[ScanRecord] = []
            self.est_trajectory: list[np.ndarray] = []
            self._prev_t: float | None = None
            self._confidence = ConfidenceWatch()
            self._frame_check = ScanFrameCheck()
            if self._init_pose is not None:
                g = self.seq.initial_guess
                self._event(-1, "initial_guess", f"particles around x {g.x:.2f} m, y {g.y:.2f} m, yaw "
                            f"{np.degrees(g.yaw):.1f}° (σ {g.sigma_xy:g} m, {np.degrees(g.sigma_yaw):g}°)")
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
        self._interrupt.set()            # a step in progress gives up instead of holding the lock
        self._closed = True
        if self._road_removal is not None:
            self._road_removal.kill()
        with self._lock:
            self.s2m.cancel(self.k - 1, "localizer closed")
        pools = (self._rpe_pool, self._s2m_pool, self._rebuild_pool)
        for pool in pools:               # queued work is dropped …
            pool.shutdown(wait=False, cancel_futures=True)
        # … and the children close before the threads are joined: a match or registration in
        # flight is only thrown away, so a busy child is killed rather than waited for (a
        # whole-map match kept Ctrl-C waiting 1.2 s).
        self.odometry.close_process()
        self.s2m.close_processes()
        for pool in pools:
            pool.shutdown(wait=True)

    def wait_ready(self) -> None:
        """Block until every block is ready to work at full speed: the child processes (S2M's map,
        pyramid, GICP target and warm-up match; KISS-ICP) have finished their set-up, and the PF's
        kernels (scan down-sampling, likelihood) are loaded in this process.

        The real-time clock calls this before its first scan is due: a sensor's scans start
        arriving once the system is up, and set-up still running would take the CPU from the first
        scans (measured on the real drive in real time: without this the first whole-map match,
        started at scan 0, landed at scan 11–12; with it, at scan 3)."""
        from .likelihood import log_likelihood_floored

        # this process's own one-off costs too: numba loads a kernel from its cache at the first
        # call (~0.3 s for the scan down-sampling, measured), here instead of in scan 0's step
        few = np.asarray(self.prior_map.points[:64], dtype=np.float32)
        voxel_downsample_random(few, self.cfg.pf.scan_voxel, 0)
        some = self.pf.states[:2]
        log_likelihood_floored(some, few, self.lookup, self.effective_d_max, self.cfg.pf.sigma, np.zeros(len(some)))
        for worker in (self.s2m.matcher, self.odometry.process):
            if isinstance(worker, WorkerProxy):
                try:
                    worker.wait_ready()
                except RuntimeError as exc:
                    raise BlockError(str(exc)) from None

    def cpu_seconds(self) -> dict:
        """CPU time used so far by the blocks' processes, in seconds: ``main`` (this process: the
        PF, and the threads that feed the child processes), ``rpe`` (the KISS-ICP child) and
        ``s2m`` (the RS + S2M child). None where a block runs inside this process (then its time
        is in ``main``) or the platform cannot tell. Differences of two readings give what a run
        cost per block (``lidarloc run`` puts them in summary.json)."""
        try:
            import resource

            usage = resource.getrusage(resource.RUSAGE_SELF)
            main = usage.ru_utime + usage.ru_stime
        except ImportError:          # not a Unix
            main = None

        def child(worker):
            return worker.cpu_seconds() if isinstance(worker, WorkerProxy) else None
        return {"main": main, "rpe": child(self.odometry.process), "s2m": child(self.s2m.matcher)}

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

    @property
    def s2m_pending(self) -> bool:
        """Whether S2M is still waiting for its tables (road-removed map, BEV pyramid) to be built
        in the background (``defer_s2m``); it joins at the first scan after they are ready."""
        return self._pending_s2m is not None

    def s2m_status(self, k: int | None = None) -> tuple[str, str]:
        """Whether S2M can give its word at scan ``k`` (default: the next scan), and why not:
        ("ready", ""), ("building", "road removal 40 %"), ("held", "held back until scan 100") or
        ("off", "switched off"). Safe from any thread (a viewer asks while a cold start builds
        the tables)."""
        k = self.k if k is None else k
        if self._pending_s2m is not None:
            removal = self._road_removal
            if removal is not None and removal.progress < 1.0:
                return "building", f"road removal {100 * removal.progress:.0f} %"
            return "building", "road removal" if removal is None else "BEV pyramid"
        if not self.cfg.s2m.enabled:
            return "off", "switched off"
        if k < self.cfg.s2m.join_at_scan:
            return "held", f"held back until scan {self.cfg.s2m.join_at_scan}"
        return "ready", ""

    def waiting(self) -> tuple[str, float] | None:
        """While a step waits for a block: what it waits for and for how many seconds so far
        (e.g. ("the S2M match started at scan 412", 4.2)); None otherwise. Lock-free: a viewer
        asks while the step holds the lock."""
        w = self._waiting
        return None if w is None else (w[0], time.monotonic() - w[1])

    @property
    def rebuilding(self) -> bool:
        """Whether a lookup table or BEV pyramid is still being rebuilt in the background (after a
        live d_max or d_m change); a finished one is swapped in at the next scan."""
        return any(f is not None and not f.done() for f in (self._pending_lookup, self._pending_pyramid))

    # ------------------------------------------------------------------------ controls
    def reset(self, pose: np.ndarray | None = None, region: tuple | None = None) -> None:
        """Re-initialise the particles: globally, around a 4×4 pose, or inside (x0, y0, x1, y1)."""
        with self._lock:
            if region is not None:
                x0, y0, x1, y1 = region
                region = (min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
                if region[2] - region[0] <= 0 or region[3] - region[1] <= 0:
                    raise LidarlocError("reset region must have a positive width and height")
            self._reinitialize(region=region, pose=pose, why="particles reset")
            self.rules.reset()
            self.integrity.reset()
            self.controls += 1
            where = "globally" if pose is None and region is None else ("around a pose" if pose is not None else f"in {tuple(round(v, 1) for v in region)}")
            self._event(self.k - 1, "reset", f"particles re-initialised {where}")
            # A paused viewer shows the new particles at once; the last scan stays as it was.
            prev = self._snapshot
            fresh = self._make_snapshot(prev.scan_index, None, prev.pf_ms, None)
            self._snapshot = replace(fresh, scan_world=prev.scan_world)

    def kidnap(self, skip: int = 100) -> int:
        """Jump the vehicle ``skip`` scans ahead without telling the filter; returns the new index."""
        with self._lock:
            if skip < 1:
                raise LidarlocError("kidnap skip must be ≥ 1 scan")
            if self.k + 1 >= self.n_scans:
                raise LidarlocError("cannot kidnap: the sequence has no scans left")
            target = min(self.k + skip, self.n_scans - 1)
            self.controls += 1
            self.s2m.cancel(self.k - 1, "kidnap")
            self._event(self.k - 1, "kidnap", f"vehicle moved from scan {self.k} to {target}")
            self.k = target
            self.odometry.restart(origin=target)
            self._prev_t = None
            self.rules.reset()   # the odometry restarts: a window must not span the jump
            self.integrity.reset()
            self._refresh_snapshot()
            return target

    def move_estimate(self, dx: float, dy: float) -> None:
        """Move every particle by (dx, dy) metres without telling the filter: a wrong estimate
        that nobody announced (what a wrongly accepted match or a long stretch without features
        leaves behind), to test that the filter notices (``lidarloc bench integrity``). The S2M
        match in flight is dropped (its pose would put the filter right at once); the rules and
        the second opinion are not told."""
        with self._lock:
            self.controls += 1
            self.s2m.cancel(self.k - 1, "particles moved")
            self.pf.states[:, 0] += float(dx)
            self.pf.states[:, 1] += float(dy)
            self._event(self.k - 1, "kidnap", f"particles moved {float(np.hypot(dx, dy)):.0f} m; the filter was not told")
            self._refresh_snapshot()

    def set_params(self, **params) -> None:
        """Live parameter changes (:data:`~lidarloc.core.config.LIVE_PARAMS`, SI units), validated
        all together (:func:`~lidarloc.core.config.check_live_changes`), effective from the next scan."""
        with self._lock:
            if params.get("clock") == "realtime" and self.odometry.recorded:
                raise LidarlocError("the real-time clock needs live odometry (localize.recorded_odometry is on)")
            check_live_changes(self.cfg, params)
            self.controls += 1
            pf, s2m = self.cfg.pf, self.cfg.s2m
            for name, value in params.items():
                if name == "d_max":
                    pf.d_max = float(value)
                    if value > self.lookup.d_max_built + 1e-9:
                        self._rebuild_lookup(float(value))
                    self.pf.set_d_max(self.effective_d_max)
                elif name == "sigma":
                    pf.sigma = float(value)
                    self.pf.set_sigma(float(value))
                elif name == "q_std":
                    pf.q_std = tuple(float(q) for q in value)
                    self.pf.set_q_std(pf.q_std)
                elif name == "s2m_enabled":
                    s2m.enabled = bool(value)
                    if not value:
                        self.s2m.cancel(self.k - 1, "S2M switched off")
                        self._refresh_snapshot()
                elif name in ("region_x", "region_y", "angle_step"):
                    setattr(s2m, name, float(value))
                elif name == "match_resolution":
                    if abs(value - s2m.match_resolution) > 1e-9:
                        s2m.match_resolution = float(value)
                        self._rebuild_pyramid()
                elif name == "n_particles":
                    pf.n_particles = int(value)
                    self.s2m.cancel(self.k - 1, "particle count changed")   # particle indices change
                    self.pf.set_n_particles(int(value))
                elif name == "scan_voxel":
                    pf.scan_voxel = float(value)
                elif name == "clock":
                    self.cfg.localize.clock = value
                    self.s2m.follow_clock(self.k - 1)

    def live_params(self) -> dict:
        """The current value of every live parameter (keys of ``LIVE_PARAMS``, SI units)."""
        with self._lock:
            return {key: getattr(getattr(self.cfg, p.section), p.attr) for key, p in LIVE_PARAMS.items()}

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
        return min(self.cfg.pf.d_max, self.lookup.d_max_built)

    def snapshot(self) -> Snapshot:
        return self._snapshot

    def resume_payload(self, step: int):
        """What resuming from the step just recorded needs (a recording's ``step``-th row): see
        :func:`lidarloc.core.resume.resume_payload`."""
        from .resume import resume_payload

        with self._lock:
            return resume_payload(self, step)

    def _odometry_scan(self, k: int) -> np.ndarray:
        """Scan k as the odometry and S2M are given it (de-skewed if so configured)."""
        scan = self.seq.scan(k)
        return self._deskew(k, scan) if self.cfg.localize.deskew else scan

    # ------------------------------------------------------------------------ one scan
    def step(self) -> Snapshot:
        """Process the next scan and return the new snapshot."""
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
                return self._process_next_scan()
            except Interrupted:
                # The scan is not recorded, so neither are its events; a match that landed in
                # it counts as still in flight (close() or restart() reports it cancelled).
                del self.events[events_before:]
                self.s2m.job = job_before
                raise

    def _process_next_scan(self) -> Snapshot:
        """The body of step(), with the lock held."""
        self._swap_rebuilt_tables()
        k = self.k
        scan = self.seq.scan(k)
        t = self.seq.timestamp(k)
        dt = self.cfg.pf.dt if self._prev_t is None else max(t - self._prev_t, 1e-3)
        self._prev_t = t
        if self.cfg.localize.deskew:
            scan = self._deskew(k, scan)
        # RPE starts now and overlaps with the PF work below.
        self.odometry.submit(k, scan, t)

        # PF time excludes waiting for S2M (in replay the step blocks until the match is due).
        t0 = time.perf_counter()
        rng = np.random.default_rng([self.cfg.seed, k, 1])
        prepared = prepare_scan(scan, self.cfg.pf, rng)
        self.pf.predict(dt)
        self.pf.update(prepared)
        pf_s = time.perf_counter() - t0
        s2m_ms = self.s2m.land(k, prepared, self.pf, self.odometry, self._fits_better_there)
        verdict = self.s2m.verdict
        relocalized = verdict is not None and verdict.kind == "relocalize"
        if verdict is not None:
            self.integrity.note_verdict(k, verdict)
        if relocalized:
            self._relocalize(k, verdict)
        t1 = time.perf_counter()
        # Estimate from the weighted posterior, before resampling adds Monte Carlo noise.
        est = self.pf.estimate()
        n_weighed = self.pf.n
        pf_s += time.perf_counter() - t1
        self._check_scan_frame(k, est, prepared)    # before resampling: best_index names a particle

        if self.s2m_status(k)[0] == "ready" and k == self.cfg.s2m.join_at_scan > 0:
            self._event(k, "s2m_ready", f"held back until scan {k} (s2m.join_at_scan)")
        step_dist, yaw_odom = self.odometry.motion(k)
        confirmed = self.integrity.confirmed_since if self.integrity.required else None
        outcome = self.rules.update(k, est.std_xyz, step_dist, yaw_odom, confirmed)
        reinit = relocalized
        if outcome.event is not None:
            detail = f"max std {float(np.max(est.std_xyz)):.1f} m"
            if outcome.event == "localized" and self.integrity.required:
                detail += f", confirmed by the S2M match landed at scan {self.integrity.confirmed_at}"
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
        if outcome.reinit or lost is not None:
            self.integrity.reset()
            why = "a loss" if lost is not None else f"a {outcome.event.replace('_', ' ')}"
            self._reinitialize(k=k, why=f"re-initialised after {why}")
            reinit = True
            est = self.pf.estimate()
            n_weighed = self.pf.n
        else:
            entering_tracking = outcome.event == "localized" and self.cfg.localize.tracking
            if entering_tracking:    # resamples down: est.best_index no longer names a particle
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
        return snap

    def run(self, n: int | None = None, should_stop: Callable[[], bool] | None = None) -> Snapshot:
        """Process up to ``n`` scans (all remaining if None)."""
        remaining = self.n_scans - self.k if n is None else n
        for _ in range(remaining):
            if self.done or (should_stop is not None and should_stop()):
                break
            self.step()
        return self._snapshot

    # ------------------------------------------------------------------------ blocks
    def _deskew(self, k: int, scan: np.ndarray) -> np.ndarray:
        """Scan k moved into its mid-sweep frame with the newest known odometry step's constant
        velocity (see the module docstring); as it comes while no step is known."""
        from .deskew import deskew, sweep_offsets, twist_from_relative_pose

        step = self.odometry.last_step(k)
        if step is None:
            return scan
        velocity, angular_velocity = twist_from_relative_pose(*step)
        return deskew(scan, sweep_offsets(scan, self._sweep_period), velocity, angular_velocity)

    def _wait(self, future: Future, block: str, k: int, what: str | None = None):
        if not future.done():
            self._waiting = (what or (f"KISS-ICP's registration of scan {k}" if block == "RPE" else block),
                             time.monotonic())
        try:
            while not future.done():
                if self._interrupt.is_set():     # step() refuses further steps until restart()
                    raise Interrupted(f"interrupted at scan {k} while waiting for {block}")
                wait_futures([future], timeout=INTERRUPT_POLL_S)
        finally:
            self._waiting = None
        try:
            return future.result()
        except LidarlocError:
            raise
        except Exception as exc:  # a block's failure surfaces once, clearly, in the caller's thread
            self._event(k, "error", f"{block}: {exc}")
            # The step that saw it is half done (the PF already weighted scan k): refuse further
            # steps rather than silently repeat or skip work.
            self._failed = f"{block} block failed at scan {k}: {type(exc).__name__}: {exc}"
            raise BlockError(self._failed) from exc

    def _reinitialize(self, region=None, pose=None, k: int | None = None, why: str = "re-initialised",
                      speed: float | None = None) -> None:
        """Spread the particles again (globally, in a region or around a pose), leaving tracking
        mode: the full particle count comes back."""
        self.controls += 1
        self.s2m.cancel(self.k - 1 if k is None else k, why)
        if self.pf.n != self.cfg.pf.n_particles:
            self.pf.set_n_particles(self.cfg.pf.n_particles)
        if speed is None:
            self.pf.initialize(region=region, pose=pose)
        else:
            self.pf.initialize(region=region, pose=pose, speed=speed)

    def _fits_better_there(self, pose: np.ndarray, prepared: np.ndarray) -> tuple[bool, str]:
        """Whether the scan fits the map clearly better in 3D at ``pose`` than at the estimate
        (:func:`~lidarloc.core.integrity.fits_clearly_better`), and both fits in words: the
        second test a whole-map check's far pose must pass to move the filter."""
        from .geometry import pose_to_xyz_ypr
        from .likelihood import residual_stats

        d_max = self.effective_d_max
        here = residual_stats(self.pf.estimate().state[:6], prepared, self.lookup, d_max)
        there = residual_stats(pose_to_xyz_ypr(pose), prepared, self.lookup, d_max)
        words = (f"in 3D mean residual {there[1]:.2f} m against the estimate's {here[1]:.2f} m, inlier share "
                 f"{there[0]:.2f} against {here[0]:.2f}")
        return fits_clearly_better(there, here), words

    def _relocalize(self, k: int, verdict) -> None:
        """A whole-map check found a pose far from the estimate that both blocks clearly prefer:
        the particles start again around it, and the rule must fire again (with S2M's word)
        before the filter says localized (see :mod:`lidarloc.core.integrity`)."""
        self._event(k, "relocalized", f"from the estimate to {verdict.describe()}")
        self._reinitialize(pose=verdict.pose, k=k, why="re-localized by the whole-map check",
                           speed=self.odometry.rpe.speed(k) if self.odometry.rpe is not None else None)
        self.rules.reset()
        self.integrity.reset()

    def _truth_check(self, k: int, est) -> None:
        """A ``false_fire`` event when the rule says localized while the truth is farther than
        the metrics' 5 m (at the onset, or later while still localized): truth grades the filter,
        it never steers it."""
        if not self.seq.has_poses:
            return
        err = float(np.linalg.norm(est.pose[:3, 3] - self.seq.pose(k)[:3, 3]))
        alarm = truth_alarm(self.rules.localized, err)
        if alarm is not None and not self._alarm_on:
            onset = self.rules.localized_since == k
            self._event(k, "false_fire", alarm + ("" if onset else f" (localized since scan {self.rules.localized_since})"))
        self._alarm_on = alarm is not None

    def _enter_tracking(self, k: int) -> None:
        """Tracking mode: resample down to fewer particles; S2M searches a smaller region."""
        n = min(self.cfg.localize.tracking_particles, self.cfg.pf.n_particles)
        self.controls += 1
        self.s2m.cancel(k, "tracking mode: particle indices change")
        self.pf.set_n_particles(n)
        self._event(k, "tracking", f"{n} particles, S2M region ±{self.cfg.localize.tracking_region:g} m")

    # ------------------------------------------------------------------------ background rebuilds
    def _rebuild_lookup(self, d_max: float) -> None:
        from .lookup import load_or_build_lookup

        if self._pending_lookup is not None and not self._pending_lookup.done():
            return
        self.rebuild_progress = 0.0

        def build():
            def progress(f):
                self.rebuild_progress = float(f)
            return load_or_build_lookup(self.prior_map, self.map_dir, self.cfg.pf.lookup_resolution, d_max,
                                        progress=progress).value
        self._pending_lookup = self._rebuild_pool.submit(build)

    def _s2m_scheduler(self) -> S2MScheduler:
        return S2MScheduler(self.cfg, self.prior_map, self.pyramid, self.map_dir, self._bounds, self._s2m_pool,
                            wait=self._wait, event=self._event, start_matcher=not self._lazy_s2m)

    def _build_s2m_tables(self):
        """The road-removed map and the BEV pyramid (cached both), on a background thread; the
        road removal itself in a child process (:mod:`~lidarloc.core.road_removal`: open3d would
        hold the GIL for its whole run)."""
        from .bev import load_or_build_pyramid
        from .mapping import BEV_FILE, load_or_build_road_removed
        from .road_removal import RoadRemovalProcess

        if not (self.map_dir / BEV_FILE).is_file():
            self._road_removal = RoadRemovalProcess(self.map_dir, self.cfg.map)
            if self._closed:                 # closed meanwhile: nobody needs it
                self._road_removal.kill()
            self._road_removal.wait()
        prior = load_or_build_road_removed(self.prior_map, self.map_dir, self.cfg.map)   # reads the child's file
        return prior.points_bev, load_or_build_pyramid(prior, self.map_dir, replace(self.cfg.s2m)).value

    def _join_s2m(self) -> None:
        """S2M's tables are ready (``defer_s2m``): the real scheduler takes over from this scan."""
        fut, self._pending_s2m = self._pending_s2m, None
        bev, self.pyramid = self._wait(fut, "road removal and BEV pyramid", self.k)
        self.prior_map.points_bev = bev     # in place: a viewer holding the map sees it too
        self.s2m = self._s2m_scheduler()
        self._event(self.k, "s2m_ready", S2M_READY_DETAIL)
        if abs(self.pyramid.resolution - self.cfg.s2m.match_resolution) > 1e-9:   # changed meanwhile
            self._rebuild_pyramid()

    def _rebuild_pyramid(self) -> None:
        from .bev import load_or_build_pyramid

        if self._pending_s2m is not None:    # the pyramid being built follows the new value on arrival
            return
        self.rebuild_progress = 0.0
        cfg = replace(self.cfg.s2m)
        self._pending_pyramid = self._rebuild_pool.submit(
            lambda: load_or_build_pyramid(self.prior_map, self.map_dir, cfg).value)

    def _swap_rebuilt_tables(self) -> None:
        if self._pending_s2m is not None and self._pending_s2m.done():
            self._join_s2m()
        if self._pending_lookup is not None and self._pending_lookup.done():
            fut, self._pending_lookup = self._pending_lookup, None
            self.lookup = self._wait(fut, "lookup rebuild", self.k)
            self.pf.set_lookup(self.lookup)
            self.pf.set_d_max(self.effective_d_max)
            if self.cfg.pf.d_max > self.lookup.d_max_built + 1e-9:   # raised again meanwhile
                self._rebuild_lookup(self.cfg.pf.d_max)
        if self._pending_pyramid is not None and self._pending_pyramid.done():
            fut, self._pending_pyramid = self._pending_pyramid, None
            self.pyramid = self._wait(fut, "pyramid rebuild", self.k)
            self.s2m.use_pyramid(self.k, self.pyramid)
        if self._pending_lookup is None and self._pending_pyramid is None:
            self.rebuild_progress = None

    # ------------------------------------------------------------------------ outputs
    def _refresh_snapshot(self) -> None:
        """A control changed the state between scans (kidnap, S2M off): the snapshot says so at
        once — a paused viewer shows it without waiting for the next scan."""
        status, status_detail = self.s2m_status()
        self._snapshot = replace(self._snapshot, events=tuple(self.events[-50:]), localized=self.rules.localized,
                                 localized_since=self.rules.localized_since, s2m_running=self.s2m.job is not None,
                                 s2m_pending=self.s2m_pending, s2m_status=status, s2m_status_detail=status_detail,
                                 awaiting_confirmation=False,
                                 truth_alarm=truth_alarm(self.rules.localized, self._snapshot.error_m))

    def _event(self, k: int, kind: str, detail: str = "") -> None:
        self.events.append(Event(int(k), kind, detail))

    def _check_truth_frame(self) -> None:
        why = truth_outside_map(self.seq, self._bounds, self.prior_map.origin, self.cfg.pf.d_max)
        if why is not None:
            self._event(-1, "frame_mismatch", why)

    def _check_scan_frame(self, k: int, est, prepared: np.ndarray) -> None:
        """The scan-side frame check (:class:`~lidarloc.core.checks.ScanFrameCheck`): the inlier
        share at the highest-weight particle."""
        if not self._frame_check.wanted(self.steps):
            return
        from .likelihood import residual_stats

        share, _ = residual_stats(self.pf.states[est.best_index][:6], prepared, self.lookup, self.effective_d_max)
        why = self._frame_check.update(self.steps, self.n_scans, share, self.effective_d_max)
        if why is not None:
            self._event(k, "frame_mismatch", why)

    def _scan_fit(self, k: int, est, prepared: np.ndarray) -> tuple[float, float | None]:
        """How well the scan fits the map at the estimate: (inlier share, mean residual m), see
        :func:`~lidarloc.core.likelihood.residual_stats`; a ``confidence_low`` event when it
        drops (:class:`~lidarloc.core.checks.ConfidenceWatch`)."""
        from .likelihood import residual_stats

        share, residual = residual_stats(est.state[:6], prepared, self.lookup, self.effective_d_max)
        share, residual = float(share), (float(residual) if np.isfinite(residual) else None)   # None: no inlier
        why = self._confidence.update(self.rules.localized, share, residual, self.cfg.localize.min_inlier_share)
        if why is not None:
            self._event(k, "confidence_low", why)
        return share, residual

    def _make_snapshot(self, k: int, prepared, pf_ms: float, est, n_weighed: int | None = None,
                       fit: tuple[float, float | None] | None = None) -> Snapshot:
        """The snapshot after scan k (-1: none yet). ``n_weighed``: the particles the estimate
        ``est`` was computed from; ``fit``: :meth:`_scan_fit`'s (inlier share, mean residual)."""
        if est is None:
            est = self.pf.estimate()
            n_weighed = self.pf.n
        mean_T = est.pose
        gt = self.seq.pose(k) if k >= 0 and self.seq.has_poses else None
        err = None if gt is None else float(np.linalg.norm(mean_T[:3, 3] - gt[:3, 3]))
        inside = None if gt is None else inside_2sigma(mean_T[:2, 3] - gt[:2, 3], est.cov_xyz[:2, :2])
        share, residual = (None, None) if fit is None else fit
        status, status_detail = self.s2m_status(max(k, 0))
        scan_world = (np.zeros((0, 3), np.float32) if prepared is None
                      else transform_points(mean_T, prepared).astype(np.float32))
        return Snapshot(
            scan_index=k, n_scans=self.n_scans, timestamp=self.seq.timestamp(k) if k >= 0 else 0.0,
            particles=self.pf.states.copy(), weights=self.pf.weights.copy(), log_weights=self.pf.log_weights.copy(),
            best_index=int(est.best_index),
            mean_pose=mean_T, cov_xyz=est.cov_xyz, std_xyz=est.std_xyz, ellipse_xy=tuple(est.ellipse_xy),
            n_eff=float(est.n_eff), localized=self.rules.localized, localized_since=self.rules.localized_since,
            scan_world=scan_world, gt_pose=gt, error_m=err, pf_ms=pf_ms, rpe_ms=self.odometry.last_ms,
            s2m=self.s2m.last, s2m_running=self.s2m.job is not None, s2m_acceptance=self.s2m.acceptance,
            s2m_pending=self.s2m_pending,
            n_particles=int(n_weighed if n_weighed is not None else len(self.pf.states)),
            converged=bool(np.all(est.std_xyz < self.cfg.localize.std_threshold)),
            inlier_share=share, mean_residual_m=residual, inside_2sigma=inside,
            events=tuple(self.events[-50:]), done=self.k >= self.n_scans,
            s2m_status=status, s2m_status_detail=status_detail,
            awaiting_confirmation=bool(self.rules.awaiting_confirmation and not self.rules.localized),
            confirmed_at=self.integrity.confirmed_at, truth_alarm=truth_alarm(self.rules.localized, err))
