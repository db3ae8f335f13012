"""The localizer's threads and processes as a whole, seen from outside a step: this process (the
PF, and the threads that feed the children) and the blocks' child processes (KISS-ICP for the RPE;
RS + S2M). Here they are made (the threads; KISS-ICP's child early on a viewer's start), made
ready to work at full speed before a real-time clock starts, measured (the CPU time each has
used), and closed together.

Stopping: ``interrupt()`` (Ctrl-C, closing the viewer) makes a step that waits for a block give up
without recording its scan; ``close()`` cancels the match in flight and then closes the threads and
children here (:func:`close_threads_and_children`), killing children that are busy or still setting
up; ``kill_processes()`` kills every child at once, for a process about to exit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..filter.scanprep import voxel_downsample_random
from ..worker_process import WorkerProxy
from .blocks import BlockError


def start_rpe_early(cfg, defer_s2m: bool):
    """On a viewer's start (``defer_s2m``), KISS-ICP's child process, started before the map and
    tables are built: its set-up (~3 s of imports) runs meanwhile instead of in front of the first
    scan. None otherwise (the odometry starts its own when it needs one)."""
    if defer_s2m and cfg.localize.rpe_process and not cfg.localize.recorded_odometry:
        from ..odometry.worker import KissICPProcess

        return KissICPProcess()
    return None


def block_threads() -> tuple[ThreadPoolExecutor, ThreadPoolExecutor, ThreadPoolExecutor]:
    """The threads beside the caller's: one that feeds the RPE, one that feeds S2M and one for
    the background rebuilds, each doing its work in order."""
    return (
        ThreadPoolExecutor(1, thread_name_prefix="lidarloc-RPE"),
        ThreadPoolExecutor(1, thread_name_prefix="lidarloc-S2M"),
        ThreadPoolExecutor(1, thread_name_prefix="lidarloc-rebuild"),
    )


def load_kernels(points: np.ndarray, pf_cfg, states: np.ndarray, lookup, d_max: float) -> None:
    """This process's own one-off costs: numba loads a kernel from its cache at the first call
    (~0.3 s for the scan down-sampling, measured), here instead of in scan 0's step. ``points``:
    a few map points to down-sample and weigh; ``states``: particles to weigh them at."""
    from ..filter.likelihood import log_likelihood_floored

    few = np.asarray(points[:64], dtype=np.float32)
    voxel_downsample_random(few, pf_cfg.scan_voxel, 0)
    some = states[:2]
    log_likelihood_floored(some, few, lookup, d_max, pf_cfg.sigma, np.zeros(len(some)))


def wait_for_children(workers: Iterable, on_restarted: Callable[[str], None]) -> None:
    """Block until each child process among ``workers`` has finished its set-up (a block running
    in this process has none to wait for). A child killed in its set-up is started once more, and
    ``on_restarted("BLOCK: what happened")`` says so; a set-up that fails is a :class:`BlockError`."""
    for worker in workers:
        if isinstance(worker, WorkerProxy):
            try:
                words = worker.wait_ready_reviving()  # a child killed in its set-up: once more
            except RuntimeError as exc:
                raise BlockError(f"{worker.block}: {exc}", worker.block) from None
            if words is not None:
                on_restarted(f"{worker.block}: {words}")


def cpu_seconds(rpe, s2m) -> dict:
    """CPU time used so far by this process (``main``) and by the child processes ``rpe`` and
    ``s2m`` (None for a block that runs in this process, or where the platform cannot tell)."""
    try:
        import resource

        usage = resource.getrusage(resource.RUSAGE_SELF)
        main = usage.ru_utime + usage.ru_stime
    except ImportError:  # not a Unix
        main = None

    def child(worker):
        return worker.cpu_seconds() if isinstance(worker, WorkerProxy) else None

    return {"main": main, "rpe": child(rpe), "s2m": child(s2m)}


def close_threads_and_children(pools: tuple[ThreadPoolExecutor, ...], odometry, s2m) -> None:
    """Shut down the blocks' threads (``pools``) and the child processes ``odometry`` (the feed)
    and ``s2m`` (the scheduler) drive."""
    for pool in pools:  # queued work is dropped …
        pool.shutdown(wait=False, cancel_futures=True)
    # … and the children close before the threads are joined: a match or registration in
    # flight is only thrown away, so a busy child is killed rather than waited for (a
    # whole-map match kept Ctrl-C waiting 1.2 s).
    odometry.close_process()
    s2m.close_processes()
    for pool in pools:
        pool.shutdown(wait=True)
