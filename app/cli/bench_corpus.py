"""``lidarloc bench corpus``: a corpus run five ways, and what ``corpus compare`` finds in each."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..options import CacheOpt, JsonOpt
from .bench_costs import show_bench_result
from .groups import bench_app
from .sweeps import RayOpt


@bench_app.command("corpus")
def bench_corpus(
    out: Annotated[Path, typer.Option("--out", help="A new folder for the five corpus runs.")] = Path(
        "out/bench-corpus"
    ),
    drives: Annotated[int, typer.Option("--drives", min=2, help="Drives (logs) in the corpus.")] = 20,
    scans: Annotated[int, typer.Option("--scans", min=5, help="Scans of each drive.")] = 60,
    seeds: Annotated[int, typer.Option("--seeds", min=2, help="Seeds each drive runs under (the noise).")] = 2,
    workers: Annotated[int, typer.Option("--workers", min=1, help="Workers of the timed run beside one.")] = 2,
    ray: RayOpt = None,
    no_real: Annotated[
        bool,
        typer.Option("--no-real", help="Town drives only (by default the real KITTI drive is one, where present)."),
    ] = False,
    as_json: JsonOpt = False,
    cache: CacheOpt = None,
):
    """Does corpus compare find a planted regression, and only that? The built-in town's drives
    (town seeds × sensors, lived-in; with the real drive where its data is), each under --seeds
    seeds, are run with one worker and with --workers (their wall times), again under other seeds
    (every regression found is a false alarm), with pf.sigma × 5 on every drive, and with one
    drive's map missing a building (that drive must be ranked first)."""
    from ..bench.corpus import corpus_bench

    result = corpus_bench(out, drives, scans, seeds, workers, ray=ray, real=not no_real, cache_root=cache)
    show_bench_result("corpus", result, as_json)
