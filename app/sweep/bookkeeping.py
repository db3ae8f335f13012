"""The bookkeeping of many runs, whichever executor runs them: a :class:`Run` (a grid point, its
folder, its arguments), the :class:`Tally`, the progress :class:`Board`, and how a run's folder
says it is finished (``summary.json``) or failed (``error.txt``, its one-line error)."""

from __future__ import annotations

import json
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..console import err

#: a run's one-line error, beside its traceback, in its folder
ERROR_FILE = "error.txt"
#: a run's folder holds this once the run finished (written last by the run function)
DONE_FILE = "summary.json"
# A worker process that dies takes the pool's other runs with it: those are tried again once, the
# run that keeps killing its worker is then reported as failed.
POOL_RETRIES = 1
WORKER_DIED = "its worker process died (out of memory, or killed)"


@dataclass(frozen=True)
class Run:
    """One run: its grid ``point`` (the axes' values, in the axes' order), a ``label`` for
    messages, its folder, the arguments of the run function, and ``before`` — ``(callable,
    args)`` called first in the worker (the run's world on that machine, :mod:`.world`)."""

    point: tuple
    label: str
    run_dir: str
    args: tuple
    before: tuple | None = None


@dataclass
class Tally:
    """What happened: runs ``kept`` from before, ``done`` now, ``failed`` (label → one-line
    error), and whether the sweep was ``interrupted`` (Ctrl-C) before every run was over."""

    total: int
    kept: int = 0
    done: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    interrupted: bool = False

    @property
    def finished(self) -> bool:
        return self.kept + self.done == self.total


def is_done(run_dir: str | Path) -> bool:
    return (Path(run_dir) / DONE_FILE).is_file()


def one_line(exc: BaseException) -> str:
    """An exception as one line: lidarloc's own errors as they are, others with their type."""
    from ...core.errors import LidarlocError

    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if isinstance(exc, LidarlocError):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def call_run(fn: Callable, run: Run) -> tuple[str, Any]:
    """In a worker: ``("kept", summary)`` for a finished run, ``("done", summary)`` after running
    it, ``("failed", one_line)`` if it raised (the traceback in its folder's error.txt)."""
    folder = Path(run.run_dir)
    if is_done(folder):
        return "kept", json.loads((folder / DONE_FILE).read_text())
    try:
        if run.before is not None:
            run.before[0](*run.before[1])
        summary = fn(*run.args)
    except Exception as exc:
        message = one_line(exc)
        try:
            folder.mkdir(parents=True, exist_ok=True)
            (folder / ERROR_FILE).write_text(message + "\n\n" + traceback.format_exc())
        except OSError:
            pass  # the message still reaches the sweep
        return "failed", message
    (folder / ERROR_FILE).unlink(missing_ok=True)
    return "done", summary


def read_error(run_dir: str | Path) -> str | None:
    """A failed run's one-line error (None: no error recorded)."""
    path = Path(run_dir) / ERROR_FILE
    try:
        return path.read_text().splitlines()[0]
    except (OSError, IndexError):
        return None


# ------------------------------------------------------------------------------ progress
class Board:
    """The progress bar: runs done of all, how many are running and how many failed, the ETA."""

    def __init__(self, label: str, tally: Tally, console: Console | None = None):
        self.tally, self.running = tally, 0
        self.progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[state]}"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            console=console or err,
            transient=False,
        )
        self.task = self.progress.add_task(label, total=tally.total, completed=tally.kept, state=self._state())

    def _state(self) -> str:
        failed = len(self.tally.failed)
        return f"running {self.running} · failed {failed}" + (f" (kept {self.tally.kept})" if self.tally.kept else "")

    def started(self) -> None:
        self.running += 1
        self.progress.update(self.task, state=self._state())

    def ended(self, failed_label: str | None = None, message: str | None = None) -> None:
        self.running = max(0, self.running - 1)
        if failed_label is not None:
            self.tally.failed[failed_label] = message or "failed"
            # one line per failed run, above the bar, as it happens
            self.progress.console.print(f"failed: {failed_label}: {message}", markup=False, highlight=False)
        self.progress.update(self.task, advance=1, state=self._state())

    def __enter__(self):
        self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        self.progress.__exit__(*exc)
