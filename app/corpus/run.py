"""``lidarloc corpus run``: every drive of a corpus as one seeded replay-clock run, in a local
process pool or on Ray, resumable, each drive's failure one line while the others go on.

A drive is run by :func:`~lidarloc.app.bench.localize.run_one` (its summary.json, scans.csv,
events and recording in ``drives/NAME/``, so ``lidarloc view --run DIR/drives/NAME`` opens it)
through :func:`~lidarloc.app.sweep.executor.execute`, exactly as a sweep's runs are: a drive whose
folder holds summary.json is kept, not run again. Its identity (source, configuration, seed,
code) is kept beside it, and a kept drive whose definition has changed is refused rather than
mixed into new results.

On this machine the drives' maps and tables are built here first, one drive after the other
(drives of one town share one map, and two workers building one cache entry at once would
replace each other's directory); each worker then only computes its drive's odometry. On a Ray
cluster each node builds what it lacks under a lock, as a sweep's runs do.

Writes ``corpus.json``: per drive its summary and health (:mod:`.health`), and ``drives_failed``
(name → one-line reason).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from ...core.cache import default_cache_root
from ...core.config import Config, update_from_dict
from ...core.errors import LidarlocError
from ...core.runs.results import make_out_dir, write_json
from ...core.sequences.factory import SourceSpec
from ..bench.localize import code_fingerprint, numba_threads_for, prepare_cache, run_one
from ..console import err
from ..sweep.bookkeeping import ERROR_FILE, Run, Tally, is_done, one_line
from ..sweep.cluster import check_address
from ..sweep.executor import execute
from ..sweep.world import ensure_world, mark_ready, world_key
from .health import run_health
from .spec import IDENTITY_FILE, Corpus, Drive


def _identity(spec_d: dict, cfg_d: dict, drive: Drive, code: str) -> str:
    return json.dumps(
        {"source": spec_d, "config": cfg_d, "seed": drive.seed, "preset": drive.preset, "code": code},
        sort_keys=True,
        default=str,
    )


def plan_drives(
    corpus: Corpus, out_dir: Path, workers: int, overrides: Sequence[str], cache: str
) -> tuple[list[Run], dict[str, str], dict[str, float]]:
    """One Run per drive that can run; the drives that cannot (a path missing: name → reason);
    each drive's ``localize.min_inlier_share`` (its health's threshold)."""
    threads = numba_threads_for(workers)
    code = code_fingerprint()
    planned, failed, thresholds, identities = [], {}, {}, {}
    for drive in corpus.drives:
        missing = drive.missing_path()
        if missing is not None:
            failed[drive.name] = missing
            continue
        cfg = drive.config_for(overrides)
        thresholds[drive.name] = cfg.localize.min_inlier_share
        cfg_d = cfg.to_dict()
        cfg_d.pop("seed", None)
        spec_d = drive.spec.to_dict()
        run_dir = (out_dir / "drives" / drive.name).absolute()
        identity, marker = _identity(spec_d, cfg_d, drive, code), run_dir / IDENTITY_FILE
        if is_done(run_dir) and marker.is_file() and marker.read_text() != identity:
            raise LidarlocError(
                f"{run_dir}: holds a run of another source, configuration or version of lidarloc's code "
                f"than drive '{drive.name}' now names; use another --out"
            )
        identities[marker] = identity
        planned.append(
            Run(
                point=(drive.name,),
                label=drive.name,
                run_dir=str(run_dir),
                args=(spec_d, cfg_d, drive.seed, cache, str(run_dir), threads, drive.preset, True),
                before=(ensure_world, (spec_d, cfg_d, cache, threads)),
            )
        )
    for marker, identity in identities.items():  # only once every kept drive is the same drive
        make_out_dir(marker.parent)
        marker.write_text(identity)
    return planned, failed, thresholds


def prepare_here(planned: list[Run], cache: str, console: Console) -> dict[str, str]:
    """Each drive still to run has its map and tables built here, one after the other; a drive
    whose source cannot be opened (a corrupt file) fails here with its one-line reason, said as it
    happens (the builds before the runs may take minutes)."""
    failed, outcome = {}, {}  # outcome: world key → None (prepared) or the reason it failed
    for run in planned:
        if is_done(run.run_dir):
            continue
        spec_d, cfg_d = run.args[0], run.args[1]
        # without the odometry: each worker computes its own drive's, in parallel
        map_only = {**cfg_d, "localize": {**cfg_d["localize"], "recorded_odometry": False}}
        key = world_key(spec_d, map_only)  # one log under several seeds is prepared once
        if key not in outcome:
            try:
                prepare_cache(
                    SourceSpec.from_dict(spec_d), update_from_dict(Config(), map_only), Path(cache), label=run.label
                )
                outcome[key] = None
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # any failure of one drive's data is that drive's, not the corpus's
                outcome[key] = one_line(exc)
        if outcome[key] is not None:
            failed[run.label] = outcome[key]
            Path(run.run_dir, ERROR_FILE).write_text(failed[run.label] + "\n")
            console.print(f"failed: {run.label}: {failed[run.label]}", markup=False, highlight=False)
            continue
        if not cfg_d["localize"]["recorded_odometry"]:
            mark_ready(spec_d, cfg_d, cache)  # nothing left for its worker to build
    return failed


def run_corpus(
    corpus: Corpus,
    out_dir: Path,
    workers: int,
    *,
    overrides: Sequence[str] = (),
    ray: str | None = None,
    cache_root: Path | None = None,
    console: Console | None = None,
) -> tuple[dict, Tally]:
    """Run every drive of ``corpus`` not run yet into ``out_dir`` and write corpus.json; returns
    its content and the executor's tally."""
    if workers < 1:
        raise LidarlocError("--workers must be ≥ 1")
    check_address(ray)
    out_dir = Path(out_dir)
    make_out_dir(out_dir)
    cache = str(Path(cache_root or default_cache_root()).absolute())
    planned, failed, thresholds = plan_drives(corpus, out_dir, workers, overrides, cache)
    if ray in (None, "local"):
        failed.update(prepare_here(planned, cache, console or err))
    runnable = [r for r in planned if r.label not in failed]
    tally = execute(
        run_one,
        {"drive": [r.label for r in runnable]},
        runnable,
        workers,
        on_done=lambda run, summary: None,  # read back from each folder below, kept drives alike
        label=f"corpus: {len(runnable)} drives",
        ray=ray,
        ray_dir=out_dir / "ray",
        console=console,
    )
    failed.update(tally.failed)
    report = corpus_report(corpus, out_dir, runnable, failed, thresholds, tally)
    write_json(out_dir / "corpus.json", report)
    return report, tally


def corpus_report(
    corpus: Corpus, out_dir: Path, runs: list[Run], failed: dict[str, str], thresholds: dict[str, float], tally: Tally
) -> dict:
    """corpus.json: each finished drive's summary and health, the failed drives' reasons."""
    drives = {}
    for run in runs:
        if run.label in failed or not is_done(run.run_dir):
            continue
        summary = json.loads(Path(run.run_dir, "summary.json").read_text())
        drives[run.label] = {"summary": summary, "health": run_health(Path(run.run_dir), thresholds[run.label])}
    order = [d.name for d in corpus.drives]
    return {
        "corpus": str(corpus.path),
        "out": str(out_dir),
        "total": len(order),
        "done": len(drives),
        "ran_now": tally.done,
        "interrupted": tally.interrupted,
        "drives": {name: drives[name] for name in order if name in drives},
        "drives_failed": {name: failed[name] for name in order if name in failed},
    }
