"""The command groups: ``lidarloc``, ``lidarloc map``, ``lidarloc bench`` and ``lidarloc corpus``."""

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="LiDAR-only localization in a prior 3D map: scan-matching particle filter with a live viewer.",
)
map_app = typer.Typer(no_args_is_help=True, help="Build and inspect prior maps.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks behind BENCHMARKS.md.")
corpus_app = typer.Typer(
    no_args_is_help=True, help="Run many drives, one run each, and see where along each localization went wrong."
)
app.add_typer(map_app, name="map")
app.add_typer(bench_app, name="bench")
app.add_typer(corpus_app, name="corpus")
