"""``lidarloc demo`` and ``lidarloc view``: the live viewer, on the built-in town or any source,
or on recorded runs; its recordings kept under a disk budget."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from ...core.errors import LidarlocError
from ..console import err
from ..options import CacheOpt, InitOpt, ScansOpt, source_spec, with_settings, with_source
from ..viewer.budget import DEFAULT_KEEP_RUNS, DEFAULT_MAX_RECORD_GB
from ..viewer.token_gate import token_from
from .groups import app


# -------------------------------------------------------------------------------------- viewer
def _serve(
    spec,
    cfg,
    host,
    port,
    cache,
    open_browser,
    autoplay=False,
    record_dir=None,
    preset=None,
    record=True,
    foxglove_port=None,
    loop=False,
    keep_runs=DEFAULT_KEEP_RUNS,
    max_record_gb=DEFAULT_MAX_RECORD_GB,
    token=None,
):
    from ..viewer.heap import limit_arenas
    from ..viewer.serve import serve_until_interrupted

    limit_arenas()  # before the viewer's threads start (see heap.py)
    serve_until_interrupted(
        spec,
        cfg,
        host=host,
        port=port,
        cache_root=cache,
        console=err,
        open_browser=open_browser,
        autoplay=autoplay,
        record_dir=record_dir,
        preset=preset,
        record=record,
        foxglove_port=foxglove_port,
        loop=loop,
        keep_runs=None if keep_runs == 0 else keep_runs,
        max_record_gb=None if max_record_gb == 0 else max_record_gb,
        token=token,
    )


HostOpt = Annotated[
    str,
    typer.Option(
        "--host",
        help="Interface to bind (default loopback only). Any other (0.0.0.0) lets anyone who can reach the port "
        "drive the localizer and read the map, unless --token is given.",
    ),
]
TokenOpt = Annotated[
    str | None,
    typer.Option(
        "--token",
        help="Let only browsers that bring this token use the viewer (letters, digits, - and _; auto: a random "
        "one). The printed URL carries it; open that URL once and the browser remembers it. Also read from "
        "the LIDARLOC_VIEWER_TOKEN environment variable, which other users cannot see in ps.",
        show_default=False,
    ),
]
LoopOpt = Annotated[
    bool,
    typer.Option(
        "--loop",
        help="At the end of the drive, start again (recorded as a new run); a line per loop says how "
        "many scans were late.",
    ),
]
KeepRunsOpt = Annotated[
    int,
    typer.Option(
        "--keep-runs",
        min=0,
        help="Keep at most this many recorded runs under the runs folder (the cache's runs/ or --record-dir), "
        "oldest removed first, never the one playing; 0: no limit.",
    ),
]
MaxRecordGbOpt = Annotated[
    float,
    typer.Option(
        "--max-record-gb",
        min=0.0,
        help="Keep the recorded runs under this many GB in all, oldest removed first; a run that alone reaches "
        "it keeps recording its newest steps as a rolling window (its oldest ones are dropped; the page says "
        "so once); 0: no limit.",
    ),
]
PortOpt = Annotated[int, typer.Option("--port", help="Port for the viewer.")]
AutoplayOpt = Annotated[
    bool,
    typer.Option(
        "--autoplay",
        help="Start playing as soon as the localizer is ready (default: when the first browser tab opens).",
    ),
]
RecordDirOpt = Annotated[
    Path | None,
    typer.Option(
        "--record-dir",
        help="Folder for the runs the viewer plays, each start, restart and branch in a folder of its own "
        "(default: a new runs/<date-time> folder under the cache directory).",
    ),
]
NoRecordViewOpt = Annotated[
    bool,
    typer.Option(
        "--no-record",
        help="Do not record what the viewer plays (no disk use; the timeline and Branch from here are then off).",
    ),
]
FoxglovePortOpt = Annotated[
    int | None,
    typer.Option(
        "--foxglove-port",
        min=0,
        help="Also stream the live run to Foxglove (Open connection → Foxglove WebSocket "
        "ws://HOST:PORT), in the channels of export --foxglove.",
    ),
]
RunOpt = Annotated[
    list[Path] | None,
    typer.Option(
        "--run",
        help="Open a recorded run folder instead of localizing (repeat once to compare two runs of the same "
        "source side by side); the map and scans come from the source the run names.",
    ),
]
AtOpt = Annotated[
    int | None,
    typer.Option(
        "--at",
        metavar="SCAN",
        help="With --run: open the run at this scan (the timeline shows it first), e.g. the scan "
        "`lidarloc corpus compare` names.",
        show_default=False,
    ),
]


StalenessOpt = Annotated[
    Path | None,
    typer.Option(
        "--staleness",
        metavar="DIR",
        help="With --run: show the stale places of `lidarloc corpus staleness` (its --out folder) as a layer.",
        show_default=False,
    ),
]


@app.command()
@with_settings()
def demo(
    host: HostOpt = "127.0.0.1",
    port: PortOpt = 8080,
    seed: Annotated[int | None, typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    scans: ScansOpt = None,
    settings=None,
    cache: CacheOpt = None,
    open_browser: Annotated[bool, typer.Option("--open/--no-open", help="Open a browser tab.")] = False,
    autoplay: AutoplayOpt = False,
    record_dir: RecordDirOpt = None,
    no_record: NoRecordViewOpt = False,
    foxglove_port: FoxglovePortOpt = None,
    loop: LoopOpt = False,
    keep_runs: KeepRunsOpt = DEFAULT_KEEP_RUNS,
    max_record_gb: MaxRecordGbOpt = DEFAULT_MAX_RECORD_GB,
    token: TokenOpt = None,
):
    """The live demo on the built-in town: browse to the printed URL."""
    token = token_from(token)  # a bad token fails before anything starts
    cfg = settings.load(seed=seed)
    _serve(
        source_spec(town_seed=cfg.town.seed, scans=scans),
        cfg,
        host,
        port,
        cache,
        open_browser,
        autoplay,
        record_dir=record_dir,
        preset=settings.preset,
        record=not no_record,
        foxglove_port=foxglove_port,
        loop=loop,
        keep_runs=keep_runs,
        max_record_gb=max_record_gb,
        token=token,
    )


@app.command()
@with_source()
@with_settings()
def view(
    host: HostOpt = "127.0.0.1",
    port: PortOpt = 8080,
    seed: Annotated[int | None, typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    init: InitOpt = None,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
    open_browser: Annotated[bool, typer.Option("--open/--no-open", help="Open a browser tab.")] = False,
    autoplay: AutoplayOpt = False,
    record_dir: RecordDirOpt = None,
    no_record: NoRecordViewOpt = False,
    run: RunOpt = None,
    at: AtOpt = None,
    staleness: StalenessOpt = None,
    foxglove_port: FoxglovePortOpt = None,
    loop: LoopOpt = False,
    keep_runs: KeepRunsOpt = DEFAULT_KEEP_RUNS,
    max_record_gb: MaxRecordGbOpt = DEFAULT_MAX_RECORD_GB,
    token: TokenOpt = None,
):
    """The live viewer on any sequence source, or on recorded runs (--run DIR, twice to compare; --at SCAN opens them there)."""
    token = token_from(token)  # a bad token fails before anything starts
    if at is not None and not run:
        raise LidarlocError("--at opens a recorded run at a scan: give the run with --run DIR")
    if staleness is not None and not run:
        raise LidarlocError("--staleness is a layer over recorded runs: give the run with --run DIR")
    if run:
        from ..viewer.runs import serve_runs

        if foxglove_port is not None:
            raise LidarlocError(
                "--foxglove-port streams a live run; for a recorded run: lidarloc export RUN "
                "--foxglove OUT.mcap, and open that file in Foxglove"
            )

        serve_runs(
            run,
            host=host,
            port=port,
            cache_root=cache,
            open_browser=open_browser,
            console=err,
            token=token,
            at=at,
            staleness=staleness,
        )
        return
    cfg = settings.load(seed=seed)
    _serve(
        replace(spec, init=init),
        cfg,
        host,
        port,
        cache,
        open_browser,
        autoplay,
        record_dir=record_dir,
        preset=settings.preset,
        record=not no_record,
        foxglove_port=foxglove_port,
        loop=loop,
        keep_runs=keep_runs,
        max_record_gb=max_record_gb,
        token=token,
    )
