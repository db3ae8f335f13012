"""The RPE block as the localizer drives it: every scan is registered by KISS-ICP on the RPE
thread as soon as it is read, overlapping the PF's work on it, and the localizer's rules and the
S2M landing read the odometry of the scans registered so far.

KISS-ICP holds the GIL while it registers a scan, so by default it runs in a child process
(:mod:`lidarloc.core.odometry.worker`), one per localizer, reset instead of restarted. With recorded
odometry (``localize.recorded_odometry``) no ICP runs at all: the poses come from the cache.

Resuming a recorded run (:mod:`lidarloc.core.runs.branch`): ``known`` holds the poses the recorded
run's odometry gave each scan (with the scan that odometry run started from); they are used bit
for bit while they last, so a replayed step sees exactly the odometry the original saw. The first
scan without one is registered by a fresh KISS-ICP, warmed up first on the ``WARMUP_SCANS`` scans
before it (the recorded ones: KISS-ICP's local map and its adaptive threshold need a few scans of
history; ten scans of the town are ~60 m of road) and anchored at the recorded pose of the first of
them, so that its poses continue in the recorded run's odometry frame. In real time the rules read
the newest odometry finished in time, a choice of timing: ``used_plan`` repeats the recorded run's.

A KISS-ICP child that dies (killed, out of memory) is replaced on the RPE thread, before the
registration that finds it dead or that it failed: the new KISS-ICP is warmed up on the
``WARMUP_SCANS`` scans before that scan and anchored at the first of them, exactly as a resumed
run's, so the odometry goes on in the same frame and no match in flight loses its carry-forward.
What happened is in :meth:`OdometryFeed.take_notices` for the localizer's events. A restart
depends only on the scan whose registration found the child dead, so in the replay clock a run
killed between the same two scans gives the same trajectory every time. A new child that dies
again before it answered anything stops the run (:meth:`~lidarloc.core.worker_process.WorkerProxy.revive`).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from typing import Any

import numpy as np

from ..config import Config
from ..geometry import euler_zyx
from ..worker_process import WorkerDied
from .rpe import RelativePoseEstimator
from .worker import KissICPProcess

#: Registrations of one scan tried before its failure stops the run: the first, and one after
#: each of up to two restarts of a child that died after answering (one that dies again at once
#: stops the run at its restart).
REGISTRATION_ATTEMPTS = 3

#: Scans a resumed run's KISS-ICP registers before the first scan it has no recorded pose for.
WARMUP_SCANS = 10


class AnchoredICP:
    """A KISS-ICP whose poses are reported in another odometry frame: ``anchor`` · its own pose
    (its first registered scan is at the identity in its own frame)."""

    def __init__(self, icp, anchor: np.ndarray):
        self.icp = icp
        self.anchor = np.asarray(anchor, dtype=np.float64)

    def register_frame(self, points, times):
        return self.icp.register_frame(points, times)

    @property
    def last_pose(self) -> np.ndarray:
        return self.anchor @ np.asarray(self.icp.last_pose, dtype=np.float64)


class OdometryFeed:
    """One odometry run at a time (``restart``), fed scan by scan (``submit``) on ``pool``.

    ``wait(future, block, k)`` is the localizer's wait for a block: it gives up on
    ``interrupt()`` and turns a failed registration into a clear error."""

    def __init__(
        self,
        cfg: Config,
        recorded: np.ndarray | None,
        pool: ThreadPoolExecutor,
        wait: Callable[[Future, str, int], Any],
    ):
        self.cfg = cfg
        self._recorded = recorded
        self._pool = pool
        self._wait = wait
        self.process: KissICPProcess | None = None  # the KISS-ICP child, once started
        self.rpe: RelativePoseEstimator | None = None
        self.futures: dict[int, Future] = {}  # registrations by scan
        self._times: dict[int, float] = {}  # timestamps of the submitted scans
        self.origin = 0  # first scan the current KISS-ICP run has seen
        self.used: int | None = None  # last odometry scan the rules consumed (real time)
        self.last_ms: float | None = None  # wall time of the newest finished registration
        # resuming a recorded run (module docstring): scan → (its odometry run's first scan,
        # T_odom←scan), and the scans as the odometry registers them, for the warm-up
        self.known: dict[int, tuple[int, np.ndarray]] | None = None
        self.scan_source: Callable[[int], np.ndarray] | None = None
        self.live_from: int | None = None  # the first scan KISS-ICP registered after the known ones
        # real time: scan → the odometry scan the recorded run's rules read at it (timing chose it)
        self.used_plan: dict[int, int] | None = None
        self._notices: list[tuple[int, str]] = []  # (scan, what happened): restarts of the child
        self._notices_lock = threading.Lock()

    @property
    def recorded(self) -> bool:
        """Whether the poses are replayed from the cache instead of computed."""
        return self._recorded is not None

    def restart(self, origin: int) -> None:
        """A fresh odometry from scan ``origin`` on (start, restart, kidnap: KISS-ICP cannot
        register across a jump). Queued registrations finish first: they share the process."""
        for fut in list(self.futures.values()):
            try:
                fut.result()
            except Exception:
                pass
        self.origin = origin
        self.rpe = self._new_rpe()
        self.futures.clear()
        self._times.clear()
        self.used = None
        self.last_ms = None

    def _new_rpe(self) -> RelativePoseEstimator:
        if self._recorded is not None:
            return RelativePoseEstimator(recorded=self._recorded)
        if self.known is not None:
            known = {k: pose for k, (origin, pose) in self.known.items() if origin == self.origin}
            rpe = RelativePoseEstimator(known=known, make_icp=lambda k: self._warmed_up_icp(rpe, k))
            return rpe
        return RelativePoseEstimator(icp=self._fresh_icp())

    def _fresh_icp(self):
        """A KISS-ICP that has seen no scan: the child process (started once, then reset) or, with
        ``localize.rpe_process`` off, one in this process."""
        if not self.cfg.localize.rpe_process:
            from kiss_icp.kiss_icp import KissICP

            from .kiss import kiss_config

            return KissICP(kiss_config(100.0, 2.5, None))
        if self.process is None:
            self.process = KissICPProcess()
            return self.process
        words = self.process.ensure_alive()  # a fresh one has seen nothing: no reset needed
        if words is not None:
            self._notice(self.origin, words)
            return self.process
        try:
            self.process.reset()
        except WorkerDied as exc:
            self._notice(self.origin, self.process.revive(exc.worker))
        return self.process

    def _warmed_up_icp(self, rpe: RelativePoseEstimator, k: int) -> AnchoredICP:
        """The KISS-ICP that takes over at scan k from the known poses: registers the up to
        ``WARMUP_SCANS`` scans before k that the odometry holds, and reports its poses in their
        frame (anchored at the first of them)."""
        self.live_from = k
        return self._warm_up(self._fresh_icp(), rpe, k)

    def _warm_up(self, icp, rpe: RelativePoseEstimator, k: int) -> AnchoredICP:
        """``icp`` (fresh) after registering the up to ``WARMUP_SCANS`` scans before k that the
        odometry holds, reporting its poses in their frame (anchored at the first of them)."""
        held = {j: pose for j, pose, *_ in rpe.entries()}
        window = [j for j in range(max(self.origin, k - WARMUP_SCANS), k) if j in held]
        for j in window:
            pts = np.ascontiguousarray(np.asarray(self.scan_source(j))[:, :3], dtype=np.float64)
            icp.register_frame(pts, np.zeros(0))
        return AnchoredICP(icp, held[window[0]] if window else np.eye(4))

    # ------------------------------------------------------------------------ a child that died
    def _notice(self, k: int, words: str | None) -> None:
        if words:
            with self._notices_lock:
                self._notices.append((int(k), words))

    def take_notices(self) -> list[tuple[int, str]]:
        """What happened to the KISS-ICP child since the last call: (scan, words) per restart."""
        with self._notices_lock:
            out, self._notices = self._notices, []
        return out

    def _revive(self, rpe: RelativePoseEstimator, k: int, died=None) -> None:
        """The RPE thread, before registering scan k: a new KISS-ICP child in place of the dead
        one, warmed up on the scans before k (see the module docstring). Raises BlockError when
        the child died again at once."""
        words = self.process.revive(died)
        self._notice(k, words)
        if words is not None and rpe.live_icp is not None:
            rpe.live_icp = self._warm_up(self.process, rpe, k)

    # ------------------------------------------------------------------------ resuming
    def checkpoint(self) -> dict[str, np.ndarray]:
        """The odometry as the filter sees it between two scans: the registered scans' poses,
        times, path lengths and rotation sums, the run's first scan, and the rules' last scan."""
        import json

        entries = self.rpe.entries()
        return {
            "scans": np.array([e[0] for e in entries], np.int64),
            "poses": np.array([e[1] for e in entries], np.float64).reshape(-1, 4, 4),
            "times_path_turned": np.array([e[2:] for e in entries], np.float64).reshape(-1, 3),
            "meta": np.array(json.dumps({"origin": self.origin, "used": self.used, "last_ms": self.last_ms})),
        }

    def restore(self, data: dict[str, np.ndarray]) -> None:
        """Continue from a :meth:`checkpoint`: the same odometry run, its registrations done."""
        import json

        meta = json.loads(str(data["meta"]))
        self.restart(origin=int(meta["origin"]))
        scans = [int(k) for k in data["scans"]]
        tpt = np.asarray(data["times_path_turned"], np.float64)
        self.rpe.restore([(k, data["poses"][i], *tpt[i]) for i, k in enumerate(scans)])
        for i, k in enumerate(scans):
            done: Future = Future()
            done.set_result(None)
            self.futures[k] = done
            self._times[k] = float(tpt[i, 0])
        self.used, self.last_ms = meta["used"], meta["last_ms"]

    def catch_up(self, upto: int, scan_of: Callable[[int], np.ndarray], time_of: Callable[[int], float]) -> None:
        """Submit again the scans after the newest registration a restored checkpoint holds, up
        to ``upto`` (exclusive). In real time the odometry lags the filter: a checkpoint taken after
        step k may have scans up to k submitted but not yet registered, and the continuation must
        register them (from the recorded poses when it has them, else live) before it can read
        them. KISS-ICP registers in order, and a checkpoint keeps only the odometry buffer's last
        scans (not every scan since ``origin``), so nothing before the newest held one is missing."""
        first = max(self.futures) + 1 if self.futures else self.origin
        for k in range(first, upto):
            self.submit(k, scan_of(k), time_of(k))

    def pose_record(self, k: int) -> dict[str, np.ndarray]:
        """Per-step resume fields after scan k: the odometry poses of scans k and k − 1 with their
        path lengths and rotation sums (NaN where not registered yet: in real time scan k's may
        still be in progress, and the next step's record then carries it as its k − 1), the
        odometry run's first scan, and the rules' last odometry scan (−1: none)."""
        out = {"odom_origin": np.int64(self.origin), "odom_used": np.int64(-1 if self.used is None else self.used)}
        held = {j: (pose, path, turned) for j, pose, _, path, turned in self.rpe.entries(last=2)}
        for name, j in (("odom", k), ("odom_prev", k - 1)):
            pose, path, turned = held.get(j, (np.full((4, 4), np.nan), np.nan, np.nan))
            out[f"{name}_pose"] = np.asarray(pose, np.float64)
            out[f"{name}_path_turned"] = np.array([path, turned], np.float64)
        return out

    def submit(self, k: int, scan: np.ndarray, t: float) -> None:
        """Register scan k in the background."""
        self.futures[k] = self._pool.submit(self._add, self.rpe, k, scan, t)
        self._times[k] = float(t)

    def _add(self, rpe, k, scan, t):
        t0 = time.perf_counter()
        process = self.process if rpe.registers(k) else None
        for attempt in range(REGISTRATION_ATTEMPTS):
            try:
                if process is not None and not process.alive:
                    self._revive(rpe, k)
                rpe.add(k, scan, t)
                break
            except WorkerDied as exc:
                if attempt + 1 == REGISTRATION_ATTEMPTS:
                    raise
                self._revive(rpe, k, exc.worker)
        self.last_ms = (time.perf_counter() - t0) * 1000.0

    def keep_from(self, k: int | None) -> None:
        """Keep the odometry of every scan from k on (a match in flight started there and is
        carried forward from it when it lands); None: the most recent scans only."""
        if self.rpe is not None:
            self.rpe.keep_from(k)

    def registered(self, k: int) -> bool:
        """Whether scan k is registered (without waiting)."""
        registration = self.futures.get(k)
        return registration is not None and registration.done()

    def newest_registered(self) -> int | None:
        """The newest scan whose odometry is done (None before the first)."""
        return None if self.rpe is None else self.rpe.latest

    def timestamp(self, k: int) -> float:
        """The timestamp scan k was submitted with."""
        return self._times[k]

    def wait_registered(self, k: int) -> None:
        """Block until scan k is registered (a failed registration raises here)."""
        self._wait(self.futures[k], "RPE", k)

    def registered_within(self, k: int, timeout: float, behind_too: bool = False) -> bool:
        """Whether scan k is registered, waiting up to ``timeout`` seconds for it; no wait at all
        while scan k−1 is still pending (the odometry is behind), unless ``behind_too``."""
        previous = self.futures.get(k - 1)
        behind = not behind_too and previous is not None and not previous.done()  # a backlog: do not wait
        registration = self.futures[k]
        wait_futures([registration], timeout=0.0 if behind else timeout)
        return registration.done()

    def motion(self, k: int) -> tuple[float, float]:
        """Distance driven since the rules' previous scan and the odometry yaw, for the rules.

        Replay: from k−1 to k (waits for the RPE of scan k). Real time: from the previous to the
        newest scan whose odometry is done, without waiting, so the PF of scan k+1 and KISS-ICP's
        registration of scan k overlap instead of taking turns (the rules then lag the odometry by
        a scan at most; the motion is counted once all the same)."""
        planned = self.used_plan.get(k) if self.used_plan is not None else None
        if self.cfg.localize.clock == "realtime" and planned is not None and self.origin <= planned <= k:
            self.wait_registered(planned)
            latest = planned
        elif self.cfg.localize.clock == "realtime":
            latest = None
            for i in range(k, max(self.origin, self.used or 0) - 1, -1):
                fut = self.futures.get(i)
                if fut is not None and fut.done():
                    self._wait(fut, "RPE", i)  # a failed registration surfaces here
                    latest = i
                    break
            if latest is None:
                latest = self.used
                if latest is None:  # nothing registered yet since the (re)start
                    self.wait_registered(k)
                    latest = k
        else:
            self.wait_registered(k)
            latest = k
        for old in [i for i in self.futures if i < k - 200]:
            del self.futures[old]
            self._times.pop(old, None)
        yaw = float(euler_zyx(self.rpe.odom_pose(latest)[:3, :3])[0])
        prev = latest - 1 if self.cfg.localize.clock != "realtime" else self.used
        self.used = latest
        if prev is None or prev < self.origin or prev >= latest:
            return 0.0, yaw
        if prev == latest - 1:
            return float(np.linalg.norm(self.rpe.relative(prev, latest)[:3, 3])), yaw
        return self.rpe.moved_since(prev, latest), yaw

    def last_step(self, k: int) -> tuple[np.ndarray, float] | None:
        """The newest known motion before scan k, for a constant-velocity guess of scan k's:
        (T_{i−1←i}, the pose of scan i in scan i−1's frame, and the seconds between them), for
        the newest registered i < k whose predecessor is registered too; None if there is none
        yet (the first two scans after a (re)start). Never waits: replay uses i = k − 1, which
        the rules' ``motion(k − 1)`` already waited for, so a seed still fixes the result; real
        time takes the newest registration that is done."""
        for i in range(k - 1, self.origin, -1):
            fut = self.futures.get(i)
            if fut is None or not fut.done():
                if self.cfg.localize.clock != "realtime":
                    return None
                continue
            if fut.exception() is not None or not (self.rpe.has(i) and self.rpe.has(i - 1)):
                return None  # a failed registration surfaces where the rules wait for it
            dt = self._times.get(i, math.nan) - self._times.get(i - 1, math.nan)
            if not dt > 0:
                return None
            return self.rpe.relative(i - 1, i), float(dt)
        return None

    def close_process(self) -> None:
        """Close the KISS-ICP child (a busy one is killed: its registration would be thrown away)."""
        if self.process is not None:
            self.process.close()

    def kill_process(self) -> None:
        """Kill the KISS-ICP child at once, without waiting (the process is about to exit)."""
        if self.process is not None:
            self.process.kill()
