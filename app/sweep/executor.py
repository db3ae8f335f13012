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

import multiprocessing
import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from rich.console import Console

from ..console import SIGNAL_POLL_S
from .bookkeeping import POOL_RETRIES, WORKER_DIED, Board, Run, Tally, call_run, is_done


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
            finished: set = set()
            while not finished:  # timed, so that a stop signal another thread took is run (SIGNAL_POLL_S)
                finished, _ = wait(list(inflight), timeout=SIGNAL_POLL_S, return_when=FIRST_COMPLETED)
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
