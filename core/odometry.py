"""The RPE block as the localizer drives it: every scan is registered by KISS-ICP on the RPE
thread as soon as it is read, overlapping the PF's work on it, and the localizer's rules and the
S2M landing read the odometry of the scans registered so far.

KISS-ICP holds the GIL while it registers a scan, so by default it runs in a child process
(:mod:`lidarloc.core.rpe_worker`), one per localizer, reset instead of restarted. With recorded
odometry (``localize.recorded_odometry``) no ICP runs at all: the poses come from the cache.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from typing import Any, Callable

import numpy as np

from .config import Config
from .geometry import euler_zyx
from .rpe import RelativePoseEstimator
from .rpe_worker import KissICPProcess


class OdometryFeed:
    """One odometry run at a time (``restart``), fed scan by scan (``submit``) on ``pool``.

    ``wait(future, block, k)`` is the localizer's wait for a block: it gives up on
    ``interrupt()`` and turns a failed registration into a clear error."""

    def __init__(self, cfg: Config, recorded: np.ndarray | None, pool: ThreadPoolExecutor,
                 wait: Callable[[Future, str, int], Any]):
        self.cfg = cfg
        self._recorded = recorded
        self._pool = pool
        self._wait = wait
        self.process: KissICPProcess | None = None    # the KISS-ICP child, once started
        self.rpe: RelativePoseEstimator | None = None
        self.futures: dict[int, Future] = {}          # registrations by scan
        self._times: dict[int, float] = {}            # timestamps of the submitted scans
        self.origin = 0                 # first scan the current KISS-ICP run has seen
        self.used: int | None = None    # last odometry scan the rules consumed (real time)
        self.last_ms: float | None = None   # wall time of the newest finished registration

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
        self.rpe = self._new_rpe()
        self.futures.clear()
        self._times.clear()
        self.origin = origin
        self.used = None
        self.last_ms = None

    def _new_rpe(self) -> RelativePoseEstimator:
        if self._recorded is not None:
            return RelativePoseEstimator(recorded=self._recorded)
        if not self.cfg.localize.rpe_process:
            return RelativePoseEstimator()
        if self.process is None:
            self.process = KissICPProcess()
        else:
            self.process.reset()
        return RelativePoseEstimator(icp=self.process)

    def submit(self, k: int, scan: np.ndarray, t: float) -> None:
        """Register scan k in the background."""
        self.futures[k] = self._pool.submit(self._add, self.rpe, k, scan, t)
        self._times[k] = float(t)

    def _add(self, rpe, k, scan, t):
        t0 = time.perf_counter()
        rpe.add(k, scan, t)
        self.last_ms = (time.perf_counter() - t0) * 1000.0

    def wait_registered(self, k: int) -> None:
        """Block until scan k is registered (a failed registration raises here)."""
        self._wait(self.futures[k], "RPE", k)

    def registered_within(self, k: int, timeout: float) -> bool:
        """Whether scan k is registered, waiting up to ``timeout`` seconds for it; no wait at all
        while scan k−1 is still pending (the odometry is behind)."""
        previous = self.futures.get(k - 1)
        behind = previous is not None and not previous.done()   # a backlog: do not wait
        registration = self.futures[k]
        wait_futures([registration], timeout=0.0 if behind else timeout)
        return registration.done()

    def motion(self, k: int) -> tuple[float, float]:
        """Distance driven since the rules' previous scan and the odometry yaw, for the rules.

        Replay: from k−1 to k (waits for the RPE of scan k). Real time: from the previous to the
        newest scan whose odometry is done, without waiting, so the PF of scan k+1 and KISS-ICP's
        registration of scan k overlap instead of taking turns (the rules then lag the odometry by
        a scan at most; the motion is counted once all the same)."""
        if self.cfg.localize.clock == "realtime":
            latest = None
            for i in range(k, max(self.origin, self.used or 0) - 1, -1):
                fut = self.futures.get(i)
                if fut is not None and fut.done():
                    self._wait(fut, "RPE", i)     # a failed registration surfaces here
                    latest = i
                    break
            if latest is None:
                latest = self.used
                if latest is None:            # nothing registered yet since the (re)start
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
                return None          # a failed registration surfaces where the rules wait for it
            dt = self._times.get(i, math.nan) - self._times.get(i - 1, math.nan)
            if not dt > 0:
                return None
            return self.rpe.relative(i - 1, i), float(dt)
        return None

    def close_process(self) -> None:
        """Close the KISS-ICP child (a busy one is killed: its registration would be thrown away)."""
        if self.process is not None:
            self.process.close()
