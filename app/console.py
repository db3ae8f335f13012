"""What the commands print: progress bars and messages on stderr, results as JSON on stdout, and
one-line errors the user can fix (exit status 2)."""

from __future__ import annotations

import json
import resource
import sys
from typing import NoReturn

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

# stderr, so that stdout carries only results (--json) and can be piped
err = Console(stderr=True)


def progress_bar(transient: bool = True) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err,
        transient=transient,
    )


def fail(message: str) -> NoReturn:
    """Print ``lidarloc: error: message`` as one line on stderr and exit with status 2."""
    # plain write: one unwrapped line, no markup interpretation of paths with brackets
    sys.stderr.write(f"lidarloc: error: {message}\n")
    sys.exit(2)


def emit_json(data: dict) -> None:
    """A command's result as JSON on stdout."""
    typer.echo(json.dumps(data, indent=2, default=float))


def show_result(title: str, data: dict) -> None:
    """A command's result for reading: one ``key: value`` line per entry (nested entries
    indented) on stderr; ``--json`` prints the same result as JSON on stdout instead."""
    err.print(f"[bold]{title}[/bold]")
    _show(data, 1)


def _show(data: dict, depth: int) -> None:
    pad = "  " * depth
    for key, value in data.items():
        if isinstance(value, dict):
            err.print(f"{pad}{key}:", markup=False, highlight=False)
            _show(value, depth + 1)
        else:
            err.print(f"{pad}{key}: {_fmt(value)}", markup=False, highlight=False)


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def peak_rss_mb() -> float:
    """This process's peak resident memory so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux
