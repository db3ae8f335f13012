"""Many independent runs, each in a folder of its own: in a local process pool (the default) or as
Ray Tune trials (``--ray``), with the same results either way.

The unit is a :class:`Run`: a point of a grid (its axes' values: the swept settings and the seed,
or a robustness cell and the seed), a folder, and the arguments of the run function. A run whose
folder holds ``summary.json`` is finished: it is skipped, whichever executor finished it, so a
sweep interrupted by a crash, Ctrl-C or a lost node resumes where it stopped and never does a
finished run twice. A run that raises is reported with its one-line error (its traceback goes to
``error.txt`` in its folder) and the others go on; the next call runs it again.

On Ray the grid is Ray Tune's own (``tune.grid_search`` per axis); Ray Tune keeps the trials'
state in ``ray/`` and resumes it with ``Tuner.restore`` (a different grid in the same folder
starts a fresh experiment; finished runs are still skipped by their folder). Runs never share
mutable state: each builds its own localizer from the read-only cache and writes only its folder.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import traceback
from collections import deque
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
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


# ------------------------------------------------------------------------------ executing
def execute(
    fn: Callable,
    axes: dict[str, list],
    runs: list[Run],
    workers: int,
    *,
    on_done: Callable[[Run, dict], None],
    label: str = "runs",
    ray: str | None = None,
    ray_dir: Path | None = None,
    console: Console | None = None,
) -> Tally:
    """Run every run of ``runs`` (the whole grid ``axes``, one Run per point) that is not finished
    yet: ``fn(*run.args)`` in ``workers`` worker processes, or with ``ray`` as Ray Tune trials
    (state in ``ray_dir``). ``on_done(run, summary)`` is called here as each finishes. Returns
    the tally; a Ctrl-C ends the runs in flight and returns (``interrupted``)."""
    tally = Tally(total=len(runs), kept=sum(is_done(r.run_dir) for r in runs))
    with Board(label, tally, console) as board:
        if ray is None:
            _pool(fn, [r for r in runs if not is_done(r.run_dir)], workers, tally, board, on_done)
        else:
            from .cluster import import_ray

            import_ray()  # a one-line error without Ray, before its module imports it
            from .ray_tune import run_grid

            run_grid(fn, axes, runs, workers, ray, Path(ray_dir or "ray"), tally, board, on_done)
    return tally


def _pool(fn, todo: list[Run], workers: int, tally: Tally, board: Board, on_done) -> None:
    # spawn, not fork: the parent may have started OpenMP threads (numba), which do not survive a
    # fork. At most `workers` runs are handed out at a time, so "running" is what runs.
    queue, inflight, deaths = deque(todo), {}, {}
    pool = None
    try:
        while queue or inflight:
            if pool is None:
                pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))
            while queue and len(inflight) < workers:
                run = queue.popleft()
                inflight[pool.submit(call_run, fn, run)] = run
                board.started()
            finished, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
            broken = False
            for fut in finished:
                run = inflight.pop(fut)
                try:
                    status, value = fut.result()
                except BrokenProcessPool:
                    broken = True
                    deaths[run.label] = deaths.get(run.label, 0) + 1
                    if deaths[run.label] > POOL_RETRIES:
                        board.ended(run.label, WORKER_DIED)
                    else:
                        board.running -= 1
                        queue.appendleft(run)
                    continue
                if status == "failed":
                    board.ended(run.label, value)
                else:
                    tally.done += status == "done"
                    tally.kept += status == "kept"
                    on_done(run, value)
                    board.ended()
            if broken:  # the pool is unusable: its other runs go back to the queue, a new pool takes them
                for fut, run in inflight.items():
                    fut.cancel()
                    board.running -= 1
                    queue.appendleft(run)
                inflight.clear()
                _stop(pool)
                pool = None
    except KeyboardInterrupt:
        tally.interrupted = True
    finally:
        if pool is not None:
            _stop(pool)


def _stop(pool: ProcessPoolExecutor) -> None:
    """Stop a pool now: queued runs cancelled, its worker processes ended (a run cut short leaves no
    summary.json, so it runs again on resume)."""
    processes = list(getattr(pool, "_processes", {}).values())  # not public: ended below if present
    pool.shutdown(wait=False, cancel_futures=True)
    for p in processes:
        if p.is_alive():
            p.terminate()
    for p in processes:
        p.join(timeout=10)


def default_workers() -> int:
    """The machine's CPUs (the benches' reference machine has 2)."""
    return max(1, os.cpu_count() or 1)
