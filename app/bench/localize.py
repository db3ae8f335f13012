"""``lidarloc bench localize``: the paper's experiment — R seeded runs, metrics A–E, plots, report.

Runs use the replay clock (deterministic per seed) unless the configuration asks for the real-time
clock (``--set localize.clock=realtime``: each run then keeps the drive's pace, its figures depend
on the machine's load, and a worker per two cores is what keeps the pace honest). Each run writes
``runs/seed_NNN/`` with its summary and per-scan CSV; a run whose summary exists is kept, so an
interrupted benchmark resumes where it stopped (only with the same source, configuration and code,
else it refuses). The map, lookup table, BEV pyramid and (unless ``--live-odometry``) the KISS-ICP
odometry of the sequence are built once, in the parent, into the cache that every worker then loads
(process pool or Ray tasks alike). The odometry does not depend on the seed, so replaying it
changes no number (tested) and saves each run ~45–60 ms of CPU per scan (KISS-ICP, ``lidarloc bench
rpe``).

Beside A–E the summary gives whether the filter's own uncertainty can be trusted: the median over
runs of ``consistency_2sigma`` and ``false_fire_rate``, the share of runs whose rule fired more
than 5 m from the truth (:mod:`lidarloc.core.runs.metrics`).

Its pieces — :class:`Plan` (one directory's seeds, resume), :func:`prepare_cache` and
:func:`prepare_one` (the cache, in the parent and in a worker), :func:`run_tasks` (the worker
pool) and :func:`run_one` — are also the machinery of ``lidarloc bench robustness``.
"""

from __future__ import annotations

import json
import multiprocessing
import shutil
import signal
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

import numpy as np
from rich.console import Console

from ...core.config import Config, update_from_dict
from ...core.errors import LidarlocError
from ...core.runs.results import make_out_dir, summarize_run, write_run
from ...core.sequences.factory import SourceSpec, open_sequence
from ..console import SIGNAL_POLL_S, progress_bar, stop_signals_like_ctrl_c
from .common import is_town
from .localize_report import write_report


def code_fingerprint(parts: tuple[str, ...] = ("core", "app"), exclude: tuple[str, ...] = ()) -> str:
    """SHA-256 of lidarloc's own Python sources under ``parts`` (folders or files relative to the
    package's root; by default all of core and app), but for the files named in ``exclude``, and
    of the versions of the libraries that compute its numbers: two benchmark runs resume into one
    report only if they ran the same code."""
    import hashlib
    from importlib import metadata

    import lidarloc

    digest = hashlib.sha256()
    for dist in ("numpy", "numba", "scipy", "kiss-icp", "small_gicp", "open3d"):
        try:
            digest.update(f"{dist}=={metadata.version(dist)}\0".encode())
        except metadata.PackageNotFoundError:
            digest.update(f"{dist} missing\0".encode())
    root = Path(lidarloc.__file__).parent
    for part in parts:
        where = root / part
        for path in sorted(where.rglob("*.py")) if where.is_dir() else [where]:
            if path.relative_to(root).as_posix() in exclude:
                continue
            digest.update(path.relative_to(where).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def bench_sequence(spec: SourceSpec, cfg: Config, cache_root: Path | None):
    """The source; a generated town's scans are simulated once and then loaded from the cache
    (the same arrays, ~1 ms to load instead of ~20 ms to simulate; ~2 MB per scan on disk)."""
    from ...core.maps.mapping import map_cache_dir
    from ...core.sequences.base import DiskCachedScans

    seq = open_sequence(spec, cfg)
    if is_town(spec):
        map_dir = map_cache_dir(seq, cfg.map, cache_root)  # a sibling: a map build replaces map_dir
        seq = DiskCachedScans(seq, map_dir.with_name(map_dir.name + "-scans"))
    return seq


def run_one(
    spec_d: dict,
    cfg_d: dict,
    seed: int,
    cache_root: str | None,
    run_dir: str,
    numba_threads: int,
    preset: str | None = None,
    record: bool = False,
) -> dict:
    """One seeded run (executed in a worker process or a Ray task). ``preset``: the named
    configuration ``cfg_d`` came from, recorded in the run's summary. ``record``: the run's
    recording goes into its folder (``recording/``, see :mod:`lidarloc.core.runs.recording`)."""
    _numba_threads(numba_threads)
    from ...core.localizer import Localizer

    cfg = update_from_dict(Config(), cfg_d)
    cfg.seed = seed
    seq = bench_sequence(SourceSpec.from_dict(spec_d), cfg, Path(cache_root) if cache_root else None)
    out = Path(run_dir)
    with Localizer(seq, cfg, Path(cache_root) if cache_root else None) as loc:
        t0 = time.perf_counter()
        writer = None
        if record:
            from ...core.runs.recording import RecordingWriter

            if (out / "recording").exists():  # a run cut short before: its recording is redone
                shutil.rmtree(out / "recording")
            writer = RecordingWriter(out, SourceSpec.from_dict(spec_d), cfg, seq, preset=preset)
        lags = None
        if cfg.localize.clock == "realtime":
            lags = _play_in_real_time(loc, None if writer is None else writer.on_scan)
        elif writer is not None:
            while not loc.done:
                writer.on_scan(loc, loc.step())
        else:
            loc.run()
        summary = summarize_run(loc, time.perf_counter() - t0, lags, preset=preset)
        if writer is not None:
            writer.close(summary)
        out.mkdir(parents=True, exist_ok=True)
        # latencies first: summary.json (written last) marks the run as complete for a resume
        np.save(out / "pf_ms.npy", np.array([r.pf_ms for r in loc.records]))
        np.save(out / "s2m_ms.npy", np.array([r.s2m_ms for r in loc.records if r.s2m_ms is not None]))
        write_run(loc, out, summary)
    return summary


def _play_in_real_time(loc, on_step=None) -> list[float]:
    """Step ``loc`` with its scans arriving at the sequence's own rate, as ``lidarloc run`` does
    on the real-time clock (:class:`~lidarloc.core.localizer.deadline.ScanClock`): the clock starts
    once every block is up; ``on_step(loc, snapshot)`` after each step (a recording's writer);
    returns each step's lag (ms)."""
    from ...core.localizer.deadline import RecentPeak, ScanClock

    loc.wait_ready()
    clock = ScanClock(loc.seq, loc.k)
    lags, tail = [], RecentPeak()
    while not loc.done:
        lags.append(clock.wait_due(loc.k))
        snap = loc.step(clock.deadline(loc.k, tail.value))
        if on_step is not None:
            t = time.perf_counter()
            on_step(loc, snap)
            tail.add(time.perf_counter() - t)
    return lags


def prepare_one(spec_d: dict, cfg_d: dict, cache_root: str | None, numba_threads: int = 0) -> None:
    """Fill the cache for one source in a worker: its scans (a town's, simulated once) and,
    with ``localize.recorded_odometry``, its odometry. The map, lookup table and pyramid must be
    in the cache already (:func:`prepare_cache` in the parent): two workers building the same
    entry would replace each other's directory."""
    _numba_threads(numba_threads)
    from ...core.localizer import Localizer

    cfg = update_from_dict(Config(), cfg_d)
    root = Path(cache_root) if cache_root else None
    Localizer(bench_sequence(SourceSpec.from_dict(spec_d), cfg, root), cfg, root).close()


def _numba_threads(n: int) -> None:
    if n:
        import numba

        numba.set_num_threads(n)


def prepare_cache(spec: SourceSpec, cfg: Config, cache_root: Path | None, label: str = "") -> None:
    """Build map, lookup and pyramid (and the recorded odometry) once, here, so workers only
    load them."""
    from ...core.localizer import Localizer

    seq = bench_sequence(spec, cfg, cache_root)
    prefix = f"{label}: " if label else ""
    with progress_bar() as bar:
        task = bar.add_task(f"{prefix}preparing map", total=100)
        loc = Localizer(
            seq,
            cfg,
            cache_root,
            progress=lambda s, f: bar.update(task, description=f"{prefix}preparing {s}", completed=100 * f),
        )
    loc.close()


class Plan:
    """The runs of one benchmark directory: the seeds still to run and the summaries of those
    already done (resume). Refuses a directory that holds runs of another source, configuration
    or version of lidarloc's code."""

    def __init__(
        self,
        out_dir: Path,
        spec: SourceSpec,
        cfg: Config,
        runs: int,
        preset: str | None = None,
        fingerprint: str | None = None,
        record: bool = False,
    ):
        make_out_dir(out_dir)
        self.out_dir, self.spec, self.cfg, self.runs, self.preset = Path(out_dir), spec, cfg, runs, preset
        self.record = record
        self.spec_d, self.cfg_d = spec.to_dict(), cfg.to_dict()
        self.cfg_d.pop("seed", None)
        # Resuming is only honest with the same source, configuration and code: refuse a mixed
        # directory (runs kept from before a code change would silently mix two versions' numbers).
        identity = json.dumps(
            {"source": self.spec_d, "config": self.cfg_d, "preset": preset, "code": fingerprint or code_fingerprint()},
            sort_keys=True,
            default=str,
        )
        marker = self.out_dir / "bench_config.json"
        if marker.is_file() and marker.read_text() != identity:
            raise LidarlocError(
                f"{out_dir}: holds runs of another source, configuration or version of lidarloc's "
                "code; use another --out"
            )
        marker.write_text(identity)
        self.todo: list[tuple[int, str]] = []
        self.summaries: dict[int, dict] = {}
        for seed in range(runs):
            run_dir = self.out_dir / "runs" / f"seed_{seed:03d}"
            done = run_dir / "summary.json"
            if done.is_file():
                self.summaries[seed] = json.loads(done.read_text())
            else:
                self.todo.append((seed, str(run_dir)))

    def tasks(self, cache: str | None, numba_threads: int) -> dict[int, tuple]:
        """:func:`run_one`'s arguments for each seed still to run."""
        return {
            seed: (self.spec_d, self.cfg_d, seed, cache, d, numba_threads, self.preset, self.record)
            for seed, d in self.todo
        }

    def done(self) -> list[dict]:
        """The summaries of every run, by seed (all must have run)."""
        return [self.summaries[s] for s in range(self.runs)]

    def report(self, plots: bool = True) -> dict:
        return write_report(self.out_dir, self.done(), self.cfg, self.spec, preset=self.preset, plots=plots)


def numba_threads_for(workers: int) -> int:
    """With several workers on few cores, one numba thread per worker avoids oversubscription
    (0: numba's own default)."""
    return 1 if workers > 1 else 0


def run_tasks(fn, tasks: dict, workers: int, on_done, executor: str = "process", address: str | None = None) -> None:
    """Call ``fn(*args)`` for every ``key: args`` of ``tasks`` in ``workers`` worker processes (or
    Ray tasks), and ``on_done(key, result)`` in this process as each finishes. A failure cancels
    the queued tasks and is raised."""
    if not tasks:
        return
    if executor == "ray":
        _run_ray(fn, tasks, workers, address, on_done)
        return
    # spawn, not fork: the parent may have started OpenMP threads (numba), which do not survive
    # a fork; a failed run cancels the queued ones instead of running them all.
    stop_signals_like_ctrl_c()  # SIGTERM / SIGHUP stop the benchmark as Ctrl-C does
    pool = ProcessPoolExecutor(
        max_workers=workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_ignores_ctrl_c
    )
    try:
        futures = {pool.submit(fn, *args): key for key, args in tasks.items()}
        order = {fut: i for i, fut in enumerate(futures)}  # runs that finish together: in task order
        pending = set(futures)
        while pending:
            # waits with a timeout: a stop signal taken by another of this process's threads (the
            # pool's) is run on the main thread only when it next runs Python code
            done, pending = wait(pending, timeout=SIGNAL_POLL_S, return_when=FIRST_COMPLETED)
            for fut in sorted(done, key=lambda f: order[f]):
                on_done(futures[fut], fut.result())
    except BaseException:
        # Ctrl-C, a signal or a failed run: the runs in progress are thrown away, so their
        # processes end now (they would otherwise run on, orphaned, into a closed pipe).
        workers_left = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in workers_left:
            proc.terminate()
        for proc in workers_left:
            proc.join(timeout=5)
        raise
    pool.shutdown(wait=True)


def _worker_ignores_ctrl_c() -> None:
    """A benchmark's worker process leaves Ctrl-C to its parent, which ends it (no traceback from
    every worker; the parent writes what finished)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def check_runs(runs: int, workers: int, executor: str = "process") -> None:
    if runs < 1 or workers < 1:
        raise LidarlocError("--runs and --workers must be ≥ 1")
    if executor not in ("process", "ray"):
        raise LidarlocError(f"unknown executor '{executor}' (process or ray)")


def run_bench(
    spec: SourceSpec,
    cfg: Config,
    runs: int,
    workers: int,
    out_dir: Path,
    executor: str = "process",
    address: str | None = None,
    cache_root: Path | None = None,
    console: Console | None = None,
    preset: str | None = None,
    record: bool = False,
) -> dict:
    """``runs`` seeded runs (seeds 0…runs−1) of ``cfg`` on ``spec`` into ``out_dir``; returns the
    aggregate summary. ``preset``: the named configuration ``cfg`` came from (recorded);
    ``record``: each run records itself into its folder (``runs/seed_NNN/recording``)."""
    stop_signals_like_ctrl_c()  # from the start: preparing the cache can take minutes
    check_runs(runs, workers, executor)
    plan = Plan(out_dir, spec, cfg, runs, preset, record=record)
    prepare_cache(spec, cfg, cache_root)
    cache = str(cache_root) if cache_root else None
    with progress_bar(transient=False) as bar:
        task = bar.add_task(f"{runs} runs ({len(plan.summaries)} resumed)", total=runs, completed=len(plan.summaries))

        def done(seed, summary):
            plan.summaries[seed] = summary
            bar.advance(task)

        run_tasks(run_one, plan.tasks(cache, numba_threads_for(workers)), workers, done, executor, address)
    return plan.report()


def _run_ray(fn, tasks: dict, workers: int, address: str | None, on_done) -> None:
    from ..sweep.cluster import connect, import_ray

    connect(address or "local", workers)  # a local instance: no dashboard, a small object store
    ray = import_ray()
    remote = ray.remote(num_cpus=1)(fn)
    refs = {remote.remote(*args): key for key, args in tasks.items()}
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        on_done(refs[ready[0]], ray.get(ready[0]))
