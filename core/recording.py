"""Recording a run: every step's full state, appended to disk as it happens, and read back.

A run's results folder gets ``recording/``; ``open(folder)`` reads it back (in a notebook too)::

    from lidarloc.core import recording
    rec = recording.open("out/run0")
    rec.n                       # complete steps recorded
    rec.mean_pose[i]            # 4×4 estimate after step i (the i-th processed scan)
    rec.particles(i)            # (N, 11) float32 particles after step i, rec.weights(i) their weights
    rec.events                  # [(step, Event), …]
    rec.snapshot(i, seq)        # the step as the viewer shows it

Format (version 1), chosen so that a recording is cheap to append, memory-mappable and readable
up to its last complete step after a crash:

- ``index.json``: ``format`` ("lidarloc-recording"), ``version``, ``meta`` (the source options,
  the configuration, the seed, the sequence, the clock, …) and ``fields``: per field its dtype,
  per-step shape and the first step it was written at.
- One raw little-endian file per per-step field (``mean_pose.bin``: rows of 4×4 float64, …).
  Particles vary in number (KLD, tracking), so ``particles.bin`` (float32 rows of 11 states) and
  ``log_weights.bin`` (float32) hold every step's rows one after the other, and the per-step field
  ``particle_rows`` says where (first row, count). Float32 is what a display needs; the filter's
  exact float64 state for resuming is in the resume payload's checkpoints.
- ``events.jsonl``: one event per line with the step after which it was recorded (-1: before the
  first scan).
- ``s2m/STEP.json`` and ``s2m/STEP.f16``: each S2M match that landed (an
  :class:`~lidarloc.core.snapshot.S2MView`; its road-removed scan in the matched pose's frame as
  float16: a display's precision, ≤ 6 cm at 100 m).
- ``resume/STEP-NAME.npz``: what resuming needs (:meth:`Localizer.resume_payload`: checkpoints of
  the filter's exact state, raw S2M outcomes); its per-step arrays are ordinary fields.
- ``steps.bin``: the commit log, one int64 per step, written after everything else of the step.
  A step exists only once its row is there, so a recording cut short (Ctrl-C, a killed process)
  opens up to its last complete step.

The scan itself is not stored: it is a reference to the source the recording names, and
:meth:`Recording.snapshot` recomputes the prepared scan (the same voxel and random seed as the
filter used). With ``localize.deskew`` the filter saw the scan de-skewed with the odometry of
that moment; the recomputed one is not de-skewed (a display difference of a few centimetres).

Size: 48 bytes per particle per step (11 float32 states and a float32 log-weight), ~0.5 kB of
per-step fields, plus the resume payload: ~55 MB per 1000 steps at 1000 particles
(``lidarloc bench record``).
"""

from __future__ import annotations

import bisect
import builtins
import dataclasses
import datetime as _dt
import json
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from .errors import LidarlocError
from .integrity import truth_alarm
from .snapshot import Event, S2MView, Snapshot

FORMAT = "lidarloc-recording"
VERSION = 1
FOLDER = "recording"
INDEX = "index.json"
STEPS = "steps.bin"
N_STATE = 11
COMPRESS_ABOVE_BYTES = 64 * 1024
# Steps the writing thread may fall behind before a step waits for it (~50 kB each at 1000
# particles, a checkpoint ~0.2 MB): a slow disk slows the run instead of filling the memory.
_QUEUE_STEPS = 64


class RecordingError(LidarlocError):
    """A recording folder is missing, foreign, corrupt or unwritable."""


@dataclasses.dataclass
class ResumePayload:
    """What a localizer adds to a step's record for resuming from it: ``per_step`` arrays (one
    fixed shape per name, appended as fields) and ``files`` (each saved as ``resume/STEP-NAME.npz``)."""

    per_step: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    files: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)


# The display fields every step has: name → (dtype, per-step shape).
_FIELDS: dict[str, tuple[str, tuple]] = {
    "scan_index": ("<i8", ()), "timestamp": ("<f8", ()), "mean_pose": ("<f8", (4, 4)),
    "cov_xyz": ("<f8", (3, 3)), "std_xyz": ("<f8", (3,)), "ellipse_xy": ("<f8", (3,)),
    "n_eff": ("<f8", ()), "n_particles": ("<i8", ()), "best_index": ("<i8", ()),
    "localized": ("|u1", ()), "localized_since": ("<i8", ()), "converged": ("|u1", ()),
    "error_m": ("<f8", ()), "gt_pose": ("<f8", (4, 4)), "pf_ms": ("<f8", ()), "rpe_ms": ("<f8", ()),
    "s2m_ms": ("<f8", ()), "reinit": ("|u1", ()), "inlier_share": ("<f8", ()),
    "mean_residual_m": ("<f8", ()), "inside_2sigma": ("|i1", ()), "scan_voxel": ("<f8", ()),
    "s2m_running": ("|u1", ()), "s2m_pending": ("|u1", ()), "s2m_acceptance": ("<f8", ()),
    "done": ("|u1", ()), "particle_rows": ("<i8", (2,)),
    "awaiting_confirmation": ("|u1", ()), "confirmed_at": ("<i8", ()), "s2m_status": ("|i1", ()),
}
#: ``s2m_status`` as recorded (the index into this tuple)
S2M_STATUSES = ("ready", "building", "held", "off")
_PARTICLES = ("particles", "<f4", (N_STATE,))
_LOG_WEIGHTS = ("log_weights", "<f4", ())

_S2M_ARRAYS = ("pose", "start_pose", "candidates", "match_pose", "gicp_pose")


def _nan(value) -> float:
    return float("nan") if value is None else float(value)


def _jsonable(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _source_dict(spec) -> dict:
    """The source options with absolute paths: a run folder opened from elsewhere finds its data."""
    out = {}
    for f in dataclasses.fields(spec):
        value = getattr(spec, f.name)
        if isinstance(value, Path):
            value = str(value.expanduser().resolve())
        out[f.name] = value
    return out


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_jsonable(data), indent=1))
    os.replace(tmp, path)        # a reader never sees half an index


# ---------------------------------------------------------------------------------------- writing
class RecordingWriter:
    """Appends a localizer's steps to ``run_dir/recording/`` (see the module docstring).

    Call :meth:`on_scan` after every successful ``Localizer.step()`` (on the stepping thread) and
    :meth:`close` at the end. One writer records one run from one (re)start: a restarted localizer
    gets a new writer.

    ``on_scan`` only gathers copies of the step; a thread of the writer's own writes them, in
    order, and commits each step once all of it is on disk. :attr:`committed` counts those (what
    a reader sees), :meth:`flush` waits for the rest, :meth:`close` writes what is queued. A
    failure to write is raised by the next ``on_scan``, ``flush`` or ``close``."""

    def __init__(self, run_dir, spec, cfg, seq, preset: str | None = None, branch_of: dict | None = None,
                 first_step: int = 0):
        from .. import __version__ as version

        self.path = Path(run_dir) / FOLDER
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            if (self.path / STEPS).exists():
                raise RecordingError(f"{self.path}: a recording is already there; choose another --out")
            (self.path / "s2m").mkdir(exist_ok=True)
            (self.path / "resume").mkdir(exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot write the recording ({exc.strerror or exc})") from None
        self.meta = {
            "source": _source_dict(spec), "source_description": spec.describe(), "config": cfg.to_dict(),
            "seed": int(cfg.seed), "sequence": getattr(seq, "name", "sequence"), "n_source_scans": int(len(seq)),
            "clock": cfg.localize.clock, "preset": preset,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "branch_of": branch_of, "first_step": int(first_step), "lidarloc_version": version,
        }
        self.fields: dict[str, dict] = {}
        self._files: dict[str, Any] = {}
        for name, (dtype, shape) in _FIELDS.items():
            self._declare(name, dtype, shape, 0)
        self._declare(_PARTICLES[0], _PARTICLES[1], _PARTICLES[2], 0)
        self._declare(_LOG_WEIGHTS[0], _LOG_WEIGHTS[1], _LOG_WEIGHTS[2], 0)
        self._write_index()
        self._events = builtins.open(self.path / "events.jsonl", "a", encoding="utf-8")
        self._steps = builtins.open(self.path / STEPS, "ab")
        self.n = 0
        self._particle_row = 0
        self._n_events = 0
        self._last_steps: int | None = None
        self._last_scan: int | None = None
        self._last_s2m = None
        self.closed = False
        # The disk work is done on a thread of its own, so that a step costs the filter only the
        # copies it hands over; ``committed`` counts the steps on disk (what a reader sees).
        self.committed = 0
        self.writer_cpu_s = 0.0           # the writing thread's CPU time
        self._error: RecordingError | None = None
        self._queue: queue.Queue = queue.Queue(maxsize=_QUEUE_STEPS)
        self._committed_changed = threading.Condition()
        self._thread = threading.Thread(target=self._drain, name="lidarloc-recording", daemon=True)
        self._thread.start()

    def continue_from(self, loc) -> None:
        """A branch's writer: the events up to ``loc.recorded_events_base``, the last scan and the
        last S2M view ``loc`` already has are the recorded run's; record only what follows."""
        self._n_events = int(loc.recorded_events_base)
        self._last_scan = int(loc.snapshot().scan_index)
        self._last_s2m = loc.s2m.last
        self._last_steps = int(loc.steps)

    def _declare(self, name: str, dtype: str, shape: tuple, first_step: int) -> None:
        self.fields[name] = {"dtype": dtype, "shape": list(shape), "first_step": int(first_step)}
        self._files[name] = builtins.open(self.path / f"{name}.bin", "ab")

    def _write_index(self) -> None:
        _write_json(self.path / INDEX, {"format": FORMAT, "version": VERSION, "meta": self.meta, "fields": self.fields})

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
            "scan_index": snap.scan_index, "timestamp": snap.timestamp, "mean_pose": snap.mean_pose,
            "cov_xyz": snap.cov_xyz, "std_xyz": snap.std_xyz, "ellipse_xy": np.asarray(snap.ellipse_xy, float),
            "n_eff": snap.n_eff, "n_particles": snap.n_particles if snap.n_particles else n,
            "best_index": snap.best_index, "localized": snap.localized,
            "localized_since": -1 if snap.localized_since is None else snap.localized_since,
            "converged": snap.converged, "error_m": _nan(snap.error_m),
            "gt_pose": np.full((4, 4), np.nan) if snap.gt_pose is None else snap.gt_pose,
            "pf_ms": snap.pf_ms, "rpe_ms": _nan(snap.rpe_ms),
            "s2m_ms": _nan(record.s2m_ms if record is not None else None),
            "reinit": bool(record.reinit) if record is not None else False,
            "inlier_share": _nan(snap.inlier_share), "mean_residual_m": _nan(snap.mean_residual_m),
            "inside_2sigma": -1 if snap.inside_2sigma is None else int(bool(snap.inside_2sigma)),
            "scan_voxel": float(loc.cfg.pf.scan_voxel), "s2m_running": snap.s2m_running,
            "s2m_pending": snap.s2m_pending, "s2m_acceptance": snap.s2m_acceptance, "done": snap.done,
            "particle_rows": (self._particle_row, n),
            "awaiting_confirmation": snap.awaiting_confirmation,
            "confirmed_at": -1 if snap.confirmed_at is None else snap.confirmed_at,
            "s2m_status": S2M_STATUSES.index(snap.s2m_status) if snap.s2m_status in S2M_STATUSES else 0,
        }
        rows = {name: self._row(name, value) for name, value in values.items()}
        payload = loc.resume_payload(i) if hasattr(loc, "resume_payload") else None
        if payload is not None:   # the next step must not change what this one hands over
            payload = ResumePayload(per_step={k: np.array(v) for k, v in payload.per_step.items()},
                                    files={k: dict(v) for k, v in payload.files.items()})
        s2m = snap.s2m if snap.s2m is not None and snap.s2m is not self._last_s2m else None
        item = _Step(i, np.array(snap.particles, np.float32), np.array(lw, np.float32), rows,
                     self._event_lines(loc, i, snap.scan_index), s2m, payload)
        self._queue.put(item)        # blocks while the writing thread is _QUEUE_STEPS steps behind
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
        for ev in events[self._n_events:]:
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
                    self._steps.flush()      # the commit: the steps exist from here on
                except Exception as exc:   # whatever it is, the thread lives on (a step waiting for it must not hang)
                    why = exc.strerror if isinstance(exc, OSError) and exc.strerror else (str(exc) or type(exc).__name__)
                    self._error = RecordingError(f"{self.path}: cannot write the recording ({why})")
            self.writer_cpu_s += time.thread_time() - t0
            with self._committed_changed:
                if self._error is None:
                    self.committed += len(items)
                self._committed_changed.notify_all()
            if batch[-1] is None:
                return

    def _write_step(self, item: "_Step") -> None:
        self._files["particles"].write(item.particles.tobytes())
        self._files["log_weights"].write(item.log_weights.tobytes())
        for name, row in item.rows.items():
            self._files[name].write(row)
        for line in item.event_lines:
            self._events.write(line)
        if item.s2m is not None:
            _save_s2m(self.path / "s2m", item.index, item.s2m)
        if item.payload is not None:
            self._write_payload(item.index, item.payload)

    def _write_payload(self, i: int, payload: ResumePayload) -> None:
        new_field = False
        for name, value in payload.per_step.items():
            arr = np.asarray(value)
            if name not in self.fields:
                if name in _FIELDS or name in (_PARTICLES[0], _LOG_WEIGHTS[0]):
                    raise RecordingError(f"resume field {name} clashes with a display field")
                self._declare(name, arr.dtype.newbyteorder("<").str, arr.shape, i)
                new_field = True
            self._files[name].write(self._row(name, arr))
        for name, arrays in payload.files.items():
            # a checkpoint (~0.1 MB at 1000 particles) compresses ~10×; a small file is not worth the time
            big = sum(np.asarray(a).nbytes for a in arrays.values()) > COMPRESS_ABOVE_BYTES
            (np.savez_compressed if big else np.savez)(self.path / "resume" / f"{i:06d}-{name}.npz", **arrays)
        if new_field:
            self._write_index()

    def flush(self) -> None:
        """Wait until every step handed over is on disk (readers see it); raises the writing
        thread's failure, if it had one."""
        with self._committed_changed:
            self._committed_changed.wait_for(lambda: self.committed >= self.n or self._error is not None
                                             or not self._thread.is_alive())
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
            except OSError:      # its failure is the one reported below
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


def _save_s2m(folder: Path, step: int, view: S2MView) -> None:
    """``STEP.json`` (every field but the scan; JSON keeps float64 exactly) and ``STEP.f16`` (the
    scan: its bulk, in the matched pose's frame as float16, ≤ 6 cm at 100 m, a display's needs,
    about a quarter of the size of float32 world coordinates). Plain files, no zip: a match lands
    every other scan, and compressing it cost more than the rest of the step's record."""
    data: dict[str, Any] = {}
    for f in dataclasses.fields(view):
        value = getattr(view, f.name)
        if f.name == "scan_world":
            pose = np.asarray(view.pose, np.float64)
            local = (np.asarray(value, np.float64).reshape(-1, 3) - pose[:3, 3]) @ pose[:3, :3]
            (folder / f"{step:06d}.f16").write_bytes(local.astype("<f2").tobytes())
        elif isinstance(value, np.ndarray):
            data[f.name] = np.asarray(value, np.float64).tolist()
        elif isinstance(value, tuple):
            data[f.name] = [float(v) for v in value]
        else:
            data[f.name] = _jsonable(value)
    (folder / f"{step:06d}.json").write_text(json.dumps(data))


def _load_s2m(folder: Path, step: int) -> S2MView:
    d = json.loads((folder / f"{step:06d}.json").read_text())
    kw: dict[str, Any] = {}
    for f in dataclasses.fields(S2MView):
        if f.name == "scan_world":
            raw = folder / f"{step:06d}.f16"
            local = np.frombuffer(raw.read_bytes(), "<f2").reshape(-1, 3).astype(np.float64) if raw.is_file() \
                else np.zeros((0, 3))
            pose = np.asarray(d["pose"], np.float64)
            kw[f.name] = (local @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
            continue
        if f.name not in d:
            continue
        v = d[f.name]
        if f.name in _S2M_ARRAYS:
            kw[f.name] = None if v is None else np.asarray(v, np.float64)
        elif f.name == "nodes_per_level":
            kw[f.name] = tuple(int(x) for x in v)
        elif f.name in ("region", "gicp_correction"):
            kw[f.name] = tuple(float(x) for x in v)
        else:
            kw[f.name] = v
    if kw.get("candidates") is not None:
        kw["candidates"] = kw["candidates"].reshape(-1, 4)
    return S2MView(**kw)


# ---------------------------------------------------------------------------------------- reading
def open(path) -> "Recording":  # noqa: A001 - the documented name: recording.open(dir)
    """The recording of a run folder (or the ``recording/`` folder itself)."""
    return Recording(path)


class Recording:
    """A recorded run, read-only (see the module docstring). Per-step fields are attributes
    (``rec.mean_pose``, ``rec.error_m``, …) of length :attr:`n`."""

    def __init__(self, path):
        path = Path(path).expanduser()
        if not path.exists():
            raise RecordingError(f"{path}: no such run folder")
        if (path / FOLDER / INDEX).is_file():
            path = path / FOLDER
        index_file = path / INDEX
        if not index_file.is_file():
            raise RecordingError(f"{path}: not a recorded run (no {FOLDER}/{INDEX}; record with lidarloc run, "
                                 "without --no-record)")
        try:
            index = json.loads(index_file.read_text())
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{index_file}: unreadable recording index ({exc})") from None
        if not isinstance(index, dict) or index.get("format") != FORMAT:
            raise RecordingError(f"{index_file}: not a lidarloc recording")
        if index.get("version") != VERSION:
            raise RecordingError(f"{index_file}: recording format version {index.get('version')}, "
                                 f"this lidarloc reads version {VERSION}")
        self.path = path
        self.run_dir = path.parent
        self.meta: dict = index.get("meta", {})
        self._fields: dict = index.get("fields", {})
        steps_file = path / STEPS
        n = steps_file.stat().st_size // 8 if steps_file.is_file() else 0
        self._cache: dict[str, np.ndarray] = {}
        try:
            for name, info in self._fields.items():   # a step counts only if every field has its row
                if name in (_PARTICLES[0], _LOG_WEIGHTS[0]):
                    continue
                rows = self._rows_on_disk(name, info)
                n = min(n, info["first_step"] + rows) if rows >= 0 else n
            if n > 0:   # the particles of the last steps may be cut short too
                n_rows = min(self._rows_on_disk(*_named(self._fields, _PARTICLES[0])),
                             self._rows_on_disk(*_named(self._fields, _LOG_WEIGHTS[0])))
                while n > 0 and self.field("particle_rows", n)[n - 1].sum() > n_rows:
                    n -= 1
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"{index_file}: corrupt recording index ({exc})") from None
        self.n = int(n)
        self._cache.clear()
        self._s2m_cache: dict[int, S2MView] = {}
        self._s2m_steps: list[int] | None = None
        self._events: list | None = None

    # ------------------------------------------------------------------ fields
    def _rows_on_disk(self, name: str, info: dict) -> int:
        f = self.path / f"{name}.bin"
        size = np.dtype(info["dtype"]).itemsize * int(np.prod(info["shape"], dtype=np.int64))
        return f.stat().st_size // size if f.is_file() else 0

    @property
    def field_names(self) -> list[str]:
        return list(self._fields)

    def field(self, name: str, n: int | None = None) -> np.ndarray:
        """A per-step field as an array of length ``n`` (default: :attr:`n`); steps before the field
        first appeared are NaN (floats) or 0."""
        n = self.n if n is None else n
        key = f"{name}:{n}"
        if key in self._cache:
            return self._cache[key]
        if name not in self._fields:
            raise RecordingError(f"{self.path}: no field {name!r} in this recording")
        info = self._fields[name]
        dtype, shape, first = np.dtype(info["dtype"]), tuple(info["shape"]), int(info["first_step"])
        count = max(n - first, 0)
        raw = np.fromfile(self.path / f"{name}.bin", dtype=dtype, count=count * int(np.prod(shape, dtype=np.int64)))
        arr = raw.reshape((count,) + shape)
        if first > 0:
            head = np.full((min(first, n),) + shape, np.nan if dtype.kind == "f" else 0, dtype=dtype)
            arr = np.concatenate([head, arr])
        if dtype == np.dtype("|u1") and name in _FIELDS:
            arr = arr.astype(bool)
        self._cache[key] = arr
        return arr

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        fields = self.__dict__.get("_fields", {})
        if name in fields and name not in (_PARTICLES[0], _LOG_WEIGHTS[0]):
            return self.field(name)
        raise AttributeError(f"Recording has no field or attribute {name!r}")

    def _memmap(self, name: str) -> np.ndarray:
        if name not in self._cache:
            dtype, shape = (np.dtype(_PARTICLES[1]), _PARTICLES[2]) if name == _PARTICLES[0] else (np.dtype(_LOG_WEIGHTS[1]), ())
            f = self.path / f"{name}.bin"
            rows = f.stat().st_size // (dtype.itemsize * int(np.prod(shape, dtype=np.int64))) if f.is_file() else 0
            self._cache[name] = (np.memmap(f, dtype=dtype, mode="r", shape=(rows,) + shape) if rows
                                 else np.zeros((0,) + shape, dtype))
        return self._cache[name]

    def _check(self, i: int) -> int:
        if not -self.n <= i < self.n:
            raise RecordingError(f"step {i} is outside the recording (0…{self.n - 1})")
        return i % self.n

    def particles(self, i: int) -> np.ndarray:
        """(N, 11) float32 particles after step i (see config.STATE_NAMES)."""
        start, count = self.field("particle_rows")[self._check(i)]
        return np.asarray(self._memmap(_PARTICLES[0])[start:start + count])

    def log_weights(self, i: int) -> np.ndarray:
        start, count = self.field("particle_rows")[self._check(i)]
        return np.asarray(self._memmap(_LOG_WEIGHTS[0])[start:start + count])

    def weights(self, i: int) -> np.ndarray:
        """Normalised float64 weights after step i (from the log-weights: no underflow to all-zero)."""
        lw = self.log_weights(i).astype(np.float64)
        if lw.size == 0:
            return lw
        w = np.exp(lw - lw.max())
        return w / w.sum()

    # ------------------------------------------------------------------ events, S2M, summary
    @property
    def events(self) -> list[tuple[int, Event]]:
        """(step, event) of every event of the recorded steps; step -1: before the first scan."""
        if self._events is None:
            out = []
            f = self.path / "events.jsonl"
            if f.is_file():
                for line in f.read_text(encoding="utf-8").splitlines():
                    try:
                        d = json.loads(line)
                    except ValueError:
                        break                     # a line cut short by a crash: the steps after it are not complete
                    if d["step"] >= self.n:
                        break
                    out.append((int(d["step"]), Event(int(d["scan"]), str(d["kind"]), str(d.get("detail", "")))))
            self._events = out
        return self._events

    @property
    def s2m_steps(self) -> list[int]:
        """Steps at which an S2M match landed (listed once: the recording is read as it was opened)."""
        if self._s2m_steps is None:
            steps = []
            for f in (self.path / "s2m").glob("*.json"):
                try:
                    step = int(f.stem)
                except ValueError:
                    continue
                if step < self.n:
                    steps.append(step)
            self._s2m_steps = sorted(steps)
        return self._s2m_steps

    def s2m(self, i: int) -> S2MView | None:
        """The last S2M match that landed at or before step i."""
        i = self._check(i)
        steps = self.s2m_steps
        at = bisect.bisect_right(steps, i)
        if at == 0:
            return None
        step = steps[at - 1]
        if step not in self._s2m_cache:
            try:
                self._s2m_cache[step] = _load_s2m(self.path / "s2m", step)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise RecordingError(f"{self.path}/s2m/{step:06d}.json: unreadable ({exc})") from None
        return self._s2m_cache[step]

    @property
    def summary(self) -> dict | None:
        """The run folder's summary.json (or the summary the recording was closed with)."""
        f = self.run_dir / "summary.json"
        if f.is_file():
            try:
                return json.loads(f.read_text())
            except ValueError:
                pass
        return self.meta.get("summary")

    def resume_steps(self, name: str) -> list[int]:
        steps = []
        for f in (self.path / "resume").glob(f"*-{name}.npz"):
            try:
                step = int(f.name.split("-", 1)[0])
            except ValueError:
                continue
            if step < self.n:
                steps.append(step)
        return sorted(steps)

    def resume_file(self, step: int, name: str) -> dict[str, np.ndarray] | None:
        f = self.path / "resume" / f"{step:06d}-{name}.npz"
        if step >= self.n or not f.is_file():
            return None
        try:
            with np.load(f, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{f}: unreadable ({exc})") from None

    # ------------------------------------------------------------------ source and config
    def source_spec(self):
        """The source options the run was made with (a SourceSpec)."""
        from .sequences.factory import SourceSpec

        names = {f.name: f for f in dataclasses.fields(SourceSpec)}
        kw = {}
        for key, value in self.meta.get("source", {}).items():
            if key not in names:
                continue
            if value is not None and key in ("kitti_odometry", "kitti_raw", "trajectory", "calib", "map", "bag",
                                             "scans_dir", "gt", "gt_times", "extrinsic"):
                value = Path(value)
            kw[key] = value
        return SourceSpec(**kw)

    def check_source(self) -> None:
        """One line naming the path the run expected, if its source has moved."""
        for key, value in self.meta.get("source", {}).items():
            if isinstance(value, str) and key in ("kitti_odometry", "kitti_raw", "trajectory", "calib", "map", "bag",
                                                  "scans_dir", "gt", "gt_times", "extrinsic"):
                if not Path(value).exists():
                    raise RecordingError(f"{value}: the run's source is not there any more (named by "
                                         f"{self.path / INDEX} as --{key.replace('_', '-')}); put it back or "
                                         "rerun")

    def open_sequence(self):
        """The run's sequence, rebuilt from its source (one-line error if the source moved)."""
        from .sequences.factory import open_sequence

        self.check_source()
        return open_sequence(self.source_spec(), self.config())

    def config(self):
        """The configuration the run started with (a Config)."""
        from .config import Config, update_from_dict

        return update_from_dict(Config(), self.meta.get("config", {}))

    @property
    def _max_elevation(self) -> float:
        """The run's pf.max_elevation (a scan is re-prepared as the run prepared it)."""
        value = getattr(self, "_max_elevation_cache", None)
        if value is None:
            value = self._max_elevation_cache = float(self.config().pf.max_elevation)
        return value

    # ------------------------------------------------------------------ snapshots
    def step_of_scan(self, scan: int) -> int | None:
        """The step that processed source scan ``scan`` (None if none did)."""
        hits = np.flatnonzero(self.scan_index == scan)
        return int(hits[0]) if hits.size else None

    def events_until(self, i: int) -> list[Event]:
        return [ev for step, ev in self.events if step <= i]

    def prepared_scan(self, i: int, seq) -> np.ndarray:
        """(M, 3) float32: step i's scan as the filter weighed it (one random point per voxel, the
        run's seed and voxel), in the LiDAR's frame, recomputed from the run's sequence ``seq``."""
        from .scanprep import voxel_downsample_random

        i = self._check(i)
        k = int(self.scan_index[i])
        rng = np.random.default_rng([int(self.meta.get("seed", 0)), k, 1])
        return voxel_downsample_random(seq.scan(k), float(self.scan_voxel[i]), rng, self._max_elevation)

    def snapshot(self, i: int, seq=None) -> Snapshot:
        """Step i as a :class:`~lidarloc.core.snapshot.Snapshot` (what the viewer draws). With the run's
        sequence ``seq``, ``scan_world`` is the prepared scan at the estimate, recomputed from the
        source; without, it is empty."""
        from .geometry import transform_points

        i = self._check(i)
        k = int(self.scan_index[i])
        pose = self.mean_pose[i]
        scan_world = np.zeros((0, 3), np.float32)
        if seq is not None:
            scan_world = transform_points(pose, self.prepared_scan(i, seq)).astype(np.float32)
        gt = self.gt_pose[i]
        since = int(self.localized_since[i])
        inside = int(self.inside_2sigma[i])

        def opt(v):
            return None if not np.isfinite(v) else float(v)

        def recorded(name, default):    # a field recordings made before it appeared do not have
            return self.field(name)[i] if name in self._fields else default
        confirmed_at = int(recorded("confirmed_at", -1))
        status = S2M_STATUSES[int(recorded("s2m_status", 0))]

        return Snapshot(
            scan_index=k, n_scans=int(self.meta.get("n_source_scans", self.n)), timestamp=float(self.timestamp[i]),
            particles=self.particles(i).astype(np.float64), weights=self.weights(i),
            log_weights=self.log_weights(i).astype(np.float64), best_index=int(self.best_index[i]),
            mean_pose=pose.copy(), cov_xyz=self.cov_xyz[i].copy(), std_xyz=self.std_xyz[i].copy(),
            ellipse_xy=tuple(float(v) for v in self.ellipse_xy[i]), n_eff=float(self.n_eff[i]),
            localized=bool(self.localized[i]), localized_since=None if since < 0 else since,
            scan_world=scan_world, gt_pose=None if not np.all(np.isfinite(gt)) else gt.copy(),
            error_m=opt(self.error_m[i]), pf_ms=float(self.pf_ms[i]), rpe_ms=opt(self.rpe_ms[i]),
            s2m=self.s2m(i), s2m_running=bool(self.s2m_running[i]), s2m_acceptance=float(self.s2m_acceptance[i]),
            s2m_pending=bool(self.s2m_pending[i]), n_particles=int(self.n_particles[i]),
            converged=bool(self.converged[i]), inlier_share=opt(self.inlier_share[i]),
            mean_residual_m=opt(self.mean_residual_m[i]), inside_2sigma=None if inside < 0 else bool(inside),
            events=tuple(self.events_until(i)[-50:]), done=bool(self.done[i]),
            awaiting_confirmation=bool(recorded("awaiting_confirmation", False)),
            confirmed_at=None if confirmed_at < 0 else confirmed_at, s2m_status=status,
            truth_alarm=truth_alarm(bool(self.localized[i]), opt(self.error_m[i])))

    def size_bytes(self) -> int:
        """Bytes on disk of the whole recording."""
        return sum(f.stat().st_size for f in self.path.rglob("*") if f.is_file())


def _named(fields: dict, name: str) -> tuple[str, dict]:
    return name, fields[name]
