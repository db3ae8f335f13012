"""The per-scan figures of the current run, kept for the plots, the trajectories and the list of
recent events."""

from __future__ import annotations

import math
import threading

import numpy as np

from ...core.snapshot import Event, Snapshot
from .style import EVENTS_SHOWN

#: per-scan float series (NaN where unknown: no ground truth, no KISS-ICP time yet)
SERIES = ("std", "spread", "error", "along", "cross", "vertical", "heading", "n_eff_share", "pf_ms", "rpe_ms", "s2m_ms")
#: the events the plots mark on the scan axis
MARKED_EVENTS = (
    "localized",
    "false_fire",
    "false_positive",
    "loss",
    "unconfirmed",
    "relocalized",
    "reset",
    "kidnap",
    "s2m_accepted",
    "s2m_rejected",
)


def cloud_spread(particles: np.ndarray) -> float:
    """The particle cloud's own spread: max of the unweighted x and y standard deviations (m). With
    collapsed weights the weighted std reads ~0 while the cloud is still spread out."""
    P = np.asarray(particles)
    if len(P) < 2:
        return 0.0
    return float(np.max(P[:, :2].std(axis=0)))


def error_components(mean_pose: np.ndarray, gt_pose: np.ndarray) -> tuple[float, float, float, float]:
    """(along-track, cross-track, vertical, heading) error of the estimate against the truth: the
    position error in the truth's heading frame (m; along = ahead of the truth is positive, cross
    = to its left) and the yaw error wrapped to (−π, π] (rad)."""
    T, G = np.asarray(mean_pose, float), np.asarray(gt_pose, float)
    e = T[:3, 3] - G[:3, 3]
    psi = math.atan2(G[1, 0], G[0, 0])
    c, s = math.cos(psi), math.sin(psi)
    yaw = math.atan2(T[1, 0], T[0, 0])
    d = (yaw - psi + math.pi) % (2 * math.pi) - math.pi
    return float(c * e[0] + s * e[1]), float(-s * e[0] + c * e[1]), float(e[2]), float(d)


class History:
    """Per-scan values of the current run (cleared on restart), written by the player thread and
    read by the display thread; appends and whole-array reads happen under one short lock."""

    def __init__(self, capacity: int = 1024):
        self._lock = threading.Lock()
        self.epoch = 0
        self._cap = capacity
        self._alloc(capacity)
        self.events: list[Event] = []
        self.marks: list[tuple[int, str]] = []  # (scan, kind) of every marked event of the run
        self.version = 0

    def _alloc(self, cap: int) -> None:
        self.n = 0
        self.first_step = 0  # the run's step of row 0 (a recorded rolling window's first)
        self.scan = np.zeros(cap, np.int64)
        # std: max(std_x, std_y) weighted (m); spread: the cloud's unweighted one; error: |est − truth|
        # (m); along/cross/vertical (m), heading (rad): see error_components; s2m_ms: the last landed
        # match's wall time, held between landings
        for name in SERIES:
            setattr(self, name, np.full(cap, np.nan))
        self.est = np.zeros((cap, 3), np.float32)
        self.gt = np.full((cap, 3), np.nan, np.float32)
        self._last_s2m = None

    def _grow(self) -> None:
        cap = 2 * len(self.scan)
        for name in ("scan", "est", "gt") + SERIES:
            old = getattr(self, name)
            fill = 0 if name in ("scan", "est") else np.nan
            new = np.full((cap,) + old.shape[1:], fill, old.dtype)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)

    def _restart(self) -> None:
        self.epoch += 1
        self._alloc(self._cap)
        self.events = []
        self.marks = []

    def clear(self) -> None:
        with self._lock:
            self._restart()
            self.version += 1

    def record(self, snap: Snapshot) -> None:
        with self._lock:
            k = snap.scan_index
            if self.n and (k < self.scan[self.n - 1] or k < 0):
                # the scan index went back: a restart; the old run's curves end here
                self._restart()
            self._merge_events(snap.events)
            if k >= 0:
                if self.n and self.scan[self.n - 1] == k:
                    i = self.n - 1  # same scan again (e.g. the snapshot after a reset)
                else:
                    if self.n == len(self.scan):
                        self._grow()
                    i = self.n
                    self.n += 1
                self._fill(i, snap)
            self.version += 1

    def load(self, series: dict, events: list | None = None) -> None:
        """Start over with the figures of a recorded run (``RecordedRun.series``) and its events
        (``[(step, Event), …]``): scrubbing, a branch's steps before it, ``view --run``."""
        with self._lock:
            self._restart()
            n = len(series["scan"])
            while len(self.scan) < n:
                self._grow()
            self.n = n
            self.scan[:n] = series["scan"]
            for name in SERIES:
                getattr(self, name)[:n] = series[name]
            self.est[:n] = series["est"]
            self.gt[:n] = series["gt"]
            self.marks = list(series["marks"])
            self.events = [e for _, e in (events or [])][-200:]
            self.first_step = int(series.get("first", 0))
            self.version += 1

    def _fill(self, i: int, snap: Snapshot) -> None:
        self.scan[i] = snap.scan_index
        std = np.asarray(snap.std_xyz, float)
        self.std[i] = float(max(std[0], std[1]))
        self.spread[i] = cloud_spread(snap.particles)
        self.error[i] = np.nan if snap.error_m is None else float(snap.error_m)
        if snap.gt_pose is not None:
            self.along[i], self.cross[i], self.vertical[i], self.heading[i] = error_components(
                snap.mean_pose, snap.gt_pose
            )
            self.gt[i] = np.asarray(snap.gt_pose)[:3, 3]
        self.n_eff_share[i] = snap.n_eff_share
        self.pf_ms[i] = float(snap.pf_ms)
        self.rpe_ms[i] = np.nan if snap.rpe_ms is None else float(snap.rpe_ms)
        if snap.s2m is not None:
            self._last_s2m = snap.s2m
        self.s2m_ms[i] = 0.0 if self._last_s2m is None else float(self._last_s2m.ms)
        self.est[i] = np.asarray(snap.mean_pose)[:3, 3]

    def _merge_events(self, events: tuple) -> None:
        """Snapshots carry a rolling window of recent events; append only the ones not seen yet
        (the longest prefix of the window that equals the tail of what we have is old)."""
        events = tuple(events)
        if not events:
            return
        mine = self.events[-len(events) :]
        for overlap in range(min(len(mine), len(events)), -1, -1):
            if overlap == 0 or tuple(mine[-overlap:]) == events[:overlap]:
                break
        new = events[overlap:]
        self.events.extend(new)
        self.marks.extend((e.scan, e.kind) for e in new if e.kind in MARKED_EVENTS)
        del self.events[:-200]

    def arrays(self) -> dict:
        with self._lock:
            n = self.n
            out = {
                "epoch": self.epoch,
                "version": self.version,
                "scan": self.scan[:n].copy(),
                "events": list(self.events[-EVENTS_SHOWN:]),
                "marks": list(self.marks),
            }
            for name in SERIES:
                out[name] = getattr(self, name)[:n].copy()
            return out

    def recent_events(self) -> list[Event]:
        with self._lock:
            return list(self.events[-EVENTS_SHOWN:])

    def trajectories(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            n = self.n
            return self.epoch, self.scan[:n].copy(), self.est[:n].copy(), self.gt[:n].copy()
