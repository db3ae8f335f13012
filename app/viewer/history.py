"""The per-scan figures of the current run, kept for the plots, the trajectories and the list of
recent events."""

from __future__ import annotations

import threading

import numpy as np

from lidarloc.core.snapshot import Event, Snapshot

from .style import EVENTS_SHOWN


class History:
    """Per-scan values of the current run (cleared on restart), written by the player thread and
    read by the display thread; appends and whole-array reads happen under one short lock."""

    def __init__(self, capacity: int = 1024):
        self._lock = threading.Lock()
        self.epoch = 0
        self._cap = capacity
        self._alloc(capacity)
        self.events: list[Event] = []
        self.version = 0

    def _alloc(self, cap: int) -> None:
        self.n = 0
        self.scan = np.zeros(cap, np.int64)
        self.std = np.zeros(cap)            # max(std_x, std_y), m
        self.error = np.full(cap, np.nan)   # m, NaN without ground truth
        self.pf_ms = np.zeros(cap)
        self.s2m_ms = np.zeros(cap)         # wall time of the last landed match (held between landings)
        self.est = np.zeros((cap, 3), np.float32)
        self.gt = np.full((cap, 3), np.nan, np.float32)
        self._last_s2m = None

    def _grow(self) -> None:
        cap = 2 * len(self.scan)
        for name in ("scan", "std", "error", "pf_ms", "s2m_ms", "est", "gt"):
            old = getattr(self, name)
            new = np.full((cap,) + old.shape[1:], np.nan if name in ("error", "gt") else 0, old.dtype)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)

    def clear(self) -> None:
        with self._lock:
            self.epoch += 1
            self._alloc(self._cap)
            self.events = []
            self.version += 1

    def record(self, snap: Snapshot) -> None:
        with self._lock:
            k = snap.scan_index
            if self.n and (k < self.scan[self.n - 1] or k < 0):
                # the scan index went back: a restart; the old run's curves end here
                self.epoch += 1
                self._alloc(self._cap)
                self.events = []
            self._merge_events(snap.events)
            if k >= 0:
                if self.n and self.scan[self.n - 1] == k:
                    i = self.n - 1          # same scan again (e.g. the snapshot after a reset)
                else:
                    if self.n == len(self.scan):
                        self._grow()
                    i = self.n
                    self.n += 1
                self.scan[i] = k
                std = np.asarray(snap.std_xyz, float)
                self.std[i] = float(max(std[0], std[1]))
                self.error[i] = np.nan if snap.error_m is None else float(snap.error_m)
                self.pf_ms[i] = float(snap.pf_ms)
                if snap.s2m is not None:
                    self._last_s2m = snap.s2m
                self.s2m_ms[i] = 0.0 if self._last_s2m is None else float(self._last_s2m.ms)
                self.est[i] = np.asarray(snap.mean_pose)[:3, 3]
                if snap.gt_pose is not None:
                    self.gt[i] = np.asarray(snap.gt_pose)[:3, 3]
            self.version += 1

    def _merge_events(self, events: tuple) -> None:
        """Snapshots carry a rolling window of recent events; append only the ones not seen yet
        (the longest prefix of the window that equals the tail of what we have is old)."""
        events = tuple(events)
        if not events:
            return
        mine = self.events[-len(events):]
        for overlap in range(min(len(mine), len(events)), -1, -1):
            if overlap == 0 or tuple(mine[-overlap:]) == events[:overlap]:
                break
        self.events.extend(events[overlap:])
        del self.events[:-200]

    def arrays(self) -> dict:
        with self._lock:
            n = self.n
            return {"epoch": self.epoch, "version": self.version, "scan": self.scan[:n].copy(),
                    "std": self.std[:n].copy(), "error": self.error[:n].copy(), "pf_ms": self.pf_ms[:n].copy(),
                    "s2m_ms": self.s2m_ms[:n].copy(), "events": list(self.events[-EVENTS_SHOWN:])}

    def recent_events(self) -> list[Event]:
        with self._lock:
            return list(self.events[-EVENTS_SHOWN:])

    def trajectories(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            n = self.n
            return self.epoch, self.scan[:n].copy(), self.est[:n].copy(), self.gt[:n].copy()

