"""``lidarloc bench`` commands of time travel: what recording a run costs, how fast the timeline
scrubs and how fast a branch starts."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from ..console import err, progress_bar
from ..options import CacheOpt, JsonOpt, open_source, with_settings, with_source
from .bench_costs import SeedOpt, show_bench_result
from .groups import bench_app


def _recorded_unless(run_dir: Path | None, spec, cfg):
    """(spec, the sequence to record first): none with --run, else the source's first 1000 scans
    unless --scans says otherwise."""
    if run_dir is not None:
        return spec, None
    spec = replace(spec, scans=1000 if spec.scans is None else spec.scans)
    return spec, open_source(spec, cfg, err)


@bench_app.command("record")
@with_source()
@with_settings()
def bench_record(
    particles: Annotated[
        int | None, typer.Option("--particles", min=1, help="Particles (default: the config's).")
    ] = None,
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """What recording a run costs (≤ 5 % of the PF step, ≤ 60 MB per 1000 scans at 1000
    particles) and how fast it opens again (≤ 3 s for 1000 scans).

    Records the town's first 1000 scans unless the source options say otherwise."""
    from ..bench.record import run as run_bench

    cfg = settings.load(seed=seed)
    if particles is not None:
        cfg.pf.n_particles = particles
    spec, seq = _recorded_unless(None, spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task("recording", total=len(seq))
        result = run_bench(spec, seq, cfg, cache_root=cache, progress=lambda i, n: bar.update(task, completed=i))
    show_bench_result("record", result, as_json)


@bench_app.command("scrub")
@with_source()
@with_settings()
def bench_scrub(
    run_dir: Annotated[
        Path | None,
        typer.Option("--run", help="A recorded run folder to scrub (default: record the source's scans first)."),
    ] = None,
    moves: Annotated[int, typer.Option("--moves", min=1, help="Slider moves timed.")] = 200,
    out: Annotated[
        Path | None, typer.Option("--out", help="Keep the run recorded first here (default: a temporary folder).")
    ] = None,
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """The viewer's timeline: the server-side redraw per slider move on a recorded run (target
    ≤ 50 ms median), and until the step's scan is drawn too.

    Without --run, records the town's first 1000 scans first (unless the source options say otherwise)."""
    from ..bench.scrub import scrub

    cfg = settings.load(seed=seed)
    spec, seq = _recorded_unless(run_dir, spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task("recording", total=None if seq is None else len(seq))
        result = scrub(
            run_dir,
            spec=spec,
            seq=seq,
            cfg=cfg,
            cache_root=cache,
            moves=moves,
            out=out,
            progress=lambda i, n: bar.update(task, completed=i),
        )
    show_bench_result("scrub", result, as_json)


@bench_app.command("branch")
@with_source()
@with_settings()
def bench_branch(
    run_dir: Annotated[
        Path | None, typer.Option("--run", help="A recorded run to branch (default: record the source's scans first).")
    ] = None,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Times each of the last 10 steps is branched.")] = 3,
    as_json: JsonOpt = False,
    spec=None,
    cfg=None,
    cache: CacheOpt = None,
):
    """How fast a branch of a recorded run starts (target ≤ 1 s, the sequence open) and what the
    resume data costs per 1000 steps (checkpoints and per-step fields ≤ 10 MB at the run's own
    particle counts; scaled to 1000 particles beside it).

    Records the town's first 1000 scans unless --run or the source options say otherwise."""
    from ..bench.branch import run as run_bench

    spec, seq = _recorded_unless(run_dir, spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task("recording", total=None if seq is None else len(seq))
        result = run_bench(
            spec,
            seq,
            cfg,
            cache_root=cache,
            run_dir=run_dir,
            repeats=repeats,
            progress=lambda i, n: bar.update(task, completed=i),
        )
    show_bench_result("branch", result, as_json)
