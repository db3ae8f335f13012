"""The ``lidarloc`` command line (typer): one module per command group. Every command that takes
a sequence accepts the same source options; errors the user can fix print one line on stderr and
exit with status 2."""

from __future__ import annotations

import typer

from ...core.errors import LidarlocError
from ..console import fail, stop_signals_like_ctrl_c
from . import (  # noqa: F401  (each registers its commands)
    admin,
    bench_corpus,
    bench_costs,
    bench_live,
    bench_runs,
    bench_travel,
    corpus,
    maps,
    runs,
    sources,
    sweeps,
    viewing,
)
from .groups import app


def main() -> None:
    """Entry point: click's usage errors behave as usual; LidarlocError becomes one line + exit 2."""
    command = typer.main.get_command(app)
    # Every command, the benchmarks that start viewers and browsers included, stops on SIGTERM and
    # SIGHUP as on Ctrl-C: its cleanup runs, so it leaves no child process behind.
    stop_signals_like_ctrl_c()
    try:
        command.main(prog_name="lidarloc", standalone_mode=True)
    except LidarlocError as exc:
        fail(str(exc))
    except MemoryError:
        fail("out of memory")
