"""What the commands print: progress bars and messages on stderr, results as JSON on stdout, and
one-line errors the user can fix (exit status 2)."""

from __future__ import annotations

import json
import resource
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import NoReturn, TypeVar

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

T = TypeVar("T")

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


def preparing(build: Callable[[Callable[[str, float], None]], T], label: str = "preparing map") -> T:
    """``build(progress)`` (a Localizer, a branch: whatever builds the map and its tables) behind
    one progress bar that names the table being prepared; returns what it built."""
    with progress_bar() as bar:
        task = bar.add_task(label, total=100)
        return build(lambda stage, f: bar.update(task, description=f"preparing {stage}", completed=100 * f))


def stage_progress(bar: Progress) -> Callable[[str, float], None]:
    """``progress(stage, fraction)`` drawing on ``bar``: a line per stage, added when it first reports."""
    tasks: dict = {}

    def progress(what: str, fraction: float) -> None:
        if what not in tasks:
            tasks[what] = bar.add_task(what, total=1.0)
        bar.update(tasks[what], completed=fraction)

    return progress


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


#: The signals that stop a command the way Ctrl-C does: a terminal's Ctrl-C, ``kill`` and a
#: service manager (SIGTERM), a closed terminal or SSH session (SIGHUP).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _as_ctrl_c(signum, frame) -> None:
    """SIGTERM / SIGHUP: whatever Ctrl-C does at this moment (the command's own SIGINT handler,
    else Python's KeyboardInterrupt)."""
    handler = signal.getsignal(signal.SIGINT)
    if callable(handler) and handler is not _as_ctrl_c:
        handler(signum, frame)
    else:
        raise KeyboardInterrupt


def stop_signals_like_ctrl_c() -> None:
    """Make SIGTERM and SIGHUP stop this process exactly as Ctrl-C would, whichever SIGINT handler
    a command installs later, and make Ctrl-C work in a process started in the background (a
    shell without job control starts it with SIGINT ignored). Call it once, early, from the main
    thread; elsewhere it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) in (signal.SIG_IGN, None):
        signal.signal(signal.SIGINT, signal.default_int_handler)
    for sig in STOP_SIGNALS[1:]:
        signal.signal(sig, _as_ctrl_c)


#: How long a main thread waits on worker processes at most before it looks again, so that a stop
#: signal another of the process's threads took is run (Python runs handlers on the main thread,
#: only when it runs Python code; see :func:`wait_for_stop`), in seconds.
SIGNAL_POLL_S = 0.5


def wait_for_stop(stop: threading.Event, poll_s: float = 0.1) -> None:
    """Block the main thread until a stop signal's handler sets ``stop``.

    Short sleeps, not ``stop.wait()``: a signal sent to the process can be taken by any of its
    threads, and Python runs the handler only when the main thread next runs Python code, which a
    wait without a timeout never does (a SIGTERM taken by another thread left the viewer running
    for good: reproduced by sending it to one of the viewer's threads). Nor a timed
    ``stop.wait()``: the handler, run on this same thread in the middle of it, would set ``stop``
    while wait() holds the Event's lock, and deadlock. ``poll_s`` bounds how late the stop begins."""
    while not stop.is_set():
        time.sleep(poll_s)
