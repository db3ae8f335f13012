"""A recorded run as the viewer reads it: its steps (a branch's first steps are its original's),
each step's snapshot, the steps its events happened at, and its per-scan series for the plots.

A run the viewer is still recording grows while it is read: :class:`RecordedRun` re-opens its
recording when a step beyond the last one it knows is asked for (opening reads the small index
and the sizes of the field files: about a millisecond).

A branch records only its own steps (``meta["first_step"]`` on, ``meta["branch_of"]`` naming the
original run and the step it branched after); its steps before that are read from the original,
so a branch scrubs, plots and draws from scan 0 like any run.

A run kept as a rolling window under the recording budget (:mod:`.recorder`) holds its steps
from :attr:`RecordedRun.first_kept` on: a step index stays the run's own step number, the steps
before the window read as "dropped by the recording budget", and the series and events start at
the window (``series()["first"]`` says where).
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from ...core.geometry import transform_points
from ...core.runs import recording
from ...core.snapshot import Snapshot
from .history import MARKED_EVENTS, SERIES, cloud_spread, error_components

#: the events the timeline's previous / next event buttons stop at
TIMELINE_EVENTS = MARKED_EVENTS


class RecordedRun:
    """One run's recording (and, for a branch, the original's steps before it), read on demand.

    ``seq``: the run's sequence, for the scans of scrubbed steps (None: snapshots without scan).
    Thread-safe: the display thread and GUI callbacks read it at once."""

    def __init__(self, path, seq=None, *, live: bool = False):
        self._lock = threading.RLock()
        self.seq = seq
        self.live = live  # still being recorded: re-open when asked for more
        self._rec = recording.open(path)
        self.path: Path = self._rec.run_dir
        self.meta = self._rec.meta
        #: the run's first own step (a branch: the step after its branch point)
        self.start = int(self.meta.get("first_step", 0) or 0)
        self.parent: RecordedRun | None = None
        branch = self.meta.get("branch_of")
        if branch and self.start > 0:
            self.parent = RecordedRun(branch["run"], seq)
        self._snap: tuple[int, Snapshot] | None = None

    # ------------------------------------------------------------------ steps
    @property
    def rec(self) -> recording.Recording:
        """The run's own recording (its steps from ``first_step`` on)."""
        return self._rec

    @property
    def first_step(self) -> int:
        """The step the run's own recording holds first (``start``, unless a rolling window
        dropped the steps before)."""
        return self._rec.first_step

    @property
    def first_kept(self) -> int:
        """The first step that can be read: 0, or the first of a rolling window (the steps before
        were dropped by the recording budget, here or in a branch's original)."""
        if self._rec.dropped > 0:
            return self._rec.first_step
        return self.parent.first_kept if self.parent is not None else self.start

    @property
    def n(self) -> int:
        """Steps known so far, the original's before a branch included (a step index: the run's
        step after the last one recorded)."""
        return self._rec.first_step + self._rec.n

    def refresh(self) -> int:
        """Re-open a recording still being written; returns the steps now known."""
        with self._lock:
            if self.live:
                self._rec = recording.open(self._rec.path)
                self._snap = None
            return self.n

    def dropped(self, i: int) -> recording.RecordingError:
        return recording.RecordingError(
            f"step {i} was dropped by the recording budget (this run keeps a rolling window of steps "
            f"{self.first_kept}…{self.n - 1})"
        )

    def _locate(self, i: int) -> tuple[recording.Recording, int]:
        """(recording, its own row) of step i."""
        if i < 0:
            raise recording.RecordingError(f"step {i} is outside the recording (0…{self.n - 1})")
        if i >= self.n:
            self.refresh()
        if i < self.first_kept:
            raise self.dropped(i)
        if i < self.start and self.parent is not None:
            return self.parent._locate(i)
        return self._rec, i - self._rec.first_step

    def snapshot(self, i: int) -> Snapshot:
        """Step i with its scan recomputed from the source (a ray-cast or a file read and the
        filter's voxel subsample: the slow part, tens of milliseconds, done outside the lock)."""
        with self._lock:  # what it reads of the recording (the window may move meanwhile)
            rec, j = self._locate(i)
            snap = rec.snapshot(j, None)
            if self.seq is None:
                return snap
            rec.field("scan_voxel")  # read now: the scan below needs it
        scan = transform_points(snap.mean_pose, rec.prepared_scan(j, self.seq)).astype(np.float32)
        return dataclasses.replace(snap, scan_world=scan)

    def figures(self, i: int) -> Snapshot:
        """Step i without its scan: particles, estimate, S2M match, status figures (a few ms; the
        last one asked for is kept, so a redraw reads nothing)."""
        with self._lock:
            if self._snap is not None and self._snap[0] == i:
                return self._snap[1]
            rec, j = self._locate(i)
            snap = rec.snapshot(j, None)
            self._snap = (i, snap)
            return snap

    def scan_of(self, i: int) -> int:
        with self._lock:
            rec, j = self._locate(i)
            return int(rec.scan_index[j])

    # ------------------------------------------------------------------ events
    def events(self) -> list[tuple[int, object]]:
        """(step, Event) of every event of the run, the original's before a branch included."""
        with self._lock:
            if self.live:  # a button asks: the events up to the newest recorded step
                self.refresh()
            rec = self._rec
            if rec.dropped > 0:  # a rolling window: its events only (-1: after the last dropped step)
                return [(rec.first_step + s, e) for s, e in rec.events]
            own = [(self.start + s if s >= 0 else s, e) for s, e in rec.events]
            if self.parent is None:
                return own
            before = [(s, e) for s, e in self.parent.events() if s < self.start]
            return before + [(s, e) for s, e in own if s >= 0]

    def event_steps(self, kinds=TIMELINE_EVENTS) -> np.ndarray:
        """Sorted steps at which an event of ``kinds`` happened (an event before the first scan
        counts at step 0, one before a rolling window at its first step)."""
        first = self.first_kept
        steps = {max(s, first) for s, e in self.events() if e.kind in kinds}
        return np.array(sorted(steps), np.int64)

    # ------------------------------------------------------------------ series
    def columns(self, upto: int | None = None) -> dict:
        """``error``, ``localized`` and ``pf_ms`` of steps ``first`` … ``upto`` − 1 (default: all;
        ``first``: 0, or a rolling window's first step; the original's before a branch): what the
        Compare table reads, a few fields, no particles."""
        with self._lock:
            n = self.n if upto is None else min(int(upto), self.n)
            rec = self._rec
            own_n = max(n - rec.first_step, 0)
            own = {
                "error": rec.field("error_m", rec.n)[:own_n].astype(float),
                "localized": rec.field("localized", rec.n)[:own_n].astype(bool),
                "pf_ms": rec.field("pf_ms", rec.n)[:own_n].astype(float),
            }
            if self.parent is None or rec.first_step == 0 or rec.dropped > 0:
                return {**own, "first": rec.first_step}
            head = self.parent.columns(min(n, self.start))
            return {**{k: np.concatenate([head[k], own[k]]) for k in own}, "first": head["first"]}

    def series(self, upto: int | None = None) -> dict:
        """The per-scan figures of steps ``first`` … ``upto`` − 1 (default: all; ``first``: 0, or a
        rolling window's first step), keyed as :meth:`History.arrays` (plus ``est``/``gt``
        positions, ``step`` and ``first``), for the plots and trajectories."""
        with self._lock:
            n = self.n if upto is None else min(int(upto), self.n)
            rec = self._rec
            if self.parent is not None and self.start > 0 and rec.dropped == 0:
                head = self.parent.series(min(n, self.start))
                own = _series(rec, max(n - self.start, 0), self.start, s2m_before=_last_finite(head["s2m_ms"]))
                out = {
                    k: (np.concatenate([head[k], own[k]]) if isinstance(own[k], np.ndarray) else head[k] + own[k])
                    for k in own
                }
                out["marks"] = head["marks"] + own["marks"]
                out["first"] = head["first"]
                return out
            out = _series(rec, max(n - rec.first_step, 0), rec.first_step)
            out["first"] = rec.first_step
            return out


def _last_finite(a: np.ndarray) -> float:
    f = a[np.isfinite(a)]
    return float(f[-1]) if f.size else np.nan


def _series(rec: recording.Recording, n: int, offset: int, s2m_before: float = np.nan) -> dict:
    """:meth:`RecordedRun.series` of one recording's first ``n`` steps (global steps from ``offset``)."""
    out: dict = {"step": np.arange(offset, offset + n, dtype=np.int64)}
    if n == 0:
        out.update(
            {
                "scan": np.zeros(0, np.int64),
                "est": np.zeros((0, 3), np.float32),
                "gt": np.zeros((0, 3), np.float32),
                "localized": np.zeros(0, bool),
                "marks": [],
            }
        )
        out.update({name: np.zeros(0) for name in SERIES})
        return out
    scan = rec.field("scan_index", rec.n)[:n]
    std = rec.field("std_xyz", rec.n)[:n]
    pose = rec.field("mean_pose", rec.n)[:n]
    gt = rec.field("gt_pose", rec.n)[:n]
    out["scan"] = scan.astype(np.int64)
    out["std"] = np.maximum(std[:, 0], std[:, 1])
    out["spread"] = np.array([cloud_spread(rec.particles(i)) for i in range(n)])
    out["error"] = rec.field("error_m", rec.n)[:n].astype(float)
    comps = np.full((n, 4), np.nan)
    known = np.isfinite(gt).all(axis=(1, 2))
    for i in np.flatnonzero(known):
        comps[i] = error_components(pose[i], gt[i])
    out["along"], out["cross"], out["vertical"], out["heading"] = comps.T
    n_part = rec.field("n_particles", rec.n)[:n].astype(float)
    out["n_eff_share"] = rec.field("n_eff", rec.n)[:n] / np.maximum(n_part, 1)
    out["pf_ms"] = rec.field("pf_ms", rec.n)[:n].astype(float)
    out["rpe_ms"] = rec.field("rpe_ms", rec.n)[:n].astype(float)
    # the last landed match's time, held between landings (as the live history plots it)
    s2m = rec.field("s2m_ms", rec.n)[:n].astype(float)
    held = np.where(np.isfinite(s2m), s2m, np.nan)
    idx = np.where(np.isfinite(held), np.arange(n), -1)
    np.maximum.accumulate(idx, out=idx)
    first = 0.0 if not np.isfinite(s2m_before) else s2m_before
    out["s2m_ms"] = np.where(idx >= 0, held[np.maximum(idx, 0)], first)
    out["localized"] = rec.field("localized", rec.n)[:n].astype(bool)
    out["est"] = pose[:, :3, 3].astype(np.float32)
    out["gt"] = np.where(known[:, None], gt[:, :3, 3], np.nan).astype(np.float32)
    out["marks"] = [(int(e.scan), e.kind) for s, e in rec.events if s < n and e.kind in MARKED_EVENTS]
    return out


def reopened(run: RecordedRun) -> RecordedRun:
    """The original run as it now stands (it stopped growing when the branch took over)."""
    run.refresh()
    run.live = False
    return run


def open_branch_at(run: RecordedRun, step: int, overrides: dict, cache_root):
    """A localizer in ``run``'s exact state after ``step``, ``overrides`` (live parameters, SI)
    applied (:func:`lidarloc.core.runs.branch.open_branch`)."""
    try:
        from ...core.runs.branch import open_branch
    except ImportError:
        raise LidarlocError(
            "branching is not available in this installation (lidarloc.core.runs.branch missing)"
        ) from None
    with run._lock:
        rec, j = run._locate(step)
    return open_branch(rec, j + rec.dropped, overrides=overrides or None, seq=run.seq, cache_root=cache_root)
