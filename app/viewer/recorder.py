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
``Budget.every_s`` seconds the oldest runs are removed, never the one recording. A run that alone
outgrows ``max_bytes`` stops recording with a message saying so; the filter plays on.
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
from ...core.runs.recording import RecordingWriter
from .budget import DEFAULT_KEEP_RUNS, DEFAULT_MAX_RECORD_GB, _scan_folder, enforce
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
        return run.first_step + (w.committed if w is not None else run.rec.n)

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
        if self.budget is not None:
            self.keep_to_budget()
            if self._budget_thread is None:
                self._budget_thread = threading.Thread(target=self._watch_budget, name="lidarloc-budget", daemon=True)
                self._budget_thread.start()
        return path

    def keep_to_budget(self) -> list[Path]:
        """Remove the oldest runs beyond the budget (never the one recording); a recording that
        alone outgrew it stops. Returns the folders removed."""
        b = self.budget
        if b is None:
            return []
        current = self.run_dir
        removed = [r.path for r in enforce(b.root, b.keep_runs, b.max_bytes, protect=[current] if current else [])]
        self.removed += removed
        if removed:
            self._on_notice(f"recording budget: removed {len(removed)} oldest run(s), the newest of them {removed[-1]}")
        if b.max_bytes is not None and current is not None and self.writer is not None:
            size = _scan_folder(current).bytes
            if size > b.max_bytes:
                with self.lock:
                    if self.writer is not None and self.run_dir == current:
                        self._fail(
                            f"recording stopped at step {self.n}: this run alone reached the recording budget "
                            f"({b.max_bytes / 1e9:.3g} GB); the filter plays on (raise --max-record-gb to keep more)"
                        )
        return removed

    def _watch_budget(self) -> None:
        b = self.budget
        while b is not None and not self._budget_stop.wait(b.every_s):
            try:
                self.keep_to_budget()
            except Exception as exc:  # one line; the recording itself goes on
                self._on_failure(f"recording budget check failed: {one_line(exc)}")

    def stop(self) -> None:
        """Close the current run and stop checking the budget."""
        self._budget_stop.set()
        self.close()

    def on_scan(self, loc, snap) -> bool:
        """Append the step ``snap`` of ``loc`` (player thread); False if it was not recorded (another
        run's, or writing failed)."""
        with self.lock:
            w = self.writer
            if w is None or loc is not self._loc or snap is not loc.snapshot():
                return False
            try:
                w.on_scan(loc, snap)
            except LidarlocError as exc:
                self._fail(f"recording stopped: {exc}")
                return False
            except OSError as exc:
                self._fail(f"recording stopped: {exc}")
                return False
            return True

    def _fail(self, message: str) -> None:
        w, self.writer = self.writer, None
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


def _json_default(value):
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(type(value).__name__)
