"""Starting and stopping a viewer: :func:`serve` starts one on a ready Localizer or on a factory
that builds one, and returns at once; :func:`serve_until_interrupted` is ``lidarloc demo`` /
``lidarloc view``: start the viewer at once, build the localizer behind a progress bar (console
and page), and serve until Ctrl-C."""

from __future__ import annotations

import inspect
import signal
import sys
import threading
import traceback
import webbrowser
from collections.abc import Callable
from pathlib import Path

import viser
from rich.console import Console

from ...core.config import Config
from ...core.errors import LidarlocError
from ...core.localizer import Localizer
from ...core.sequences.factory import SourceSpec
from ..console import progress_bar, wait_for_stop
from ..options import open_source
from .app import Viewer
from .budget import DEFAULT_KEEP_RUNS, DEFAULT_MAX_RECORD_GB
from .collector import FullCollections, freeze_startup, release_at_exit
from .recorder import Budget, Recorder, default_record_root
from .style import SPEEDS
from .token_gate import resolve_token, start_server, with_token


class ViewerHandle:
    """What :func:`serve` returns: where the viewer is, and how to stop it."""

    def __init__(self, viewer: Viewer, server: viser.ViserServer, host: str, token: str | None = None):
        self.viewer = viewer
        self.server = server
        self.port = int(server.get_port())
        self.token = token  # the viewer's token (--token), None without one
        shown = "localhost" if host in ("0.0.0.0", "::") else host
        self.url = with_token(f"http://{shown}:{self.port}", token)  # what a browser opens
        self.foxglove_url: str | None = None  # where the Foxglove stream is (serve's foxglove_port)
        self._stopped = threading.Event()

    @property
    def localizer(self) -> Localizer | None:
        return self.viewer.localizer

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Block until the localizer is built and shown (False on timeout or failed start)."""
        return self.viewer.wait_ready(timeout)

    def wait(self) -> None:
        """Block until :meth:`stop` (in short waits, so Ctrl-C gets through at once)."""
        while not self._stopped.wait(0.25):
            pass

    def stop(self) -> None:
        """Stop playback, the display and the server; close the localizer if the viewer built it.
        Bounded: returns within about half a second. A scan of the viewer's own localizer that is
        waiting for a block gives up at once (``Localizer.interrupt``); one still computing
        finishes on its daemon thread, and the localizer's worker pools are joined by Python at
        exit. The localizer's child processes are killed first, not asked to exit: what they were
        computing would be thrown away, their caches are written under a temporary name and
        renamed, and a child at its low priority on a busy machine took longer to run its
        interpreter's exit than the whole stop may take. The children of runs a branch took over
        and whose close is not done yet are killed too, so none outlives the viewer."""
        if self._stopped.is_set():
            return
        loc = self.viewer.localizer
        owned = loc is not None and self.viewer.owns_localizer
        if owned:
            loc.interrupt()
        self.viewer.stop()
        self.viewer.close_gui()
        self.server.stop()
        for sink in self.viewer.sinks:
            sink.stop()
        if owned:
            loc.kill_processes()
            closer = threading.Thread(target=loc.close, name="lidarloc-close", daemon=True)
            closer.start()
            closer.join(timeout=0.1)  # the pools; a step still computing is left to its daemon thread
        self.viewer.retired.kill_unfinished()  # nor those of a run a branch took over
        self._stopped.set()


def _call_factory(factory: Callable[..., Localizer], progress, on_map=None) -> Localizer:
    """Build the localizer, handing it the progress callback and the ``on_map`` callback (the
    prior map, as soon as it exists) where it takes them."""
    try:
        params = inspect.signature(factory).parameters
    except (TypeError, ValueError):
        params = {}
    anything = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    kwargs = {}
    if "progress" in params or anything:
        kwargs["progress"] = progress
    if on_map is not None and ("on_map" in params or anything):
        kwargs["on_map"] = on_map
    return factory(**kwargs)


def serve(
    localizer_or_factory: Localizer | Callable[..., Localizer],
    host: str = "127.0.0.1",
    port: int = 8080,
    open_browser: bool = False,
    *,
    autoplay: bool | None = None,
    speed: str = "10",
    record_to: Path | None = None,
    spec: SourceSpec | None = None,
    preset: str | None = None,
    cache_root: Path | None = None,
    foxglove_port: int | None = None,
    budget: Budget | None = None,
    token: str | None = None,
) -> ViewerHandle:
    """Start the viewer and return at once.

    ``localizer_or_factory``: a ready Localizer (the caller keeps ownership and closes it), or a
    callable returning one — called on a background thread, with ``progress=`` if it accepts it
    (the Localizer's ``(stage, fraction)`` callback) and ``on_map=`` (called with the prior map as
    soon as it exists: the page shows it while the tables are built), while the page shows a
    progress bar; the viewer then owns it and closes it on :meth:`ViewerHandle.stop`.
    ``autoplay``: None (default) starts playback when the first browser tab is open and the
    localizer ready, True as soon as it is ready, False never (the caller or the user plays).
    ``port``: the first port tried (viser moves up if it is taken; the handle has the real one).
    ``spec``: the source options the localizer's sequence was opened with; given, every run the
    viewer plays is recorded under ``record_to`` (default: a new ``runs/<date-time>`` under the
    cache root), so that the timeline can scrub it and branches can start from it.
    ``cache_root``: where a branch finds the map's tables.
    ``foxglove_port``: also stream every step played to Foxglove clients on this port (on
    ``host``; 0: any free port), see :mod:`.foxglove_live`; the handle's ``foxglove_url`` says where.
    ``budget``: keep the recordings' root under it (:class:`~.recorder.Budget`; None: no limit).
    ``token``: answer only requests that carry it (``auto``: a random one), see :mod:`.token_gate`;
    the handle's ``url`` has it.
    """
    if speed not in SPEEDS:
        raise LidarlocError(f"speed must be one of {', '.join(SPEEDS)}, got {speed!r}")
    if not (isinstance(localizer_or_factory, Localizer) or callable(localizer_or_factory)):
        raise LidarlocError("serve() needs a Localizer or a callable that returns one")
    token = resolve_token(token)
    server = start_server(token, host=host, port=port, label="lidarloc", verbose=False)
    viewer = None
    try:
        viewer = Viewer(server, autoplay=autoplay, speed=speed)
        viewer.cache_root = cache_root
        if spec is not None:
            root = record_to if record_to is not None else default_record_root(cache_root)
            viewer.travel.record_with(
                Recorder(
                    root,
                    spec,
                    preset,
                    on_failure=lambda message: viewer.show_message(message, error=True, everyone=True),
                    budget=budget,
                    on_notice=viewer.show_message,
                )
            )
        if foxglove_port is not None:
            from .foxglove_live import FoxgloveLive

            viewer.sinks.append(
                FoxgloveLive(
                    host,
                    foxglove_port,
                    on_failure=lambda message: viewer.show_message(message, error=True, everyone=True),
                )
            )
    except BaseException:
        for sink in viewer.sinks if viewer is not None else []:
            sink.stop()
        server.stop()
        raise
    if isinstance(localizer_or_factory, Localizer):
        try:
            viewer.attach(localizer_or_factory)
        except BaseException:
            viewer.stop()
            server.stop()
            raise
    else:
        factory = localizer_or_factory

        def build():
            try:
                loc = _call_factory(factory, viewer.build_progress, viewer.show_map)
                viewer.owns_localizer = True
                if viewer.stopping:  # stopped while building: nobody will show it
                    loc.close()
                    return
                viewer.attach(loc)
            except LidarlocError as exc:
                viewer.startup_failed(str(exc))
            except Exception as exc:
                traceback.print_exc(file=sys.stderr)
                viewer.startup_failed(f"{type(exc).__name__}: {exc}")

        threading.Thread(target=build, name="lidarloc-build", daemon=True).start()
    handle = ViewerHandle(viewer, server, host, token)
    handle.foxglove_url = next((sink.url for sink in viewer.sinks if hasattr(sink, "url")), None)
    if open_browser:
        threading.Thread(target=webbrowser.open, args=(handle.url,), daemon=True).start()
    return handle


def serve_until_interrupted(
    spec: SourceSpec,
    cfg: Config,
    host: str,
    port: int,
    cache_root: Path | None,
    console: Console,
    open_browser: bool = False,
    autoplay: bool = False,
    record_dir: Path | None = None,
    preset: str | None = None,
    record: bool = True,
    foxglove_port: int | None = None,
    loop: bool = False,
    keep_runs: int | None = DEFAULT_KEEP_RUNS,
    max_record_gb: float | None = DEFAULT_MAX_RECORD_GB,
    token: str | None = None,
) -> None:
    """``lidarloc demo`` / ``view``: playback starts when the first browser tab is open, or at
    once with ``autoplay``. Every run played is recorded under ``record_dir`` (default: a new
    ``runs/<date-time>`` folder under the cache root), which is printed; with ``record`` False
    nothing is (``--no-record``: the timeline and Branch from here are then off). The runs under
    ``record_dir`` (default: the cache's ``runs/``) are kept to ``keep_runs`` and ``max_record_gb``,
    oldest removed first. ``loop``: at the end of the drive start again (a line per loop says how
    many scans were late). ``token``: the viewer answers only browsers that bring it (the printed
    URL has it). Ctrl-C, SIGTERM and SIGHUP all stop it the same way."""
    token = resolve_token(token)  # a bad token fails before anything starts
    seq = open_source(spec, cfg, console)  # bad paths fail here, before any server starts
    bar = progress_bar(transient=True)
    task = bar.add_task("preparing", total=100)
    ready = threading.Event()
    failure: list[BaseException] = []

    def factory(progress=None, on_map=None):
        def report(stage, frac):
            bar.update(task, description=f"preparing {stage}", completed=100 * float(frac))
            if progress is not None:
                progress(stage, frac)

        try:
            # S2M's tables follow in the background on a first start: playback begins sooner
            return Localizer(seq, cfg, cache_root, progress=report, on_map=on_map, defer_s2m=True)
        except BaseException as exc:  # the page shows it too; the console gets one line
            failure.append(exc)
            raise
        finally:
            ready.set()

    stop = threading.Event()
    # Ctrl-C, a service manager's SIGTERM and a closed terminal's SIGHUP set an event instead of
    # raising wherever the main thread happens to be; installed before the server starts so an
    # early signal also shuts down in order (child processes are closed by handle.stop()).
    previous = _on_stop_signals(lambda *_: stop.set())
    try:
        root = None if not record else record_dir if record_dir is not None else default_record_root(cache_root)
        budget = None
        if root is not None and (keep_runs is not None or max_record_gb is not None):
            runs_root = record_dir if record_dir is not None else root.parent
            max_bytes = None if max_record_gb is None else max_record_gb * 1e9
            budget = Budget(runs_root, keep_runs, max_bytes)
        handle = serve(
            factory,
            host=host,
            port=port,
            open_browser=open_browser,
            autoplay=True if autoplay else None,
            record_to=root,
            spec=spec if record else None,
            preset=preset,
            cache_root=cache_root,
            foxglove_port=foxglove_port,
            budget=budget,
            token=token,
        )
    except BaseException:
        _restore_signals(previous)
        raise
    collections = FullCollections()
    if loop:
        handle.viewer.on_finished = _looper(handle.viewer, console, collections)
    announce(handle, host, console)
    if handle.foxglove_url is not None:
        console.print(
            f"Foxglove: open connection → Foxglove WebSocket {handle.foxglove_url}", markup=False, highlight=False
        )
    console.print(
        f"recording into {root} (open a run later with lidarloc view --run {root}/run)"
        if root is not None
        else "not recording (--no-record): the timeline and Branch from here are off",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    try:
        with bar:
            while not ready.wait(0.2) and not stop.is_set():
                pass
        if failure:
            exc = failure[0]
            raise exc if isinstance(exc, LidarlocError) else LidarlocError(f"{type(exc).__name__}: {exc}")
        if not stop.is_set():
            freeze_startup()  # the start-up's objects, out of the full collections' way (see collector.py)
        failed = None
        if not stop.is_set() and autoplay:
            # "playing" once the first scan is on the page, not merely once playback was told to start
            while not stop.is_set() and not handle.viewer.first_scan_shown.wait(0.2):
                failed = handle.viewer.step_failed
                if failed:  # playback paused on it: say so instead of waiting for a scan that will not come
                    console.print(
                        f"the first scan failed: {failed}; the page says so (restart or step there)",
                        markup=False,
                        highlight=False,
                        soft_wrap=True,
                    )
                    break
        if not stop.is_set() and not failed:
            console.print(
                "ready: playing; use the page's controls to pause, step and tune"
                if autoplay
                else "ready: playback starts when a browser tab is open; use the page's controls to pause, "
                "step and tune"
            )
        wait_for_stop(stop)
    finally:
        _restore_signals(previous)
        try:
            console.print("stopping viewer")
        except (OSError, ValueError):  # SIGHUP: the terminal is gone; stop all the same
            pass
        handle.stop()
        collections.close()
        release_at_exit()


#: Hosts that only this machine reaches: no warning.
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def announce(handle: ViewerHandle, host: str, console: Console) -> None:
    """The viewer's URL (with its token, if any) and, bound beyond the loopback, who can reach it."""
    console.print(f"[bold green]lidarloc viewer:[/bold green] {handle.url}  (Ctrl-C to stop)", soft_wrap=True)
    if host in LOOPBACK:
        return
    if handle.token is None:
        line = (
            f"warning: --host {host}: anyone who can reach port {handle.port} can drive the localizer and "
            "read the map (there is no password; on a shared machine keep the default 127.0.0.1 and use an "
            "SSH tunnel, or add --token auto)"
        )
    else:
        line = (
            f"--host {host}: only a browser given the URL above (its token) can open the viewer; the "
            "connection is not encrypted, so anyone watching the network can read the token"
        )
    console.print(line, markup=False, highlight=False, soft_wrap=True)


STOP_SIGNALS = tuple(s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None)


def _on_stop_signals(handler) -> dict:
    return {s: signal.signal(s, handler) for s in STOP_SIGNALS}


def _restore_signals(previous: dict) -> None:
    for s, h in previous.items():
        signal.signal(s, h)


def _looper(viewer: Viewer, console: Console, collections: FullCollections) -> Callable[[], None]:
    """``--loop``: at the end of the drive, one line with the loop's scans, late scans, largest
    lag and full garbage collections (what ``bench soak`` reads), then play it again."""
    loops = [0]

    def again() -> None:
        loops[0] += 1
        c = viewer.player.take_counts() if viewer.player is not None else {}
        g = collections.take()
        try:
            console.print(
                f"loop {loops[0]}: {c.get('steps', 0)} scans, {c.get('late', 0)} late, "
                f"largest lag {c.get('max_lag_s', 0.0)} s, {g['count']} full garbage collections "
                f"(longest {g['longest_ms']} ms)",
                markup=False,
                highlight=False,
                soft_wrap=True,  # one line, whatever the terminal's width: bench soak reads it
            )
        except (OSError, ValueError):
            pass
        viewer.play_again()

    return again
