"""``lidarloc demo`` / ``lidarloc view``: start the viewer at once, build the localizer behind a
progress bar (console and page), and serve until Ctrl-C."""

from __future__ import annotations

import signal
import threading
from pathlib import Path

from rich.console import Console

from lidarloc.core.config import Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.sequences.factory import SourceSpec, open_sequence


def serve_until_interrupted(spec: SourceSpec, cfg: Config, host: str, port: int, cache_root: Path | None,
                            console: Console, open_browser: bool = False) -> None:
    from lidarloc.core.localizer import Localizer

    from .cli import progress_bar
    from .viewer import serve

    seq = open_sequence(spec, cfg)          # bad paths fail here, before any server starts
    bar = progress_bar(transient=True)
    task = bar.add_task("preparing", total=100)
    ready = threading.Event()
    failure: list[BaseException] = []

    def factory(progress=None):
        def report(stage, frac):
            bar.update(task, description=f"preparing {stage}", completed=100 * float(frac))
            if progress is not None:
                progress(stage, frac)
        try:
            return Localizer(seq, cfg, cache_root, progress=report)
        except BaseException as exc:   # the page shows it too; the console gets one line
            failure.append(exc)
            raise
        finally:
            ready.set()

    stop = threading.Event()
    # Ctrl-C sets an event instead of raising wherever the main thread happens to be; installed
    # before the server starts so an early Ctrl-C also shuts down in order.
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        handle = serve(factory, host=host, port=port, open_browser=open_browser)
    except BaseException:
        signal.signal(signal.SIGINT, previous)
        raise
    console.print(f"[bold green]lidarloc viewer:[/bold green] {handle.url}  (Ctrl-C to stop)")
    try:
        with bar:
            while not ready.wait(0.2) and not stop.is_set():
                pass
        if failure:
            exc = failure[0]
            raise exc if isinstance(exc, LidarlocError) else LidarlocError(f"{type(exc).__name__}: {exc}")
        if not stop.is_set():
            console.print("ready: playing; use the page's controls to pause, step and tune")
        stop.wait()
    finally:
        signal.signal(signal.SIGINT, previous)
        console.print("stopping viewer")
        handle.stop()
