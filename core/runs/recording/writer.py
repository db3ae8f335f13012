"""Writing a recording (see :mod:`.format`): the localizer's thread gathers copies of a step, a
thread of the writer's own appends them to disk in order and commits them. A run kept under a
size budget goes on in segments (:meth:`RecordingWriter.next_segment`, :mod:`.segments`)."""

from __future__ import annotations

import builtins
import dataclasses
import datetime as _dt
import json
import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from ...snapshot import S2MView, Snapshot
from .format import (
    COMPRESS_ABOVE_BYTES,
    FIELDS,
    FOLDER,
    FORMAT,
    INDEX,
    LOG_WEIGHTS,
    PARTICLES,
    QUEUE_STEPS,
    S2M_STATUSES,
    STEPS,
    VERSION,
    RecordingError,
    ResumePayload,
    nan_or_value,
    save_s2m,
    write_json_atomic,
)
from .segments import CARRIED, folder_bytes, segment_folder


class RecordingWriter:
    """Appends a localizer's steps to ``run_dir/recording/`` (see the module docstring).

    Call :meth:`on_scan` after every successful ``Localizer.step()`` (on the stepping thread) and
    :meth:`close` at the end. One writer records one run from one (re)start: a restarted localizer
    gets a new writer.

    ``on_scan`` only gathers copies of the step; a thread of the writer's own writes them, in
    order, and commits each step once all of it is on disk. :attr:`committed` counts those (what
    a reader sees), :meth:`flush` waits for the rest, :meth:`close` writes what is queued. A
    failure to write is raised by the next ``on_scan``, ``flush`` or ``close``."""

    def __init__(
        self, run_dir, spec, cfg, seq, preset: str | None = None, branch_of: dict | None = None, first_step: int = 0
    ):
        from ...version import VERSION as version

        meta = {
            "source": spec.to_dict(absolute=True),
            "source_description": spec.describe(),
            "config": cfg.to_dict(),
            "seed": int(cfg.seed),
            "sequence": getattr(seq, "name", "sequence"),
            "n_source_scans": int(len(seq)),
            "clock": cfg.localize.clock,
            "preset": preset,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "branch_of": branch_of,
            "first_step": int(first_step),
            "lidarloc_version": version,
        }
        self._open(Path(run_dir) / FOLDER, meta, None)

    def _open(self, path: Path, meta: dict, top: Path | None) -> None:
        """Start writing the recording folder ``path`` (``top``: the run's first segment's folder,
        None: ``path`` is it)."""
        self.path = path
        self.top = path if top is None else top
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            if (self.path / STEPS).exists():
                raise RecordingError(f"{self.path}: a recording is already there; choose another --out")
            (self.path / "s2m").mkdir(exist_ok=True)
            (self.path / "resume").mkdir(exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot write the recording ({exc.strerror or exc})") from None
        self.meta = meta
        self.fields: dict[str, dict] = {}
        self._files: dict[str, Any] = {}
        for name, (dtype, shape) in FIELDS.items():
            self._declare(name, dtype, shape, 0)
        self._declare(PARTICLES[0], PARTICLES[1], PARTICLES[2], 0)
        self._declare(LOG_WEIGHTS[0], LOG_WEIGHTS[1], LOG_WEIGHTS[2], 0)
        self._write_index()
        self._events = builtins.open(self.path / "events.jsonl", "a", encoding="utf-8")
        self._steps = builtins.open(self.path / STEPS, "ab")
        self.n = 0
        self._particle_row = 0
        self._n_events = 0
        self._events_base = 0  # the first of loc.events this run records (a branch: after the original's)
        self._last_steps: int | None = None
        self._last_scan: int | None = None
        self._last_s2m = None
        self.closed = False
        # The disk work is done on a thread of its own, so that a step costs the filter only the
        # copies it hands over; ``committed`` counts the steps on disk (what a reader sees).
        self.committed = 0
        self.writer_cpu_s = 0.0  # the writing thread's CPU time
        # bytes: what is on disk (counted by the writing thread) and, for the steps handed over but
        # not written yet, their uncompressed size (each counter has one writer thread)
        self._base_bytes = folder_bytes(self.path)
        self._written_bytes = 0
        self._handed_estimate = 0
        self._written_estimate = 0
        self._error: RecordingError | None = None
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_STEPS)
        self._committed_changed = threading.Condition()
        self._thread = threading.Thread(target=self._drain, name="lidarloc-recording", daemon=True)
        self._thread.start()

    @property
    def first_step(self) -> int:
        """The run's step this writer's first row is."""
        return int(self.meta["first_step"])

    @property
    def bytes(self) -> int:
        """This folder's size on disk once every step handed over is written (an upper bound: the
        steps still queued count uncompressed)."""
        return self._base_bytes + self._written_bytes + max(self._handed_estimate - self._written_estimate, 0)

    def next_segment(self) -> RecordingWriter:
        """Close this writer and return one that records the same run's next steps into a segment
        of its own (:mod:`.segments`): a recording of the same format starting at the run's step
        after this one's last, with the events, last scan and S2M view carried over. Its first step
        gets a checkpoint: the localizer checkpoints a recording's row 0 and every
        ``CHECKPOINT_EVERY``-th row after it. Raises the
        writing thread's failure, if it had one (the run's recording then ends here)."""
        self.close(None)
        meta = {k: v for k, v in self.meta.items() if k not in ("summary", "closed")}
        meta["first_step"] = self.first_step + self.n
        meta["segment"] = {"events_before": self._n_events - self._events_base}
        nxt = RecordingWriter.__new__(RecordingWriter)
        nxt._open(segment_folder(self.top, meta["first_step"]), meta, self.top)
        nxt._n_events, nxt._events_base = self._n_events, self._events_base
        nxt._last_scan, nxt._last_steps, nxt._last_s2m = self._last_scan, self._last_steps, self._last_s2m
        if self._last_s2m is not None:  # what the segment's first steps show, until a match lands in it
            try:
                save_s2m(nxt.path / "s2m", CARRIED, self._last_s2m)
            except OSError as exc:
                nxt.close(None)
                raise RecordingError(f"{nxt.path}: cannot write the recording ({exc.strerror or exc})") from None
            nxt._base_bytes = folder_bytes(nxt.path)
        return nxt

    def continue_from(self, loc) -> None:
        """A branch's writer: the events up to ``loc.recorded_events_base``, the last scan and the
        last S2M view ``loc`` already has are the recorded run's; record only what follows."""
        self._n_events = self._events_base = int(loc.recorded_events_base)
        self._last_scan = int(loc.snapshot().scan_index)
        self._last_s2m = loc.s2m.last
        self._last_steps = int(loc.steps)

    def _declare(self, name: str, dtype: str, shape: tuple, first_step: int) -> None:
        self.fields[name] = {"dtype": dtype, "shape": list(shape), "first_step": int(first_step)}
        self._files[name] = builtins.open(self.path / f"{name}.bin", "ab")

    def _write_index(self) -> None:
        write_json_atomic(
            self.path / INDEX, {"format": FORMAT, "version": VERSION, "meta": self.meta, "fields": self.fields}
        )

    def on_scan(self, loc, snap: Snapshot) -> None:
        """Append the step ``snap`` is the snapshot of (``loc`` just produced it; call it before
        the next control changes ``loc``). What the step needs is gathered here, as copies; the
        writing thread puts it on disk. Raises the writing thread's failure, if it had one."""
        if self.closed:
            raise RecordingError(f"{self.path}: the recording is closed")
        if self._error is not None:
            raise self._error
        steps = int(getattr(loc, "steps", self.n + 1))
        if snap.scan_index < 0 or (self._last_steps is not None and steps <= self._last_steps):
            raise RecordingError("recording: this snapshot is not a new step (a restarted run needs a new recording)")
        i = self.n
        record = loc.records[-1] if getattr(loc, "records", None) else None
        n = len(snap.particles)
        lw = snap.log_weights if snap.log_weights is not None else np.log(np.maximum(snap.weights, 1e-300))
        values = {
            "scan_index": snap.scan_index,
            "timestamp": snap.timestamp,
            "mean_pose": snap.mean_pose,
            "cov_xyz": snap.cov_xyz,
            "std_xyz": snap.std_xyz,
            "ellipse_xy": np.asarray(snap.ellipse_xy, float),
            "n_eff": snap.n_eff,
            "n_particles": snap.n_particles if snap.n_particles else n,
            "best_index": snap.best_index,
            "localized": snap.localized,
            "localized_since": -1 if snap.localized_since is None else snap.localized_since,
            "converged": snap.converged,
            "error_m": nan_or_value(snap.error_m),
            "gt_pose": np.full((4, 4), np.nan) if snap.gt_pose is None else snap.gt_pose,
            "pf_ms": snap.pf_ms,
            "rpe_ms": nan_or_value(snap.rpe_ms),
            "s2m_ms": nan_or_value(record.s2m_ms if record is not None else None),
            "reinit": bool(record.reinit) if record is not None else False,
            "inlier_share": nan_or_value(snap.inlier_share),
            "mean_residual_m": nan_or_value(snap.mean_residual_m),
            "inside_2sigma": -1 if snap.inside_2sigma is None else int(bool(snap.inside_2sigma)),
            "scan_voxel": float(loc.cfg.pf.scan_voxel),
            "s2m_running": snap.s2m_running,
            "s2m_pending": snap.s2m_pending,
            "s2m_acceptance": snap.s2m_acceptance,
            "done": snap.done,
            "particle_rows": (self._particle_row, n),
            "awaiting_confirmation": snap.awaiting_confirmation,
            "confirmed_at": -1 if snap.confirmed_at is None else snap.confirmed_at,
            "s2m_status": S2M_STATUSES.index(snap.s2m_status) if snap.s2m_status in S2M_STATUSES else 0,
        }
        rows = {name: self._row(name, value) for name, value in values.items()}
        payload = loc.resume_payload(i) if hasattr(loc, "resume_payload") else None
        if payload is not None:  # the next step must not change what this one hands over
            payload = ResumePayload(
                per_step={k: np.array(v) for k, v in payload.per_step.items()},
                files={k: dict(v) for k, v in payload.files.items()},
            )
        s2m = snap.s2m if snap.s2m is not None and snap.s2m is not self._last_s2m else None
        item = _Step(
            i,
            np.array(snap.particles, np.float32),
            np.array(lw, np.float32),
            rows,
            self._event_lines(loc, i, snap.scan_index),
            s2m,
            payload,
        )
        item.estimate = item.size_estimate()
        self._handed_estimate += item.estimate
        self._queue.put(item)  # blocks while the writing thread is QUEUE_STEPS steps behind
        self._particle_row += n
        self._last_s2m = snap.s2m
        self.n += 1
        self._last_steps = steps
        self._last_scan = snap.scan_index

    def _row(self, name: str, value) -> bytes:
        info = self.fields[name]
        arr = np.asarray(value, dtype=np.dtype(info["dtype"]))
        if list(arr.shape) != info["shape"]:
            raise RecordingError(f"recording field {name}: shape {arr.shape}, expected {tuple(info['shape'])}")
        return arr.tobytes()

    def _event_lines(self, loc, i: int, scan: int) -> list[str]:
        events = getattr(loc, "events", [])
        lines = []
        for ev in events[self._n_events :]:
            # an event from before the first scan (scan -1), or from a control between the previous
            # step and this one (a kidnap or reset names the previous scan), belongs to that step
            if ev.scan < 0:
                step = -1
            elif self._last_scan is not None and ev.scan == self._last_scan and ev.scan != scan:
                step = i - 1
            else:
                step = i
            lines.append(json.dumps({"step": step, "scan": int(ev.scan), "kind": ev.kind, "detail": ev.detail}) + "\n")
        self._n_events = len(events)
        return lines

    # ------------------------------------------------------------------------ the writing thread
    def _drain(self) -> None:
        """The writing thread: take the steps handed over, in order; write each, flush once for
        all of those that were waiting, then commit them (their rows in ``steps.bin``)."""
        while True:
            batch = [self._queue.get()]
            while batch[-1] is not None:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            items = [b for b in batch if b is not None]
            t0 = time.thread_time()
            if items and self._error is None:
                try:
                    for item in items:
                        self._write_step(item)
                    for f in self._files.values():
                        f.flush()
                    self._events.flush()
                    self._steps.write(np.asarray([item.index for item in items], np.int64).tobytes())
                    self._steps.flush()  # the commit: the steps exist from here on
                except Exception as exc:  # whatever it is, the thread lives on (a step waiting for it must not hang)
                    why = (
                        exc.strerror if isinstance(exc, OSError) and exc.strerror else (str(exc) or type(exc).__name__)
                    )
                    self._error = RecordingError(f"{self.path}: cannot write the recording ({why})")
            self.writer_cpu_s += time.thread_time() - t0
            with self._committed_changed:
                if self._error is None:
                    self.committed += len(items)
                self._committed_changed.notify_all()
            if batch[-1] is None:
                return

    def _write_step(self, item: _Step) -> None:
        self._files["particles"].write(item.particles.tobytes())
        self._files["log_weights"].write(item.log_weights.tobytes())
        size = item.particles.nbytes + item.log_weights.nbytes
        for name, row in item.rows.items():
            self._files[name].write(row)
            size += len(row)
        for line in item.event_lines:
            self._events.write(line)
            size += len(line.encode("utf-8"))
        if item.s2m is not None:
            save_s2m(self.path / "s2m", item.index, item.s2m)
            size += sum(_size(self.path / "s2m" / f"{item.index:06d}{ext}") for ext in (".json", ".f16"))
        if item.payload is not None:
            size += self._write_payload(item.index, item.payload)
        self._written_bytes += size
        self._written_estimate += item.estimate

    def _write_payload(self, i: int, payload: ResumePayload) -> int:
        """Write a step's resume payload; returns its bytes on disk."""
        new_field = False
        size = 0
        for name, value in payload.per_step.items():
            arr = np.asarray(value)
            if name not in self.fields:
                if name in FIELDS or name in (PARTICLES[0], LOG_WEIGHTS[0]):
                    raise RecordingError(f"resume field {name} clashes with a display field")
                self._declare(name, arr.dtype.newbyteorder("<").str, arr.shape, i)
                new_field = True
            row = self._row(name, arr)
            self._files[name].write(row)
            size += len(row)
        for name, arrays in payload.files.items():
            # a checkpoint (~0.1 MB at 1000 particles) compresses ~10×; a small file is not worth the time
            big = sum(np.asarray(a).nbytes for a in arrays.values()) > COMPRESS_ABOVE_BYTES
            f = self.path / "resume" / f"{i:06d}-{name}.npz"
            (np.savez_compressed if big else np.savez)(f, **arrays)
            size += _size(f)
        if new_field:
            self._write_index()
        return size

    def flush(self) -> None:
        """Wait until every step handed over is on disk (readers see it); raises the writing
        thread's failure, if it had one."""
        with self._committed_changed:
            self._committed_changed.wait_for(
                lambda: self.committed >= self.n or self._error is not None or not self._thread.is_alive()
            )
        if self._error is not None:
            raise self._error

    def close(self, summary: dict | None = None) -> None:
        """Write what is still queued, then close; ``summary`` (the run's summary.json content)
        goes into the index too. Raises the writing thread's failure after closing, if it had one."""
        if self.closed:
            return
        self.closed = True
        self._queue.put(None)
        self._thread.join()
        for f in self._files.values():
            try:
                f.close()
            except OSError:  # its failure is the one reported below
                pass
        self._events.close()
        self._steps.close()
        if summary is not None:
            self.meta["summary"] = summary
        self.meta["closed"] = True
        try:
            self._write_index()
        except OSError as exc:
            if self._error is None:
                self._error = RecordingError(f"{self.path}: cannot write the recording ({exc.strerror or exc})")
        if self._error is not None:
            raise self._error


@dataclasses.dataclass
class _Step:
    """One step as handed to the writing thread: copies of everything it writes."""

    index: int
    particles: np.ndarray
    log_weights: np.ndarray
    rows: dict[str, bytes]
    event_lines: list[str]
    s2m: S2MView | None
    payload: ResumePayload | None
    estimate: int = 0  # its bytes on disk at most (uncompressed), counted until it is written

    def size_estimate(self) -> int:
        size = self.particles.nbytes + self.log_weights.nbytes + sum(len(r) for r in self.rows.values())
        size += sum(len(line) for line in self.event_lines)
        if self.s2m is not None:  # the scan as float16, the rest as JSON
            size += 6 * len(self.s2m.scan_world) + 16384
        if self.payload is not None:
            size += sum(np.asarray(v).nbytes for v in self.payload.per_step.values())
            for arrays in self.payload.files.values():
                size += 1024 + sum(np.asarray(a).nbytes + 256 for a in arrays.values())
        return size


def _size(f: Path) -> int:
    try:
        return f.stat().st_size
    except OSError:
        return 0
