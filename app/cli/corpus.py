"""``lidarloc corpus``: many drives, one run each, with where along each drive it went wrong, and
two corpus runs compared."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..console import emit_json, err
from ..options import CacheOpt, JsonOpt, SetOpt
from .groups import corpus_app
from .sweeps import RayOpt, WorkersOpt, workers_for


@corpus_app.command("example")
def example(
    drives: Annotated[int, typer.Option("--drives", min=1, help="Drives in the corpus.")] = 8,
    scans: Annotated[
        int | None, typer.Option("--scans", min=1, help="Scans of each drive (default: the whole drive).")
    ] = None,
    seeds: Annotated[
        int,
        typer.Option(
            "--seeds",
            min=1,
            help="Run each drive under this many seeds (NAME-s0, NAME-s1, …): corpus compare measures the "
            "seed-to-seed noise from them.",
        ),
    ] = 1,
):
    """Print a corpus file of the built-in town's drives (town seeds × its sensors, lived-in world) on stdout.

    `lidarloc corpus run` takes it as it is; edit it into a corpus of your own logs (docs/corpus.md)."""
    from ..corpus.example import example_corpus

    typer.echo(example_corpus(drives, scans, seeds), nl=False)


@corpus_app.command("run")
def run(
    corpus: Annotated[
        Path, typer.Argument(metavar="CORPUS.yaml", help="The corpus file (YAML, docs/corpus.md).", show_default=False)
    ],
    out: Annotated[
        Path, typer.Option("--out", help="Folder of the drives' runs and corpus.json (resumed if it exists).")
    ] = Path("out/corpus"),
    workers: WorkersOpt = None,
    ray: RayOpt = None,
    set_: SetOpt = None,
    as_json: JsonOpt = False,
    cache: CacheOpt = None,
):
    """Run every drive of a corpus: one seeded replay-clock run each, and each drive's health.

    Writes DIR/drives/NAME/ (open one with `lidarloc view --run DIR/drives/NAME`) and DIR/corpus.json: each drive's summary, its first fix, withdrawals, false fires, RMSE and the stretches of scans that fitted poorly, were late or were localized in the wrong place. --set applies to every drive, after its own. Run the same command again to resume: finished drives are kept, failed ones run again. Exits with status 1 when a drive failed."""
    from ..corpus.run import run_corpus
    from ..corpus.spec import load_corpus

    overrides = list(set_ or [])
    loaded = load_corpus(corpus, overrides)
    report, tally = run_corpus(loaded, out, workers_for(workers, ray), overrides=overrides, ray=ray, cache_root=cache)
    if as_json:
        emit_json(report)
    else:
        _print_report(report)
    if tally.interrupted:
        err.print("interrupted: run the same command again to resume", highlight=False)
        raise typer.Exit(130)
    if report["drives_failed"]:
        raise typer.Exit(1)


@corpus_app.command("compare")
def compare(
    base: Annotated[
        Path, typer.Argument(metavar="BASE", help="The --out folder of the corpus run before.", show_default=False)
    ],
    new: Annotated[
        Path, typer.Argument(metavar="NEW", help="The --out folder of the corpus run after.", show_default=False)
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Folder for compare.md and compare.html (default: NEW/compare).", show_default=False
        ),
    ] = None,
    as_json: JsonOpt = False,
):
    """What got worse from one corpus run (BASE) to another (NEW), beyond the seed-to-seed noise, and where.

    Per drive of both: first fix, withdrawals, false fires, RMSE, poor-fit, wrong and unlocalized scans, median inlier share, and each stretch of poor fit, wrong or unlocalized scans NEW has and BASE lacks or that grew; each drive's first diverging scan. Regressions worst first (false fires and wrong localization before all), each with the `lidarloc view --run … --at SCAN` command that shows it. Noise is measured from the corpus: drives of one log under several seeds (docs/corpus.md). Writes compare.md and compare.html (one file, plots inline). A regression is a finding: the exit status is 0."""
    from ..corpus.compare import JSON_KEYS, compare_outputs
    from ..corpus.compare_report import write_reports
    from ..corpus.figures import read_output

    base_out, new_out = read_output(base, "BASE"), read_output(new, "NEW")
    result = compare_outputs(base_out, new_out)
    md, page = write_reports(result, base_out, new_out, out if out is not None else new / "compare")
    if as_json:
        emit_json({k: result[k] for k in JSON_KEYS})
        return
    for i, e in enumerate(result["regressions"], 1):
        err.print(f"{i}. {e['drive']}: {e['text']}", highlight=False, markup=False, soft_wrap=True)
        err.print(f"   {e['view']}", highlight=False, markup=False, soft_wrap=True)
    err.print(
        f"drives compared: {result['drives_compared']}; regressions: {len(result['regressions'])}, "
        f"improvements: {len(result['improvements'])}; only in BASE: {len(result['only_in_base'])}, "
        f"only in NEW: {len(result['only_in_new'])}; report: {md}, {page}",
        highlight=False,
        markup=False,
        soft_wrap=True,
    )


@corpus_app.command("staleness")
def staleness(
    run_dir: Annotated[
        Path, typer.Argument(metavar="RUN_DIR", help="The --out folder of a corpus run.", show_default=False)
    ],
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Folder of the outputs (default: RUN_DIR/staleness).", show_default=False),
    ] = None,
    cell: Annotated[float, typer.Option("--cell", help="Side of a grid cell (m).")] = 1.0,
    min_distance: Annotated[
        float,
        typer.Option(
            "--min-distance",
            help="A point this far from the map (m), or a map point seen through by this much, disagrees.",
        ),
    ] = 1.0,
    range_m: Annotated[float, typer.Option("--range", help="Judge points up to this far from the sensor (m).")] = 40.0,
    every: Annotated[int, typer.Option("--every", help="Judge every N-th localized scan.")] = 2,
    scan_share: Annotated[
        float, typer.Option("--scan-share", help="Share of a drive's scans seeing a cell that must disagree on it.")
    ] = 0.3,
    drive_share: Annotated[
        float, typer.Option("--drive-share", help="Share of the drives seeing a cell that must disagree on it.")
    ] = 0.3,
    min_drives: Annotated[int, typer.Option("--min-drives", help="Drives that must disagree on a cell.")] = 2,
    as_json: JsonOpt = False,
    cache: CacheOpt = None,
):
    """Where the prior map is stale: the places where the drives of a corpus run disagree with the map, drive after drive.

    Each localized scan, at its estimate, is compared with the map: points the map cannot explain (something new) and map points the beams passed through (something gone). A cell of the map's top view is stale when that recurs in at least --min-drives drives and --drive-share of the drives that saw it: traffic passes in one drive, a moved object is seen by every drive. Writes OUT/MAP/staleness.png (heat map), staleness.npz (grid), stale.ply (the stale places' points; `lidarloc view --run … --staleness OUT`) and OUT/staleness.json. On the built-in town with changes, also how many of the known changes were found (recall, precision) and whether traffic was flagged (docs/corpus.md)."""
    from ..corpus.staleness import Settings
    from ..corpus.staleness_out import write_outputs
    from ..corpus.staleness_run import corpus_staleness

    settings = Settings(cell, min_distance, range_m, every, scan_share, drive_share, min_drives).check()

    def progress(label: str, i: int, n: int) -> None:
        if i == n:
            err.print(f"{label}: {n} scans judged", highlight=False, markup=False)

    results = corpus_staleness(run_dir, settings, cache, progress)
    target = out if out is not None else run_dir / "staleness"
    summary = write_outputs(results, settings, target, run_dir)
    if as_json:
        emit_json(summary)
        return
    for m in summary["maps"]:
        line = f"{m['map']}: {len(m['drives'])} drives, {m['cells_stale']} stale cells in {len(m['places'])} places"
        known = m.get("known_changes")
        if known is not None:
            line += (
                f"; known changes: recall {known['recall']}, precision {known['precision']}, "
                f"traffic flagged: {'yes' if known['traffic_flagged'] else 'no'}"
            )
        err.print(line, highlight=False, markup=False)
    err.print(f"outputs in {target}", highlight=False, markup=False)


def _print_report(report: dict) -> None:
    for name, drive in report["drives"].items():
        health = drive["health"]
        fix = health["first_fix"]
        rmse = health["rmse_localized_m"]
        line = (
            f"{name}: "
            + ("never localized" if fix is None else f"localized at scan {fix['scan']} ({fix['seconds']:.1f} s)")
            + ("" if rmse is None else f", RMSE {rmse:.2f} m")
            + f", {len(health['withdrawals'])} withdrawals"
            + ("" if health["false_fires"] is None else f", {health['false_fires']} false fires")
        )
        err.print(line, highlight=False, markup=False)
        for stretch in health["stretches"]:
            if stretch["kind"] != "late":  # wall-clock noise: corpus.json keeps them
                err.print(f"  {stretch['text']}", highlight=False, markup=False)
    for name, reason in report["drives_failed"].items():
        err.print(f"{name}: failed: {reason}", highlight=False, markup=False)
    err.print(
        f"{report['done']} of {report['total']} drives done ({report['ran_now']} now); corpus.json in {report['out']}",
        highlight=False,
        markup=False,
    )
