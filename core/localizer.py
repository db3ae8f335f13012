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
forward with it; see ``_odometry_ready_to_land``), and the rules read the newest finished
odometry instead of waiting for scan k's, so KISS-ICP and the PF overlap across scans.

Choice where the paper is vague: the paper suspends resampling between k and k'. We resample as
usual but protect the S2M particle's slot (the PF's ``protect`` argument), which keeps the
particle intact without starving the filter of resampling while S2M runs back to back.

Kidnap (viewer feature): the data index jumps ahead without telling the filter. The RPE's
KISS-ICP cannot register across a jump, so it is restarted at the new scan (a real system would
detect the failed registration the same way); the filter itself learns nothing.

Every ``s2m_started`` event ends in exactly one of ``s2m_accepted``, ``s2m_rejected`` or
``s2m_cancelled`` (the match could no longer land: re-initialised or resized particles, a kidnap,
S2M switched off, a clock change, a rebuilt pyramid, or ``close()``). Stopping: ``interrupt()``
(Ctrl-C, closing the viewer) makes a step that waits for a block give up without recording its
scan, and ``close()`` kills child processes that are busy or still setting up.
"""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .config import Config, DEG
from .errors import LidarlocError
from .geometry import euler_zyx, pose_matrix, pose_to_xyz_ypr, transform_points
from .mapping import load_or_build_map
from .rules import LocalizationRules
from .s2m_worker import S2MProcess
from .scanprep import voxel_downsample_random
from .snapshot import Event, S2MView, Snapshot


# Real time: how long a finished S2M match waits for its scan's odometry before it tries again at
# the next scan. Typical waits are ~10 ms (KISS-ICP registers scan k while the PF weighs it).
REALTIME_LAND_WAIT_S = 0.03
# … and after how many such tries it waits for the odometry however long it takes: a transient
# backlog (one slow registration, ~0.65 s on the town) clears well within it, while under a
# sustained one the landing still happens and the RPE queue stays bounded.
REALTIME_LAND_MAX_DEFERRALS = 20


class BlockError(LidarlocError):
    """A localizer block (thread) raised; the run stops with this one-line message."""


class Interrupted(LidarlocError):
    """``interrupt()`` stopped a step that was waiting for a block; that scan is not recorded."""


#: How often a step waiting for a block checks for ``interrupt()`` (seconds).
INTERRUPT_POLL_S = 0.05


@dataclass
class ScanRecord:
    """One row of the per-scan log (headless CSV, metrics A–E)."""

    scan: int
    time: float
    x: float
    y: float
    z: float
    yaw: float
    pitch: float
    roll: float
    std_x: float
    std_y: float
    std_z: float
    n_eff: float
    localized: bool
    error_m: float | None
    gt_x: float | None
    gt_y: float | None
    gt_z: float | None
    gt_yaw: float | None
    pf_ms: float
    s2m_ms: float | None
    reinit: bool


@dataclass
class _S2MJob:
    started_at: int
    particle: int
    generation: int
    start_pose: np.ndarray
    future: Future
    deferrals: int = 0        # real time: scans at which the finished match could not land yet


# Parameters the viewer may change live, with their validity checks.
_LIVE_PARAMS = {
    "d_max": lambda v: v > 0,
    "sigma": lambda v: v > 0,
    "q_std": lambda v: len(v) == 11 and all(math.isfinite(q) and q >= 0 for q in v),
    "s2m_enabled": lambda v: isinstance(v, bool),
    "region_x": lambda v: v > 0,
    "region_y": lambda v: v > 0,
    "match_resolution": lambda v: 0.1 <= v <= 10,
    "angle_step": lambda v: 0 < v <= math.pi,
    "n_particles": lambda v: int(v) == v and 1 <= v <= 200_000,
    "scan_voxel": lambda v: 0.05 <= v <= 10,
    "clock": lambda v: v in ("replay", "realtime"),
}


class Localizer:
    def __init__(self, seq, cfg: Config, cache_root: Path | None = None,
                 progress: Callable[[str, float], None] | None = None):
        from .bev import load_or_build_pyramid
        from .lookup import load_or_build_lookup
        from .pf import ParticleFilter
        from .rpe import RelativePoseEstimator
        from .s2m import ScanToMapMatcher

        self.seq, self.cfg = seq, cfg
        self.n_scans = len(seq)
        self._progress = progress or (lambda stage, frac: None)
        self.prior_map, self.map_dir, _ = load_or_build_map(
            seq, cfg.map, cache_root, progress=lambda i, n: self._progress("map", i / n))
        self._progress("lookup", 0.0)
        self.lookup, _ = load_or_build_lookup(self.prior_map, self.map_dir, cfg.pf.lookup_resolution, cfg.pf.d_max,
                                              progress=lambda f: self._progress("lookup", f))
        self._progress("pyramid", 0.0)
        self.pyramid = load_or_build_pyramid(self.prior_map, self.map_dir, cfg.s2m)
        self._recorded_odometry = None
        if cfg.localize.recorded_odometry:
            from .rpe import load_or_build_odometry

            self._progress("odometry", 0.0)
            self._recorded_odometry = load_or_build_odometry(seq, self.map_dir,
                                                             progress=lambda f: self._progress("odometry", f))
        if cfg.localize.s2m_process:
            # loads the cached map and pyramid and builds its GICP target while we go on
            self.matcher = S2MProcess(self.map_dir, cfg.map, cfg.s2m, self._s2m_nice())
        else:
            self.matcher = ScanToMapMatcher(self.prior_map, self.pyramid, cfg.s2m, cfg.map)
        self._progress("ready", 1.0)
        self._RPE = RelativePoseEstimator
        self._PF = ParticleFilter
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
        self._failed: str | None = None      # a block's failure: steps refuse until restart()
        self._kiss_process = None
        self._retired_matchers: list = []    # S2M processes replaced by a clock change
        self.restart(cfg.seed)

    # ------------------------------------------------------------------------ lifecycle
    def restart(self, seed: int | None = None) -> None:
        """Back to scan 0 with a fresh filter (same map, lookup table and pyramid)."""
        with self._lock:
            if seed is not None:
                self.cfg.seed = int(seed)
            self._cancel_s2m()
            self._interrupt.clear()
            if hasattr(self, "_rpe_futures"):
                self._wait_rpe_idle()
            self.pf = self._PF(self.cfg.pf, self.lookup, self._bounds[0], self._bounds[1], seed=self.cfg.seed,
                               map_points=self.prior_map.points)
            self.pf.initialize()
            self.rpe = self._new_rpe()
            self.rules = LocalizationRules(self.cfg.localize)
            self._failed = None
            self.k = 0                      # index of the next scan to process
            self.steps = 0                  # scans processed since the start (kidnap skips don't count)
            self.events: list[Event] = []
            self.records: list[ScanRecord] = []
            self.est_trajectory: list[np.ndarray] = []
            self._s2m_job: _S2MJob | None = None
            self._s2m_generation = 0
            self._last_s2m_start: int | None = None
            self._s2m_landed = 0
            self._s2m_accepted = 0
            self._last_s2m: S2MView | None = None
            self._rpe_futures: dict[int, Future] = {}
            self._rpe_origin = 0            # first scan the current KISS-ICP run has seen
            self._rpe_used: int | None = None   # last odometry scan the rules consumed (real time)
            self._prev_t: float | None = None
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
        with self._lock:
            self._closed = True
            self._cancel_s2m(why="localizer closed")
        pools = (self._rpe_pool, self._s2m_pool, self._rebuild_pool)
        for pool in pools:               # queued work is dropped …
            pool.shutdown(wait=False, cancel_futures=True)
        # … and the children close before the threads are joined: a match or registration in
        # flight is only thrown away, so a busy child is killed rather than waited for (a
        # whole-map match kept Ctrl-C waiting 1.2 s).
        if self._kiss_process is not None:
            self._kiss_process.close()
        for matcher in [self.matcher, *self._retired_matchers]:
            if isinstance(matcher, S2MProcess):
                matcher.close()
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
        log_likelihood_floored(some, few, self.lookup, self.cfg.pf.d_max, self.cfg.pf.sigma, np.zeros(len(some)))
        for worker in (self.matcher, self._kiss_process):
            if hasattr(worker, "wait_ready"):
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
            reading = getattr(worker, "cpu_seconds", None)
            return reading() if reading is not None else None
        return {"main": main, "rpe": child(self._kiss_process), "s2m": child(self.matcher)}

    def _new_rpe(self):
        """A fresh odometry. KISS-ICP holds the GIL while it registers a scan, so by default it
        runs in a child process (one per localizer, reset instead of restarted)."""
        if self._recorded_odometry is not None:
            return self._RPE(recorded=self._recorded_odometry)
        if not self.cfg.localize.rpe_process:
            return self._RPE()
        if self._kiss_process is None:
            from .rpe_worker import KissICPProcess

            self._kiss_process = KissICPProcess()
        else:
            self._kiss_process.reset()
        return self._RPE(icp=self._kiss_process)

    def _wait_rpe_idle(self) -> None:
        """Let queued RPE work finish before its odometry is replaced (it shares the process)."""
        for fut in list(self._rpe_futures.values()):
            try:
                fut.result()
            except Exception:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def done(self) -> bool:
        return self.k >= self.n_scans

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
            self._cancel_s2m(why="kidnap")
            self._event(self.k - 1, "kidnap", f"vehicle moved from scan {self.k} to {target}")
            self.k = target
            self._wait_rpe_idle()
            self.rpe = self._new_rpe()
            self._rpe_futures.clear()
            self._rpe_origin = target
            self._rpe_used = None
            self._prev_t = None
            self.rules.reset()   # the odometry restarts: a window must not span the jump
            return target

    def set_params(self, **params) -> None:
        """Live parameter changes, validated, effective from the next scan."""
        with self._lock:
            for name, value in params.items():
                check = _LIVE_PARAMS.get(name)
                if check is None:
                    raise LidarlocError(f"unknown parameter '{name}'")
                try:
                    if isinstance(value, float) and not math.isfinite(value):
                        raise ValueError
                    ok = check(value)
                except (TypeError, ValueError):
                    ok = False
                if not ok:
                    raise LidarlocError(f"invalid value for {name}: {value!r}")
                if name == "clock" and value == "realtime" and self._recorded_odometry is not None:
                    raise LidarlocError("the real-time clock needs live odometry (localize.recorded_odometry is on)")
            pf, s2m = self.cfg.pf, self.cfg.s2m
            for name, value in params.items():
                if name == "d_max":
                    pf.d_max = float(value)
                    if value > self.lookup.d_max_built + 1e-9:
                        self._rebuild_lookup(float(value))
                    self.pf.set_d_max(min(float(value), self.lookup.d_max_built))
                elif name == "sigma":
                    pf.sigma = float(value)
                    self.pf.set_sigma(float(value))
                elif name == "q_std":
                    pf.q_std = tuple(float(q) for q in value)
                    self.pf.set_q_std(pf.q_std)
                elif name == "s2m_enabled":
                    s2m.enabled = bool(value)
                    if not value:
                        self._cancel_s2m(why="S2M switched off")
                elif name in ("region_x", "region_y", "angle_step"):
                    setattr(s2m, name, float(value))
                elif name == "match_resolution":
                    if abs(value - s2m.match_resolution) > 1e-9:
                        s2m.match_resolution = float(value)
                        self._rebuild_pyramid()
                elif name == "n_particles":
                    pf.n_particles = int(value)
                    self._cancel_s2m(why="particle count changed")   # particle indices change
                    self.pf.set_n_particles(int(value))
                elif name == "scan_voxel":
                    pf.scan_voxel = float(value)
                elif name == "clock":
                    self.cfg.localize.clock = value
                    self._renice_s2m()

    def snapshot(self) -> Snapshot:
        return self._snapshot

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
            events_before, job_before = len(self.events), self._s2m_job
            try:
                return self._process_next_scan()
            except Interrupted:
                # The scan is not recorded, so neither are its events; a match that landed in
                # it counts as still in flight (close() or restart() reports it cancelled).
                del self.events[events_before:]
                self._s2m_job = job_before
                raise

    def _process_next_scan(self) -> Snapshot:
        """The body of step(), with the lock held."""
        self._swap_rebuilt_tables()
        k = self.k
        scan = self.seq.scan(k)
        t = self.seq.timestamp(k)
        dt = self.cfg.pf.dt if self._prev_t is None else max(t - self._prev_t, 1e-3)
        self._prev_t = t
        # RPE starts now and overlaps with the PF work below.
        self._rpe_futures[k] = self._rpe_pool.submit(self._rpe_add, self.rpe, k, scan, t)

        # PF time excludes waiting for S2M (in replay the step blocks until the match is due).
        t0 = time.perf_counter()
        rng = np.random.default_rng([self.cfg.seed, k, 1])
        prepared = voxel_downsample_random(scan[:, :3], self.cfg.pf.scan_voxel, rng)
        self.pf.predict(dt)
        self.pf.update(prepared)
        pf_s = time.perf_counter() - t0
        s2m_ms = self._maybe_land_s2m(k, prepared)
        t1 = time.perf_counter()
        # Estimate from the weighted posterior, before resampling adds Monte Carlo noise.
        est = self.pf.estimate()
        pf_s += time.perf_counter() - t1

        step_dist, yaw_odom = self._rpe_motion(k)
        outcome = self.rules.update(k, est.std_xyz, step_dist, yaw_odom)
        reinit = False
        if outcome.event is not None:
            self._event(k, outcome.event, f"max std {float(np.max(est.std_xyz)):.1f} m")
        if outcome.reinit:
            self._reinitialize(k=k, why=f"re-initialised after a {outcome.event.replace('_', ' ')}")
            reinit = True
            est = self.pf.estimate()
        else:
            entering_tracking = outcome.event == "localized" and self.cfg.localize.tracking
            if entering_tracking:    # resamples down: est.best_index no longer names a particle
                self._enter_tracking(k)
            # S2M starts from the highest-weight particle of this posterior; that slot is
            # then protected through every resampling until the match lands.
            if self.cfg.s2m.enabled and self._s2m_job is None and not entering_tracking and self._s2m_due(k):
                self._start_s2m(k, est.best_index, scan)
            t2 = time.perf_counter()
            protect = self._s2m_job.particle if self._s2m_job is not None else None
            self.pf.resample_if_needed(protect=protect)
            pf_s += time.perf_counter() - t2
        pf_ms = pf_s * 1000.0

        self.k += 1
        self.steps += 1
        snap = self._make_snapshot(k, prepared, pf_ms, est)
        self._record(k, t, est, snap, pf_ms, s2m_ms, reinit)
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
    def _rpe_add(self, rpe, k, scan, t):
        rpe.add(k, scan, t)

    def _wait(self, future: Future, block: str, k: int):
        while not future.done():
            if self._interrupt.is_set():     # step() refuses further steps until restart()
                raise Interrupted(f"interrupted at scan {k} while waiting for {block}")
            wait_futures([future], timeout=INTERRUPT_POLL_S)
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

    def _rpe_motion(self, k: int) -> tuple[float, float]:
        """Distance driven since the rules' previous scan and the odometry yaw, for the rules.

        Replay: from k−1 to k (waits for the RPE of scan k). Real time: from the previous to the
        newest scan whose odometry is done, without waiting, so the PF of scan k+1 and KISS-ICP's
        registration of scan k overlap instead of taking turns (the rules then lag the odometry by
        a scan at most; the motion is counted once all the same)."""
        if self.cfg.localize.clock == "realtime":
            latest = None
            for i in range(k, max(self._rpe_origin, self._rpe_used or 0) - 1, -1):
                fut = self._rpe_futures.get(i)
                if fut is not None and fut.done():
                    self._wait(fut, "RPE", i)     # a failed registration surfaces here
                    latest = i
                    break
            if latest is None:
                latest = self._rpe_used
                if latest is None:            # nothing registered yet since the (re)start
                    self._wait(self._rpe_futures[k], "RPE", k)
                    latest = k
        else:
            self._wait(self._rpe_futures[k], "RPE", k)
            latest = k
        for old in [i for i in self._rpe_futures if i < k - 200]:
            del self._rpe_futures[old]
        yaw = float(euler_zyx(self.rpe.odom_pose(latest)[:3, :3])[0])
        prev = latest - 1 if self.cfg.localize.clock != "realtime" else self._rpe_used
        self._rpe_used = latest
        if prev is None or prev < self._rpe_origin or prev >= latest:
            return 0.0, yaw
        if prev == latest - 1:
            return float(np.linalg.norm(self.rpe.relative(prev, latest)[:3, 3])), yaw
        return self.rpe.moved_since(prev, latest), yaw

    def _reinitialize(self, region=None, pose=None, k: int | None = None, why: str = "re-initialised") -> None:
        """Spread the particles again (globally, in a region or around a pose), leaving tracking
        mode: the full particle count comes back."""
        self._cancel_s2m(k, why)
        if self.pf.n != self.cfg.pf.n_particles:
            self.pf.set_n_particles(self.cfg.pf.n_particles)
        self.pf.initialize(region=region, pose=pose)

    def _enter_tracking(self, k: int) -> None:
        """Tracking mode: resample down to fewer particles; S2M searches a smaller region."""
        n = min(self.cfg.localize.tracking_particles, self.cfg.pf.n_particles)
        self._cancel_s2m(k, "tracking mode: particle indices change")
        self.pf.set_n_particles(n)
        self._event(k, "tracking", f"{n} particles, S2M region ±{self.cfg.localize.tracking_region:g} m")

    def _s2m_job_config(self, j: int):
        """The S2M settings for a job from particle j: the whole map until localized (if so
        configured), the tracking region while tracking, else the configured local region."""
        cfg = replace(self.cfg.s2m)
        if not self.rules.localized and cfg.global_until_localized:
            x, y = self.pf.states[j, :2]
            (x0, y0, _), (x1, y1, _) = self._bounds
            cfg.region_x = max(cfg.region_x, x - x0, x1 - x)
            cfg.region_y = max(cfg.region_y, y - y0, y1 - y)
        elif self.rules.localized and self.cfg.localize.tracking:
            cfg.region_x = min(cfg.region_x, self.cfg.localize.tracking_region)
            cfg.region_y = min(cfg.region_y, self.cfg.localize.tracking_region)
        return cfg

    def _s2m_due(self, k: int) -> bool:
        """Back to back, except in real time once localized: then every
        ``s2m.realtime_interval_localized`` scans at most (CPU for the PF and the RPE first)."""
        every = self.cfg.s2m.realtime_interval_localized
        if self.cfg.localize.clock != "realtime" or not self.rules.localized or every <= 0:
            return True
        return self._last_s2m_start is None or k - self._last_s2m_start >= every

    def _start_s2m(self, k: int, j: int, scan: np.ndarray) -> None:
        """Start a match of scan k from particle j's pose (RS, then S2M, in the background)."""
        start_pose = pose_matrix(*self.pf.states[j, :6])
        self._s2m_generation += 1
        # before localization the particle's z, pitch and roll are as random as its position
        level = not self.rules.localized
        future = self._s2m_pool.submit(self._run_s2m, self.matcher, scan, start_pose, self._s2m_job_config(j), level)
        self._s2m_job = _S2MJob(k, j, self._s2m_generation, start_pose, future)
        self._last_s2m_start = k
        self._event(k, "s2m_started", f"particle {j}")

    def _s2m_nice(self) -> int:
        """The S2M process's priority offset for the current clock (see s2m.replay_process_nice)."""
        return self.cfg.s2m.replay_process_nice if self.cfg.localize.clock == "replay" else 0

    def _renice_s2m(self) -> None:
        """After a clock change: a process niced for replay cannot be raised back (that needs
        privileges), so real time gets a fresh one at nice 0. The old one finishes its match on
        the S2M thread, which then closes it; the caller does not wait."""
        nice = self._s2m_nice()
        # same nice, or back to replay (a higher priority there changes no result): keep it
        if not isinstance(self.matcher, S2MProcess) or nice >= self.matcher.nice:
            return
        self._cancel_s2m(why="clock changed: new S2M process")
        old, self.matcher = self.matcher, S2MProcess(self.map_dir, self.cfg.map, self.cfg.s2m, nice)
        self._retired_matchers.append(old)     # close() kills it if its match is still running
        self._s2m_pool.submit(old.close)

    @staticmethod
    def _run_s2m(matcher, scan: np.ndarray, start_pose: np.ndarray, s2m_cfg, level: bool):
        if isinstance(matcher, S2MProcess):     # the child process: it takes the live settings along
            return matcher.match_local(scan, start_pose, s2m_cfg, level=level)
        matcher.cfg = s2m_cfg
        return matcher.match_local(scan, start_pose, level=level)

    def _cancel_s2m(self, k: int | None = None, why: str = "") -> None:
        """Drop the match in flight (running, or finished and waiting to land). With a reason,
        an ``s2m_cancelled`` event at scan k says so, so that every ``s2m_started`` ends in
        exactly one of accepted / rejected / cancelled."""
        job = getattr(self, "_s2m_job", None)
        if job is not None:
            job.future.cancel()  # if already running it finishes, and its result is ignored
            if why:
                self._event(self.k - 1 if k is None else k, "s2m_cancelled", f"started {job.started_at} ({why})")
        self._s2m_job = None

    def _maybe_land_s2m(self, k: int, prepared: np.ndarray) -> float | None:
        job = self._s2m_job
        if job is None:
            return None
        if self.cfg.localize.clock == "replay":
            if k < job.started_at + self.cfg.s2m.n_s2m:
                return None
        elif not job.future.done() or not self._odometry_ready_to_land(job, k):
            return None   # real time: land at a scan after the match finished (see there)
        self._s2m_job = None
        outcome = self._wait(job.future, "S2M", k)
        self._s2m_landed += 1
        accepted = bool(outcome.accepted)
        pose_k = outcome.pose
        reason = outcome.reason
        if accepted:
            # Carry the match for scan k₀ forward to scan k with the RPE relative pose.
            self._wait(self._rpe_futures[k], "RPE", k)
            if job.started_at < self._rpe_origin:
                accepted, reason = False, "odometry restarted since the match started"
            else:
                from .s2m import carry_forward

                try:
                    pose_k = carry_forward(outcome.pose, self.rpe, job.started_at, k)
                except KeyError:  # the odometry no longer holds scan k₀ (landed very late)
                    accepted, reason = False, f"odometry no longer holds scan {job.started_at}"
        if accepted:
            state = self.pf.states[job.particle].copy()
            state[:6] = pose_to_xyz_ypr(pose_k)
            state[6] = self.rpe.speed(k)
            state[7:10] = self.rpe.rates(k)
            self.pf.set_particle(job.particle, state)
            self.pf.reweight(job.particle, prepared)
            self._s2m_accepted += 1
        self._event(k, "s2m_accepted" if accepted else "s2m_rejected",
                    f"started {job.started_at}, score {outcome.score:.0f} vs {outcome.start_score:.0f}"
                    + (f" ({reason})" if reason and not accepted else ""))
        scan_world = outcome.scan_world if outcome.scan_world is not None else np.zeros((0, 3), np.float32)
        self._last_s2m = S2MView(
            started_at=job.started_at, landed_at=k, accepted=accepted, score=float(outcome.score),
            start_score=float(outcome.start_score), pose=np.asarray(pose_k),
            scan_world=scan_world,
            region=tuple(outcome.region), ms=float(outcome.ms), reason=reason or "")
        return float(outcome.ms)

    def _odometry_ready_to_land(self, job: _S2MJob, k: int) -> bool:
        """Real time: an accepted match is carried forward with scan k's odometry, so it lands
        only if KISS-ICP has registered scan k within ``REALTIME_LAND_WAIT_S`` (no wait at all
        while scan k−1 is still pending: the odometry is then behind); otherwise it tries again
        at the next scan, its particle still protected, and after ``REALTIME_LAND_MAX_DEFERRALS``
        tries it waits for the odometry. Always blocking until the odometry was done stalled the
        PF behind KISS-ICP's backlog: one town scan takes KISS-ICP 0.65 s (``lidarloc bench
        rpe``), and the landing that waited for it made 16 scans late. A failed or rejected match
        needs no odometry and lands at once."""
        if job.future.exception() is not None or not job.future.result().accepted:
            return True       # a failure (the landing reports it) or a rejection: no odometry needed
        if job.deferrals >= REALTIME_LAND_MAX_DEFERRALS:
            return True       # the landing waits for the odometry
        previous = self._rpe_futures.get(k - 1)
        behind = previous is not None and not previous.done()   # a backlog: do not wait
        registration = self._rpe_futures[k]
        wait_futures([registration], timeout=0.0 if behind else REALTIME_LAND_WAIT_S)
        if not registration.done():
            job.deferrals += 1
            return False
        return True           # registered (or failed: the landing reports it)

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
                                        progress=progress)[0]
        self._pending_lookup = self._rebuild_pool.submit(build)

    def _rebuild_pyramid(self) -> None:
        from .bev import load_or_build_pyramid

        self.rebuild_progress = 0.0
        cfg = replace(self.cfg.s2m)
        self._pending_pyramid = self._rebuild_pool.submit(load_or_build_pyramid, self.prior_map, self.map_dir, cfg)

    def _swap_rebuilt_tables(self) -> None:
        if self._pending_lookup is not None and self._pending_lookup.done():
            fut, self._pending_lookup = self._pending_lookup, None
            self.lookup = self._wait(fut, "lookup rebuild", self.k)
            self.pf.set_lookup(self.lookup)
            self.pf.set_d_max(min(self.cfg.pf.d_max, self.lookup.d_max_built))
            if self.cfg.pf.d_max > self.lookup.d_max_built + 1e-9:   # raised again meanwhile
                self._rebuild_lookup(self.cfg.pf.d_max)
        if self._pending_pyramid is not None and self._pending_pyramid.done():
            fut, self._pending_pyramid = self._pending_pyramid, None
            from .s2m import ScanToMapMatcher

            self.pyramid = self._wait(fut, "pyramid rebuild", self.k)
            self._cancel_s2m(self.k, "map pyramid rebuilt")
            if not isinstance(self.matcher, S2MProcess):  # the S2M process reloads it from the cache itself
                self.matcher = ScanToMapMatcher(self.prior_map, self.pyramid, self.cfg.s2m, self.cfg.map)
        if self._pending_lookup is None and self._pending_pyramid is None:
            self.rebuild_progress = None

    # ------------------------------------------------------------------------ outputs
    def _event(self, k: int, kind: str, detail: str = "") -> None:
        self.events.append(Event(int(k), kind, detail))

    def _make_snapshot(self, k: int, prepared, pf_ms: float, est) -> Snapshot:
        if est is None:
            est = self.pf.estimate()
        mean_T = est.pose
        gt = self.seq.pose(k) if k >= 0 and self.seq.has_poses else None
        err = None if gt is None else float(np.linalg.norm(mean_T[:3, 3] - gt[:3, 3]))
        scan_world = (np.zeros((0, 3), np.float32) if prepared is None
                      else transform_points(mean_T, prepared).astype(np.float32))
        landed = max(self._s2m_landed, 1)
        return Snapshot(
            scan_index=k, n_scans=self.n_scans, timestamp=self.seq.timestamp(k) if k >= 0 else 0.0,
            particles=self.pf.states.copy(), weights=self.pf.weights.copy(), best_index=int(est.best_index),
            mean_pose=mean_T, cov_xyz=est.cov_xyz, std_xyz=est.std_xyz, ellipse_xy=tuple(est.ellipse_xy),
            n_eff=float(est.n_eff), localized=self.rules.localized, localized_since=self.rules.localized_since,
            scan_world=scan_world, gt_pose=gt, error_m=err, pf_ms=pf_ms, s2m=self._last_s2m,
            s2m_running=self._s2m_job is not None, s2m_acceptance=self._s2m_accepted / landed,
            events=tuple(self.events[-50:]), done=self.k >= self.n_scans)

    def _record(self, k, t, est, snap: Snapshot, pf_ms, s2m_ms, reinit) -> None:
        xyz_ypr = pose_to_xyz_ypr(est.pose)
        gt = snap.gt_pose
        gt_xyz_ypr = pose_to_xyz_ypr(gt) if gt is not None else [None] * 6
        self.est_trajectory.append(est.pose)
        self.records.append(ScanRecord(
            scan=k, time=t, x=xyz_ypr[0], y=xyz_ypr[1], z=xyz_ypr[2], yaw=xyz_ypr[3], pitch=xyz_ypr[4],
            roll=xyz_ypr[5], std_x=float(est.std_xyz[0]), std_y=float(est.std_xyz[1]), std_z=float(est.std_xyz[2]),
            n_eff=float(est.n_eff), localized=snap.localized, error_m=snap.error_m,
            gt_x=gt_xyz_ypr[0], gt_y=gt_xyz_ypr[1], gt_z=gt_xyz_ypr[2], gt_yaw=gt_xyz_ypr[3],
            pf_ms=pf_ms, s2m_ms=s2m_ms, reinit=reinit))
