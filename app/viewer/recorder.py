"""The viewer records what it plays: every run it starts (the first start, each restart, each
branch) goes into its own folder under one root, so the timeline can scrub it, "Branch from here"
can resume from any of its steps, and ``lidarloc view --run FOLDER`` opens it later.

The root is ``--record-dir`` or a new ``runs/<date-time>`` under the cache root; its runs are
``run`` (the first start), ``run-2``, … (restarts) and ``branch-scan-K`` (a branch after scan K).
A step is appended on the player thread right after ``Localizer.step()`` returned it, under
:attr:`Recorder.lock`; the viewer's controls that change the filter between steps (restart,
reset, kidnap, parameters) take the same lock, so a step's resume data is the state it left.
A failure to write (disk full, folder removed) stops the recording with a message; playback goes on.

With a :class:`Budget` the runs root is kept under it (:mod:`.budget`): at each new run and every
``Budget.every_s`` seconds the oldest runs are removed, never the one recording.

A run that alone outgrows ``max_bytes`` keeps recording a rolling window of its newest steps
instead of stopping; the filter plays on. The files are append-only, so cutting the oldest
steps off them would mean rewriting the whole recording; instead the run is written in segments
(:mod:`lidarloc.core.runs.recording.segments`): a segment is closed once it holds
:data:`SEGMENT_SHARE` of the budget and the run goes on in the next one (the writer's
``next_segment``: same run, same step numbers, a checkpoint at its first step), and at that moment
the oldest segments are dropped whole while the closed ones and a full new one would exceed the
budget. So the run keeps at least ``1 − 2 × SEGMENT_SHARE`` of the budget (three quarters) of its
newest steps, less one step, and its files exceed the budget by at most a segment (the step that
crossed it, and a dropped segment while its files are being removed). The user is told once per run (``on_notice``), with the window's first step; the
timeline's lower end follows the window, and a step index stays the run's own step number. A
segment is dropped under :attr:`Recorder.lock` (its commit log emptied, the run on the timeline
re-read); its files, thousands of them at the default budget, are removed on a thread of their
own, so that the filter does not wait for the disk; a reader that opened the run before gets a
one-line "dropped by the recording budget" for the steps that went.
"""

from __future__ import annotations

import datetime as _dt
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ...core.cache import default_cache_root
from ...core.errors import LidarlocError
from ...core.runs.recording import RecordingWriter, segments
from .budget import DEFAULT_KEEP_RUNS, DEFAULT_MAX_RECORD_GB, KnownRuns, enforce
from .faults import one_line
from .recorded import RecordedRun


def default_record_root(cache_root: Path | None) -> Path:
    """A new folder for this viewer's runs: ``<cache root>/runs/<date-time>``."""
    root = (cache_root if cache_root is not None else default_cache_root()) / "runs"
    stamp = _dt.datetime.now().strftime("%Y-%m-%dT%H-%M-%S")
    return _unique(root / stamp)


def _unique(path: Path) -> Path:
    if not path.exists():
        return path
    i = 2
    while path.with_name(f"{path.name}-{i}").exists():
        i += 1
    return path.with_name(f"{path.name}-{i}")


#: A run's segment is closed at this share of the budget (see the module docstring): small enough
#: that dropping one keeps most of the budget's worth of steps, large enough that a segment's
#: start (the writer closed and opened, a checkpoint) comes rarely: every ~10000 steps at 1000
#: particles and the default 5 GB.
SEGMENT_SHARE = 1 / 8


def size_text(n: float) -> str:
    """Bytes as the user reads them: 2 GB, 350 MB, 600 kB."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} bytes"


@dataclass(frozen=True)
class Budget:
    """How much of the disk the viewer's runs may take: the runs under ``root`` (the cache's
    ``runs/`` or ``--record-dir``), at most ``keep_runs`` of them and ``max_bytes`` in all (None:
    no limit of that kind), checked every ``every_s`` seconds while recording."""

    root: Path
    keep_runs: int | None = DEFAULT_KEEP_RUNS
    max_bytes: float | None = DEFAULT_MAX_RECORD_GB * 1e9
    every_s: float = 30.0


class Recorder:
    """One :class:`~lidarloc.core.runs.recording.RecordingWriter` per run the viewer starts.

    ``spec``: the source options the localizer's sequence was opened with (the recording names
    them, so that the run can be reopened); ``on_failure(message)``: writing stopped."""

    def __init__(
        self,
        root: Path,
        spec,
        preset: str | None = None,
        on_failure: Callable[[str], None] | None = None,
        budget: Budget | None = None,
        on_notice: Callable[[str], None] | None = None,
    ):
        self.root = Path(root)
        self.budget = budget
        self.removed: list[Path] = []  # runs the budget removed, oldest first
        self._on_notice = on_notice or (lambda message: None)
        self._budget_stop = threading.Event()
        self._known_runs = KnownRuns()  # the periodic check walks only runs that changed
        self._budget_thread: threading.Thread | None = None
        self.spec = spec
        self.preset = preset
        self.lock = threading.RLock()
        self._on_failure = on_failure or (lambda message: None)
        self.writer: RecordingWriter | None = None
        self.run: RecordedRun | None = None
        self.runs: list[Path] = []  # every run folder started, oldest first
        self._t0 = 0.0
        self._loc = None
        self._end = 0  # the current run's steps on disk once its writer is gone
        self._closed: list[tuple[Path, int]] = []  # the current run's closed segments kept: (folder, bytes)
        self._removers: list[threading.Thread] = []  # removing dropped segments' files
        self._said_rolling = False  # the current run was told it keeps a rolling window

    @property
    def run_dir(self) -> Path | None:
        return None if self.run is None else self.run.path

    @property
    def n(self) -> int:
        """Steps of the current run on disk so far (a branch's original steps included): the
        timeline can open every one of them."""
        w, run = self.writer, self.run
        if run is None:
            return 0
        return w.first_step + w.committed if w is not None else self._end

    @property
    def first_kept(self) -> int:
        """The current run's first step still on disk (0 unless its recording budget dropped the
        steps before it: a rolling window)."""
        run = self.run
        return 0 if run is None else run.first_kept

    @property
    def segment_bytes(self) -> float | None:
        """A segment's size: its run goes on in a new one beyond it (None: no size budget)."""
        b = self.budget
        return None if b is None or b.max_bytes is None else b.max_bytes * SEGMENT_SHARE

    def start(self, loc, name: str = "run", branch_of: dict | None = None, first_step: int = 0) -> Path:
        """Close the current run's recording and start one for ``loc`` (just built, restarted or
        branched) in a new folder; returns it."""
        with self.lock:
            self.close(None)
            path = _unique(self.root / name)
            self.writer = RecordingWriter(
                path, self.spec, loc.cfg, loc.seq, preset=self.preset, branch_of=branch_of, first_step=first_step
            )
            if branch_of is not None:
                from ...core.runs.branch import continue_recording

                # the events and last match the branch starts with are the original's, recorded there
                continue_recording(self.writer, loc)
            self.run = RecordedRun(path, loc.seq, live=True)
            self.runs.append(path)
            self._loc = loc
            self._t0 = time.perf_counter()
            self._end = first_step
            self._closed = []
            self._said_rolling = False
        if self.budget is not None:
            self.keep_to_budget()
            if self._budget_thread is None:
                self._budget_thread = threading.Thread(target=self._watch_budget, name="lidarloc-budget", daemon=True)
                self._budget_thread.start()
        return path

    def keep_to_budget(self) -> list[Path]:
        """Remove the oldest runs beyond the budget (never the one recording: it keeps itself
        within the budget as a rolling window, see the module docstring). Returns the folders
        removed."""
        b = self.budget
        if b is None:
            return []
        current = self.run_dir
        protect = [current] if current else []
        removed = [r.path for r in enforce(b.root, b.keep_runs, b.max_bytes, protect, self._known_runs)]
        self.removed += removed
        if removed:
            self._on_notice(f"recording budget: removed {len(removed)} oldest run(s), the newest of them {removed[-1]}")
        return removed

    def _watch_budget(self) -> None:
        b = self.budget
        while b is not None and not self._budget_stop.wait(b.every_s):
            try:
                self.keep_to_budget()
            except Exception as exc:  # one line; the recording itself goes on
                self._on_failure(f"recording budget check failed: {one_line(exc)}")

    def stop(self) -> None:
        """Close the current run and stop checking the budget (the dropped segments' files are
        removed before it returns)."""
        self._budget_stop.set()
        self.close()
        for t in list(self._removers):
            t.join()

    def on_scan(self, loc, snap) -> bool:
        """Append the step ``snap`` of ``loc`` (player thread); False if it was not recorded (another
        run's, or writing failed)."""
        dropped: list[tuple[Path, bool]] = []
        with self.lock:
            w = self.writer
            if w is None or loc is not self._loc or snap is not loc.snapshot():
                return False
            try:
                w.on_scan(loc, snap)
                limit = self.segment_bytes
                if limit is not None and w.bytes >= limit:
                    dropped = self._next_segment(w)
            except LidarlocError as exc:
                self._fail(f"recording stopped: {exc}")
                return False
            except OSError as exc:
                self._fail(f"recording stopped: {exc}")
                return False
        if dropped:  # thousands of files: on a thread of their own, the filter need not wait
            remover = threading.Thread(target=_remove, args=(dropped,), name="lidarloc-drop", daemon=True)
            self._removers = [t for t in self._removers if t.is_alive()] + [remover]
            remover.start()
        return True

    def flush(self) -> None:
        """Wait until every step handed over is on disk and the dropped segments' files are gone."""
        with self.lock:
            w = self.writer
        if w is not None:
            w.flush()
        for t in list(self._removers):
            t.join()

    def _next_segment(self, w: RecordingWriter) -> list[tuple[Path, bool]]:
        """The current segment is full: the run goes on in a new one, and the oldest segments are
        dropped while the closed ones and a full new one would exceed the budget (under the
        lock). Returns the dropped folders whose files are to be removed, (folder, first segment)."""
        b = self.budget
        assert b is not None and b.max_bytes is not None
        nxt = w.next_segment()  # closes w: the steps it was handed are on disk
        self.writer = nxt
        self._closed.append((w.path, segments.folder_bytes(w.path)))
        limit = b.max_bytes * SEGMENT_SHARE
        dropped = []
        while self._closed and sum(size for _, size in self._closed) + limit > b.max_bytes:
            folder, _ = self._closed.pop(0)
            segments.drop_commit(folder)  # from here on no reader counts its steps
            dropped.append((folder, folder == w.top))
        if dropped:
            run = self.run
            if run is not None:
                run.refresh()  # the timeline reads the window from now on, not the dropped files
            if not self._said_rolling:
                self._said_rolling = True
                self._on_notice(
                    f"recording: this run reached the budget ({size_text(b.max_bytes)}); keeping its newest "
                    f"steps (a rolling window from step {self.first_kept})"
                )
        return dropped

    def _fail(self, message: str) -> None:
        w, self.writer = self.writer, None
        if w is not None:
            self._end = w.first_step + w.committed
        try:
            w.close(None)
        except Exception:  # the message says it stopped; a second failure adds nothing
            pass
        self._on_failure(message)

    def close(self, summary: dict | None = "auto") -> None:
        """Close the current run's recording, with the run's summary (``"auto"``: computed from the
        localizer, so that a comparison table can show it)."""
        with self.lock:
            w, self.writer = self.writer, None
            if w is None:
                return
            if summary == "auto":
                summary = self._summary()
            try:
                w.close(summary)
            except LidarlocError as exc:  # the writing thread failed after the last step
                self._on_failure(f"recording stopped: {exc}")
            self._end = w.first_step + w.committed
            if summary is not None and self.run is not None:
                import json

                try:
                    (self.run.path / "summary.json").write_text(json.dumps(summary, indent=1, default=_json_default))
                except OSError:
                    pass

    def _summary(self) -> dict | None:
        loc = self._loc
        if loc is None or not getattr(loc, "records", None):
            return None
        from ...core.runs.results import summarize_run

        try:
            return summarize_run(loc, time.perf_counter() - self._t0, preset=self.preset)
        except Exception:  # a summary is a convenience of the comparison; the recording stands without it
            return None


def _remove(dropped: list[tuple[Path, bool]]) -> None:
    for folder, first in dropped:
        segments.remove_files(folder, first)


def _json_default(value):
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(type(value).__name__)
