"""The command groups: ``lidarloc``, ``lidarloc map`` and ``lidarloc bench``."""

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="LiDAR-only localization in a prior 3D map: scan-matching particle filter with a live viewer.",
)
map_app = typer.Typer(no_args_is_help=True, help="Build and inspect prior maps.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks behind BENCHMARKS.md.")
app.add_typer(map_app, name="map")
app.add_typer(bench_app, name="bench")
