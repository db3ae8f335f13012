"""``lidarloc bench localize|robustness|integrity``: many seeded runs and what they say about localization."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Annotated

import typer

from ..console import emit_json, err, progress_bar, stage_progress
from ..options import OWN_DATA, CacheOpt, JsonOpt, with_settings, with_source
from ..sweep.cluster import RAY_HELP
from .bench_costs import RecordBenchOpt, SeedOpt, show_bench_result
from .groups import bench_app
from .sweeps import RayOpt


@bench_app.command("localize")
@with_source()
@with_settings(world=True)
def bench_localize(
    runs: Annotated[int, typer.Option("--runs")] = 20,
    workers: Annotated[int, typer.Option("--workers")] = 2,
    out: Annotated[Path, typer.Option("--out")] = Path("out/bench-localize"),
    no_s2m: Annotated[bool, typer.Option("--no-s2m")] = False,
    live_odometry: Annotated[
        bool,
        typer.Option(
            "--live-odometry",
            help="Run KISS-ICP in every run instead of replaying its poses, computed once "
            "per sequence (the same numbers; only slower).",
        ),
    ] = False,
    executor: Annotated[str, typer.Option("--executor", help="process or ray")] = "process",
    address: Annotated[str | None, typer.Option("--address", help="Ray cluster address.")] = None,
    record: RecordBenchOpt = False,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Metrics A–E over many seeded runs in parallel workers (the paper's Simulation section).

    On the built-in town the drive is lived-in unless --world kind says otherwise."""
    from ..bench.localize import run_bench

    cfg = settings.load(
        first=[] if live_odometry else ["localize.recorded_odometry=true"],
        last=["s2m.enabled=false"] if no_s2m else [],
    )
    summary = run_bench(
        spec,
        cfg,
        runs=runs,
        workers=workers,
        out_dir=out,
        executor=executor,
        address=address,
        cache_root=cache,
        console=err,
        preset=settings.preset,
        record=record,
    )
    show_bench_result("localize", summary, as_json)


_AXES = "Matrix (comma-separated values; each axis restricts the matrix)"


@bench_app.command("robustness")
@with_source(exclude=OWN_DATA)
@with_settings(preset=False)
def bench_robustness(
    runs: Annotated[int, typer.Option("--runs", help="Seeded runs per cell (seeds 0…N−1).")] = 5,
    workers: Annotated[int, typer.Option("--workers", help="Worker processes.")] = 2,
    out: Annotated[
        Path,
        typer.Option(
            "--out", help="Directory for the cells' runs, report.md, cells.csv, summary.json and heatmap.png."
        ),
    ] = Path("out/bench-robustness"),
    changes: Annotated[
        str,
        typer.Option(
            "--changes",
            help="Shares of the town's movable objects changed since mapping, in [0, 1].",
            rich_help_panel=_AXES,
        ),
    ] = "0,0.3,0.6",
    traffic: Annotated[str, typer.Option("--traffic", help="Traffic: off, on.", rich_help_panel=_AXES)] = "off,on",
    sensors: Annotated[
        str,
        typer.Option(
            "--sensors", help="Sensors of the localized drive: hdl64e, vlp16, vlp32c, os1-128.", rich_help_panel=_AXES
        ),
    ] = "hdl64e,vlp16,os1-128",
    skew: Annotated[str, typer.Option("--skew", help="Motion skew: off, on.", rich_help_panel=_AXES)] = "off,on",
    configs: Annotated[
        str,
        typer.Option(
            "--configs",
            help="Configurations: paper (the paper preset), default, no-S2M (default without S2M).",
            rich_help_panel=_AXES,
        ),
    ] = "paper,default,no-S2M",
    real: Annotated[
        bool | None,
        typer.Option(
            "--real/--no-real",
            help="Also the real KITTI drive, same configurations (default: where its data is present).",
            rich_help_panel=_AXES,
        ),
    ] = None,
    record: RecordBenchOpt = False,
    ray: RayOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Localization when the world is not the map: changes × traffic × sensor × skew × configuration.

    Each cell: --runs seeded runs of the town's first 300 scans (unless --scans says otherwise) against the map of the town as mapped, plus the real KITTI drive's cells. The configurations are presets (so no --preset); --config and --set apply to every cell, e.g. --set town.route=2, but may not set what the matrix sets."""
    from ..bench.robustness import parse_matrix, run_robustness

    matrix = parse_matrix(changes, traffic, sensors, skew, configs)
    summary = run_robustness(
        spec,
        settings.config,
        list(settings.overrides),
        matrix,
        runs=runs,
        workers=workers,
        out_dir=out,
        real=real,
        cache_root=cache,
        console=err,
        record=record,
        ray=ray,
    )
    if as_json:
        emit_json(summary)
    else:
        err.print((out / "report.md").read_text(), markup=False, highlight=False, soft_wrap=True)
        err.print(f"report, cells.csv, summary.json and heatmap.png in {out}", highlight=False)


@bench_app.command("integrity")
@with_source()
@with_settings(world=True)
def bench_integrity(
    runs: Annotated[int, typer.Option("--runs", help="Seeded runs per case and world (seeds 0…N−1).")] = 1,
    workers: Annotated[int, typer.Option("--workers", help="Worker processes.")] = 2,
    out: Annotated[Path, typer.Option("--out", help="Directory for the runs, report.md and summary.json.")] = Path(
        "out/bench-integrity"
    ),
    cases: Annotated[
        str,
        typer.Option(
            "--cases",
            help="Cases: s2m-at-0, s2m-at-20, s2m-at-50, s2m-at-100 (S2M held back until that scan), wrong-place (a start around a look-alike street), kidnap, moved (the particles moved 60 m unannounced).",
        ),
    ] = "s2m-at-0,s2m-at-20,s2m-at-50,s2m-at-100,wrong-place,kidnap,moved",
    sensors: Annotated[
        str, typer.Option("--sensors", help="Sensors of the town's drive: hdl64e, vlp16, vlp32c, os1-128.")
    ] = "hdl64e,vlp16,os1-128",
    real: Annotated[
        bool | None,
        typer.Option("--real/--no-real", help="Also the real KITTI drive (default: where its data is present)."),
    ] = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Never green while wrong: S2M late, a wrong-place start, a kidnap, an estimate moved unannounced.

    Per case: false fires, scans called localized while more than 5 m off, scans to recover (or to say lost), spurious relocalizations. The town's first 300 scans unless --scans says otherwise."""
    from ..bench.integrity import run_integrity

    summary = run_integrity(
        spec,
        settings.config,
        list(settings.overrides),
        [c.strip() for c in cases.split(",") if c.strip()],
        [s.strip() for s in sensors.split(",") if s.strip()],
        settings.world,
        runs=runs,
        workers=workers,
        out_dir=out,
        real=real,
        cache_root=cache,
        console=err,
        preset=settings.preset,
    )
    if as_json:
        emit_json(summary)
    else:
        err.print((out / "report.md").read_text(), markup=False, highlight=False, soft_wrap=True)
        err.print(f"report and summary.json in {out}", highlight=False)


@bench_app.command("peers")
@with_source()
@with_settings(world=True)
def bench_peers(
    global_scans: Annotated[
        int,
        typer.Option(
            "--global-scans", min=1, help="Random scans each global method registers against the whole map, per source."
        ),
    ] = 20,
    track_scans: Annotated[
        int, typer.Option("--track-scans", min=3, help="Scans tracked from the start before the kidnap.")
    ] = 250,
    after_kidnap: Annotated[
        int, typer.Option("--after-kidnap", min=1, help="Scans played after the kidnap (~50 m ahead along the drive).")
    ] = 150,
    real: Annotated[
        bool | None,
        typer.Option(
            "--real/--no-real",
            help="Also the global part on the real KITTI drive (default: where its data is present).",
        ),
    ] = None,
    paper: Annotated[
        bool | None,
        typer.Option(
            "--paper/--no-paper",
            help="Also the paper's figures beside a run of the town laid along KITTI 05 (default: where its poses are present).",
        ),
    ] = None,
    paper_scans: Annotated[
        int, typer.Option("--paper-scans", min=10, help="Scans of the KITTI 05 town the paper's part plays.")
    ] = 300,
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """lidarloc beside what a user would run instead, same scans, map and machine: global
    localization against open3d's FPFH + RANSAC and FGR, and against KISS-Matcher and MapClosures
    where `pip install 'lidarloc[peers]'` installed them (each skipped with its reason where not),
    tracking against scan-to-map GICP (small_gicp) from the true start, recovery after a kidnap,
    and the paper's own figures.

    The source (default: the built-in town) holds the global and tracking parts; on the town the
    drive is lived-in unless --world kind says otherwise."""
    from ..bench.peers import run as run_bench
    from ..bench.peers_optional import notes

    cfg = settings.load(seed=seed)
    with progress_bar() as bar:
        tasks: dict = {}

        def progress(what, i, n):
            if what not in tasks:
                tasks[what] = bar.add_task(what, total=n)
            bar.update(tasks[what], completed=i, total=n)

        result = run_bench(
            spec,
            cfg,
            global_scans=global_scans,
            track_scans=track_scans,
            after_kidnap=after_kidnap,
            real=real,
            paper=paper,
            paper_scans=paper_scans,
            cache_root=cache,
            progress=progress,
        )
    for line in notes(result):  # on stderr: --json's output stays one JSON document
        err.print(line, markup=False, highlight=False, soft_wrap=True)
    show_bench_result("peers", result, as_json)


@bench_app.command("city")
@with_source()
@with_settings()
def bench_city(
    global_scans: Annotated[
        int, typer.Option("--global-scans", min=1, help="Scans along the city's drive matched against the whole city.")
    ] = 200,
    peer_scans: Annotated[
        int,
        typer.Option(
            "--peer-scans",
            min=0,
            help="Of those, how many FPFH + RANSAC registers (seconds each on the town, minutes each on a "
            "city: a few under --peer-budget-min say enough).",
        ),
    ] = 10,
    peer_budget_min: Annotated[
        float,
        typer.Option(
            "--peer-budget-min",
            min=0.0,
            help="FPFH + RANSAC is stopped after this many minutes (building its feature map included; the "
            "map's features are kept beside it for the next run) and reports the scans it finished and where "
            "it stopped.",
        ),
    ] = 60.0,
    peer_budget_gb: Annotated[
        float | None,
        typer.Option(
            "--peer-budget-gb",
            min=0.0,
            help="FPFH + RANSAC is also stopped once its own memory passes this many GB (the mapped map's "
            "pages not counted; default: what the machine has available when it starts, less a reserve of 5 % "
            "of its memory (at least 1 GB), at most three quarters of it); it is also stopped whenever the "
            "machine's available memory falls to that reserve.",
        ),
    ] = None,
    tile_m: Annotated[float, typer.Option("--tile-m", help="Side of the lookup table's tiles (m).")] = 400.0,
    whole_map: Annotated[
        bool, typer.Option("--whole-map/--no-whole-map", help="Also today's whole-map search on the same scans.")
    ] = True,
    exact_scans: Annotated[
        int,
        typer.Option(
            "--exact-scans",
            min=0,
            help="Of the global scans, how many the exact tiled search over the whole city also matches, the "
            "reference the candidates are compared with (tens of seconds a scan on a 16 km² city).",
        ),
    ] = 10,
    localize_runs: Annotated[
        int,
        typer.Option(
            "--localize-runs",
            min=0,
            help="Also this many seeded runs of full localization on the city's drive (bench localize; "
            "each a whole drive, minutes on a city) for localize_success; with --set localize.clock=realtime "
            "on the real-time clock, for first_fix_s_median (the drive's seconds to the first fix; --workers 1).",
        ),
    ] = 0,
    workers: Annotated[
        int,
        typer.Option(
            "--workers",
            min=1,
            help="Worker processes for --localize-runs; with --ray, the Ray workers of the exact search.",
        ),
    ] = 2,
    ray: Annotated[
        str | None,
        typer.Option(
            "--ray",
            metavar="local|auto|ray://HOST:PORT",
            help=f"The exact search over the whole city split by tiles among --workers Ray workers: {RAY_HELP} "
            "(its answers are the same as on this machine; every node reads the city's tiles from the cache at "
            "the same path).",
        ),
    ] = None,
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            help="Directory for the global matches and FPFH + RANSAC's registrations, one row a scan, and "
            "the --localize-runs runs: a run stopped at any moment resumes there (same source, configuration "
            "and code).",
        ),
    ] = Path("out/bench-city"),
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """lidarloc holding a city (by default the 4 × 4 km city, a 10-minute drive through it):
    the tiled tables' build and cache size, a later start and the memory a drive keeps resident
    (in a fresh process), global localization over the whole city (the place index's candidates
    verified by the exact search and GICP, and the whole-map second opinion) beside the exact
    tiled search, the whole-map search and FPFH + RANSAC; with --localize-runs N, N seeded runs of full localization from a start
    spread over the whole city. --set town.extent_m=E (or any source option) measures another city.
    The city's tables are the lookup at 0.5 m read by tiles (pf.lookup_resolution=0.5,
    pf.lookup_tile_m=400) unless --set says otherwise."""
    from ..bench.city import localize_figures, stopped_line
    from ..bench.city import run as run_bench

    # A city's tables: the lookup at 0.5 m, read by tiles. At the default 0.25 m a 16 km² city's
    # lookup tiles store 5–7 times the bricks and take 5–6 times the CPU to build (~15 min on 2
    # cores, over the 10 the build is given); at 0.5 m runs on the city localize to 0.10–0.19 m
    # RMSE (BENCHMARKS.md, "A city").
    overrides = ["town.extent_m=4000", "town.n_scans=6000", "pf.lookup_resolution=0.5", "pf.lookup_tile_m=400"]
    cfg = settings.load(seed=seed, first=overrides)
    try:
        with progress_bar() as bar:
            result = run_bench(
                spec,
                cfg,
                cache_root=cache,
                global_scans=global_scans,
                peer_scans=peer_scans,
                peer_budget_s=peer_budget_min * 60.0,
                peer_budget_mb=None if peer_budget_gb is None else peer_budget_gb * 1024.0,
                tile_m=tile_m,
                whole_map=whole_map,
                exact_scans=exact_scans,
                progress=stage_progress(bar),
                rows_dir=out / "global",
                peer_rows_dir=out / "fpfh-ransac",
                ray=ray,
                ray_workers=workers,
            )
    except KeyboardInterrupt:
        sys.stdout.flush()
        line = stopped_line(out / "global", out / "fpfh-ransac")
        sys.stderr.write(line + "\n")  # one unwrapped line, as fail() writes
        sys.stderr.flush()
        # Not a normal exit: the interrupted search is still running in numba on its threads,
        # which the interpreter's exit would wait for (a minute or more over a city). Every row
        # done is on disk, and FPFH + RANSAC's process and the probe's are gone already.
        os._exit(130)
    if localize_runs:  # its own progress bar: after the one above has closed
        result.update(localize_figures(spec, cfg, localize_runs, workers, out / "localize", cache_root=cache))
    show_bench_result("city", result, as_json)


@bench_app.command("shards")
@with_source()
@with_settings()
def bench_shards(
    global_scans: Annotated[
        int, typer.Option("--global-scans", min=1, help="Scans of the city's drive searched over the whole city.")
    ] = 5,
    workers: Annotated[
        list[int],
        typer.Option("--workers", min=1, help="Ray workers to search with, one count at a time (repeatable)."),
    ] = [1, 2],  # noqa: B006  (typer's default for a repeatable option)
    ray: Annotated[
        str, typer.Option("--ray", metavar="local|auto|ray://HOST:PORT", help=f"Where the workers run: {RAY_HELP}.")
    ] = "local",
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """The exact search over the whole city split by tiles among Ray workers: its time with each
    count of --workers beside this machine's search (threads, one per core) on the same scans,
    the speed-up of the most workers over the fewest, and whether every answer (pose, score,
    candidates) is this machine's. The city as bench city holds it (by default the 4 × 4 km city;
    --set town.extent_m=1000 the 1 × 1 km one), its tiles built or read from the cache."""
    from ..bench.shards import run as run_bench

    cfg = settings.load(seed=seed, first=["town.extent_m=4000", "town.n_scans=6000"])
    with progress_bar() as bar:
        result = run_bench(spec, cfg, cache, global_scans, tuple(sorted(set(workers))), ray, stage_progress(bar))
    show_bench_result("shards", result, as_json)
