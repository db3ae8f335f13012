"""The live run's benchmarks: ``soak`` (the viewer over a long run: memory, descriptors, threads,
child processes, recordings, late scans), ``clients`` (many tabs and bad ones), ``faults`` (a
killed child process) and ``odometry-lag`` (KISS-ICP behind the clock)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..options import SOURCE_CHOICE, CacheOpt, JsonOpt, given, with_settings, with_source
from .bench_costs import show_bench_result
from .groups import bench_app


@bench_app.command("soak")
@with_source()
@with_settings()
def bench_soak(
    ctx: typer.Context,
    minutes: Annotated[float, typer.Option("--minutes", min=0.1, help="How long to play after the start.")] = 120.0,
    sample_s: Annotated[float, typer.Option("--sample-s", min=1.0, help="Seconds between samples.")] = 10.0,
    out: Annotated[Path, typer.Option("--out", help="Folder for soak.csv, soak.png and the recordings.")] = Path(
        "out/bench-soak"
    ),
    client: Annotated[
        str,
        typer.Option(
            "--client",
            metavar="chromium|socket|none",
            help="The tab attached: headless Chromium, a websocket tab that reads everything without "
            "drawing it (no software WebGL competing for the cores), or none.",
        ),
    ] = "chromium",
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Play `lidarloc demo` (`view` with a source) in real time in a loop for --minutes, one tab attached
    (--client) and recording on; sample its memory, descriptors, threads, child processes
    and recordings every --sample-s seconds. Targets: RSS growth ≤ 50 MB after the first loop,
    constant descriptors / threads / children, no late scans beyond the first loop's."""
    from ..bench.common import source_args
    from ..bench.soak import CLIENTS
    from ..bench.soak import run as run_bench

    if client not in CLIENTS:
        raise typer.BadParameter(f"{client!r} is not one of {', '.join(CLIENTS)}", param_hint="--client")

    settings.load()
    if given(ctx, SOURCE_CHOICE + ("map",)):
        command = ["view", *source_args(spec)]
    else:
        command = ["demo"] + (["--scans", str(spec.scans)] if spec.scans is not None else [])
    result = run_bench(
        command + settings.args(),
        minutes,
        out,
        sample_s=sample_s,
        cache=None if cache is None else str(cache),
        client=client,
    )
    show_bench_result("soak", result, as_json)


@bench_app.command("clients")
@with_source()
@with_settings()
def bench_clients(
    tabs: Annotated[int, typer.Option("--tabs", min=1, help="Browser tabs open at once.")] = 5,
    phase_s: Annotated[float, typer.Option("--phase-s", min=5.0, help="Seconds per phase.")] = 45.0,
    churn_s: Annotated[
        float | None,
        typer.Option(
            "--churn-s",
            min=5.0,
            help="Seconds of the websocket tab connecting and disconnecting (default: --phase-s; longer "
            "where 20 connections take more); thousands of connections pin the memory per connection down under the allocator's noise.",
        ),
    ] = None,
    tab_priority: Annotated[
        str,
        typer.Option(
            "--tab-priority",
            metavar="idle|normal",
            help="CPU priority of the tabs' Chromium and of the websocket clients' process: idle (they use "
            "only what the viewer leaves, as clients on their users' own machines would) or normal "
            "(clients and viewer share the cores).",
        ),
    ] = "idle",
    tab_kind: Annotated[
        str,
        typer.Option(
            "--tab-kind",
            metavar="chromium|socket",
            help="The tabs: headless Chromium, or websocket tabs that read everything the server sends "
            "without drawing it (what serving tabs costs the viewer, without browsers on the machine).",
        ),
    ] = "chromium",
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """The live viewer in real time with no client, --tabs headless Chromium tabs, one more tab
    connecting and disconnecting in a loop (a browser tab, then a websocket tab: hundreds of
    connections), and a slow client: the filter's rate, the server-side update and memory per
    phase. Targets: the real-time rate kept, update ≤ 20 ms, no growth per connection, a slow
    client slows nothing."""
    from ...core.localizer import Localizer
    from ..bench.chromium import TAB_PRIORITIES
    from ..bench.clients import TAB_KINDS
    from ..bench.clients import run as run_bench
    from ..options import open_source
    from ..viewer.heap import limit_arenas

    if tab_priority not in TAB_PRIORITIES:
        raise typer.BadParameter(
            f"{tab_priority!r} is not one of {', '.join(TAB_PRIORITIES)}", param_hint="--tab-priority"
        )
    if tab_kind not in TAB_KINDS:
        raise typer.BadParameter(f"{tab_kind!r} is not one of {', '.join(TAB_KINDS)}", param_hint="--tab-kind")
    cfg = settings.load()
    limit_arenas()  # the viewer runs in this process: as `view` and `demo` set it up
    loc = Localizer(open_source(spec, cfg), cfg, cache, defer_s2m=True)
    try:
        result = run_bench(
            loc, tabs=tabs, phase_s=phase_s, tab_priority=tab_priority, tab_kind=tab_kind, churn_s=churn_s
        )
    finally:
        loc.close()
    show_bench_result("clients", result, as_json)


@bench_app.command("faults")
def bench_faults(
    scans: Annotated[int, typer.Option("--scans", min=10, help="Scans of the built-in town played per kill.")] = 45,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Kills per child process (S2M, KISS-ICP).")] = 3,
    as_json: JsonOpt = False,
    cache: CacheOpt = None,
):
    """A child process killed mid-run (SIGKILL): how fast the run notices it and goes on with a new one.

    The built-in town in the real-time clock; a third of the way in, the S2M or the KISS-ICP child is killed; the time from the kill to its replacement's start (the run's `restarted` event). Target: within 1 s."""
    from ..bench.faults import run

    show_bench_result("faults", run(scans, repeats, cache), as_json)


@bench_app.command("odometry-lag")
def bench_odometry_lag(
    pause_ms: Annotated[
        float,
        typer.Option(
            "--pause-ms", min=0.0, help="How long the KISS-ICP child is stopped in every 100 ms (0: not at all)."
        ),
    ] = 30.0,
    runs: Annotated[int, typer.Option("--runs", min=1, help="Runs (seeds 0…N−1).")] = 3,
    scans: Annotated[int | None, typer.Option("--scans", min=10, help="Scans of the built-in town per run.")] = None,
    out: Annotated[Path, typer.Option("--out", help="Folder for the runs.")] = Path("out/bench-odometry-lag"),
    as_json: JsonOpt = False,
    cache: CacheOpt = None,
):
    """The odometry behind the clock: whether a filter that S2M cannot correct stays green while wrong.

    The built-in town's drive in real time (`lidarloc run --clock realtime`, one process per run), its KISS-ICP child stopped --pause-ms of every 100 ms: a machine whose other work takes that share of the odometry's core. Per run: scans green while more than 5 m off, false fires, withdrawals, losses, RMSE after localization, matches landed and accepted, the odometry's lag behind the current scan, late scans."""
    from ..bench.odometry_lag import run

    show_bench_result("odometry-lag", run(out, pause_ms, runs, scans, cache), as_json)
