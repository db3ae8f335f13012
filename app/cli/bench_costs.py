"""``lidarloc bench`` commands that time or size one part: the town, the map, the filter, matching, the viewer, start-up, stopping."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from ...core.errors import LidarlocError
from ..bench.common import DATA_ENV, DEFAULT_DATA, REAL_DRIVE, REAL_DRIVE_DATE
from ..console import emit_json, err, progress_bar, show_result
from ..options import (
    OWN_DATA,
    SOURCE_CHOICE,
    SOURCE_OPTIONS,
    CacheOpt,
    JsonOpt,
    given,
    open_source,
    with_settings,
    with_source,
)
from .groups import bench_app


def show_bench_result(name: str, result: dict, as_json: bool) -> None:
    if as_json:
        emit_json(result)
    else:
        show_result(f"lidarloc bench {name}", result)


def _real_drive_unless_given(ctx: typer.Context, spec, bench: str):
    """``spec`` when a source was chosen, else the real KITTI drive (with ``spec``'s --scans and --map)."""
    from ..bench.common import require_real_drive

    if given(ctx, SOURCE_CHOICE):
        return spec
    return replace(require_real_drive(bench, spec.scans), map=spec.map)


SeedOpt = Annotated[int | None, typer.Option("--seed", min=0, help="Random seed (default: the config's).")]
_MAP_PANEL = "Source (default: the built-in town and the real KITTI drive)"
_PF_PANEL = f"Source (default: KITTI raw {REAL_DRIVE_DATE} drive {REAL_DRIVE} in ${DATA_ENV} or {DEFAULT_DATA})"
_VIEWER_PANEL = "Source (none: the inputs are synthetic)"


@bench_app.command("town")
@with_source(exclude=OWN_DATA)
@with_settings()
def bench_town(
    as_json: JsonOpt = False,
    spec=None,
    cfg=None,
):
    """Town generation time and simulated-scan time.

    The built-in town only: --kitti-odometry and --kitti-raw do not apply."""
    from ..bench.town import run as run_bench

    show_bench_result("town", run_bench(spec, cfg), as_json)


@bench_app.command("map")
@with_source(_MAP_PANEL)
@with_settings()
def bench_map(
    ctx: typer.Context,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
):
    """Prior-map build and cache-load times, default town and the real drive (fresh cache).

    With a source option, that source's map only."""
    from ..bench.map import default_sources, source_name
    from ..bench.map import run as run_bench

    settings.load()  # a bad config fails here, not in the first child process
    sources = {source_name(spec): spec} if given(ctx, SOURCE_CHOICE + ("map",)) else default_sources(spec)
    show_bench_result("map", run_bench(sources, settings.args()), as_json)


@bench_app.command("mapfile")
def bench_mapfile(
    points: Annotated[int, typer.Option("--points", min=1000, help="Points of the generated map file.")] = 50_000_000,
    as_json: JsonOpt = False,
):
    """Loading a large .pcd map and building its lookup table (target ≤ 2 min, ≤ 6 GB at 50 M points).

    The map is generated in a temporary directory; reading, voxelizing and the lookup table are timed in a fresh process, then road removal apart."""
    from ..bench.mapfile import run as run_bench

    show_bench_result("mapfile", run_bench(points), as_json)


@bench_app.command("bag")
@with_source(_PF_PANEL)
@with_settings()
def bench_bag(
    ctx: typer.Context,
    total: Annotated[
        int, typer.Option("--total", min=1, help="Scans in the bag (the source's scans, repeated).")
    ] = 300,
    storage: Annotated[str, typer.Option("--storage", help="Bag kind: mcap, sqlite3 (ROS 2) or ros1.")] = "mcap",
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Times the whole bag is read (median).")] = 3,
    as_json: JsonOpt = False,
    spec=None,
    cfg=None,
):
    """Reading scans from a bag: a PointCloud2 bag of the source's scans, written in a temporary
    directory, opened (index) and read scan by scan (decode); target ≥ 200 scans/s.

    Default source: the real KITTI raw drive (64-beam scans); --town-seed N for the town."""
    from ..bench.bag import run as run_bench

    spec = _real_drive_unless_given(ctx, spec, "bag")
    show_bench_result("bag", run_bench(spec, cfg, total=total, storage=storage, repeats=repeats), as_json)


@bench_app.command("pf")
@with_source(_PF_PANEL)
@with_settings()
def bench_pf(
    ctx: typer.Context,
    particles: Annotated[
        int | None, typer.Option("--particles", min=1, help="Particles (default: the config's).")
    ] = None,
    seed: SeedOpt = None,
    big_map: Annotated[
        bool, typer.Option("--big-map/--no-big-map", help="Time the lookup table of a KITTI-05-sized synthetic map.")
    ] = True,
    town_lookup: Annotated[
        bool, typer.Option("--town/--no-town", help="Time the lookup table of the default town's map.")
    ] = True,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
):
    """Particle-filter step time and lookup-table cost, against their targets.

    Default source: the real KITTI raw drive; --town-seed N for the town."""
    from ..bench.pf import run as run_bench

    cfg = settings.load(seed=seed)
    if particles is not None:
        cfg.pf.n_particles = particles
    spec = _real_drive_unless_given(ctx, spec, "pf")
    show_bench_result("pf", run_bench(spec, cfg, big_map=big_map, town=town_lookup), as_json)


@bench_app.command("surface")
@with_source(_PF_PANEL)
@with_settings()
def bench_surface(
    ctx: typer.Context,
    samples: Annotated[int, typer.Option("--samples", min=1, help="Scans to time, spread over the sequence.")] = 10,
    repeats: Annotated[
        int, typer.Option("--repeats", min=1, help="Surfaces per scan, each around another offset of the truth.")
    ] = 3,
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
):
    """The viewer's likelihood surface: time of an 81 × 81 grid (target ≤ 150 ms) and its maximum's error.

    Default source: the real KITTI raw drive; --town-seed N for the town."""
    from ..bench.surface import run as run_bench

    cfg = settings.load(seed=seed)
    spec = _real_drive_unless_given(ctx, spec, "surface")
    show_bench_result("surface", run_bench(spec, cfg, scans=samples, repeats=repeats), as_json)


@bench_app.command("filter")
@with_source(_PF_PANEL)
@with_settings()
def bench_filter(
    ctx: typer.Context,
    seeds: Annotated[int, typer.Option("--seeds", min=1, help="Runs per likelihood option (seeds 0…N−1).")] = 3,
    option: Annotated[
        list[str] | None,
        typer.Option(
            "--option",
            help="A likelihood option to study (repeatable), each over the paper's likelihood: paper, default, T=<number>, per-point mean, unexplained 0.1 (default: paper, default, T=10, T=100, per-point mean, unexplained 0.1).",
        ),
    ] = None,
    as_json: JsonOpt = False,
    spec=None,
    cfg=None,
    cache: CacheOpt = None,
):
    """Does the filter's uncertainty mean something while it tracks? Each likelihood option started
    around the truth, no S2M: N_eff share, error and 2σ consistency (target ≥ 85 %).

    Default source: the real KITTI raw drive; --town-seed N for the town."""
    from ..bench.filter import run as run_bench

    spec = _real_drive_unless_given(ctx, spec, "filter")
    with progress_bar() as bar:
        task = bar.add_task("filter study", total=None)
        result = run_bench(
            spec,
            lambda s: open_source(s, cfg, err),
            cfg,
            seeds=seeds,
            options=option,
            cache_root=cache,
            progress=lambda i, n: bar.update(task, completed=i, total=n),
        )
    show_bench_result("filter", result, as_json)


@bench_app.command("s2m")
@with_source()
@with_settings(world=True)
def bench_s2m(
    matches: Annotated[
        int, typer.Option("--matches", min=1, help="Random scans to match (at most all of the source's).")
    ] = 350,
    seed: SeedOpt = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="Write the result, per-scan rows and RMSE histogram PNG here.")
    ] = None,
    gicp_comparison: Annotated[
        bool, typer.Option("--gicp-comparison/--no-gicp-comparison", help="Compare small_gicp with open3d GICP.")
    ] = True,
    cell_study: Annotated[bool, typer.Option("--cell-study", help="Also match with every BEV cell value.")] = False,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
):
    """Global/local M3RSM matching: success rate, latency, RMSE (the paper's experiment).

    On the built-in town the scans come from a lived-in drive unless --world kind says otherwise."""
    from ..bench.s2m import run as run_bench

    cfg = settings.load(seed=seed)
    show_bench_result(
        "s2m",
        run_bench(spec, cfg, matches=matches, out_dir=out, compare_gicp=gicp_comparison, cell_study=cell_study),
        as_json,
    )


@bench_app.command("rpe")
@with_source()
@with_settings()
def bench_rpe(
    convergence: Annotated[
        list[float] | None, typer.Option("--convergence", help="KISS-ICP convergence criteria to compare (repeatable).")
    ] = None,
    as_json: JsonOpt = False,
    spec=None,
    cfg=None,
):
    """KISS-ICP odometry: registration time and error against the truth per convergence setting.

    Registers the first 300 scans unless --scans says otherwise (at least 11)."""
    from ..bench.rpe import run as run_bench

    show_bench_result(
        "rpe", run_bench(spec, cfg, **({"convergences": tuple(convergence)} if convergence else {})), as_json
    )


@bench_app.command("viewer")
@with_source(_VIEWER_PANEL)
@with_settings()
def bench_viewer(
    ctx: typer.Context,
    as_json: JsonOpt = False,
    spec=None,
    cfg=None,
):
    """Server-side cost of one display update, and what a user waits for in a real browser.

    Display updates: synthetic inputs sized like a real drive (the source options do not apply).

    In headless Chromium, on the short town: the first likelihood surface, Kidnap's display resume, Top-down view."""
    from ..bench.viewer import run as run_bench

    chosen = given(ctx, SOURCE_OPTIONS)
    if chosen:
        raise LidarlocError(
            f"bench viewer times synthetic display updates and reads no sequence; "
            f"--{chosen[0].replace('_', '-')} does not apply"
        )
    show_bench_result("viewer", run_bench(n_particles=cfg.pf.n_particles), as_json)


@bench_app.command("startup")
@with_source()
@with_settings()
def bench_startup(
    ctx: typer.Context,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Cached starts after the first.")] = 3,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
):
    """Start-up time of `lidarloc demo`: first start (empty cache), then cached starts.

    With a source option, the start-up time of `lidarloc view` on that source."""
    from ..bench.common import source_args
    from ..bench.startup import run as run_bench

    settings.load()
    if given(ctx, SOURCE_CHOICE + ("map",)):
        command = ["view", *source_args(spec)]
    else:
        command = ["demo"] + (["--scans", str(spec.scans)] if spec.scans is not None else [])
    show_bench_result("startup", run_bench(command + settings.args(), repeats=repeats), as_json)


@bench_app.command("stop")
@with_source()
@with_settings()
def bench_stop(
    ctx: typer.Context,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Stops per clock and delay.")] = 3,
    delay: Annotated[
        list[float] | None,
        typer.Option(
            "--delay",
            min=0.0,
            help="Seconds after 'localizing' (the viewer: after 'ready') to press Ctrl-C (repeatable).",
        ),
    ] = None,
    viewer: Annotated[
        bool,
        typer.Option(
            "--viewer", help="Stop the live viewer (`demo`, or `view` on a source given) instead (target ≤ 1 s)."
        ),
    ] = False,
    busy: Annotated[
        int,
        typer.Option(
            "--busy",
            min=0,
            help="Processes spinning on a core each beside the command once it is under way (from 'localizing' or 'ready' on).",
        ),
    ] = 0,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """How fast Ctrl-C stops `lidarloc run` on the town, both clocks (target ≤ 2 s); with
    --viewer, the live viewer (target ≤ 1 s).

    Runs the town's first 300 scans unless the source options say otherwise."""
    from ..bench.common import source_args
    from ..bench.stop import run as run_bench

    settings.load()
    spec = replace(spec, scans=300 if spec.scans is None else spec.scans)
    if not viewer:
        command = None
    elif given(ctx, SOURCE_CHOICE + ("map",)):
        command = ["view", *source_args(spec), *settings.args()]
    else:
        command = ["demo", "--scans", str(spec.scans), *settings.args()]
    show_bench_result(
        "stop",
        run_bench(
            source_args(spec) + settings.args(),
            repeats=repeats,
            cache=None if cache is None else str(cache),
            busy=busy,
            viewer=command,
            **({"delays_s": tuple(delay)} if delay else {}),
        ),
        as_json,
    )


RecordBenchOpt = Annotated[
    bool,
    typer.Option(
        "--record",
        help="Record every run into its folder (runs/seed_NNN/recording: scrub, branch and compare them later).",
    ),
]
