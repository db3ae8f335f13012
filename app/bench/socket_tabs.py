"""Websocket tabs without a browser (:class:`SocketTab`: a tab as the server sees it) and the
process that holds them for ``lidarloc bench clients`` (:class:`TabHost`).

The websocket clients (the tabs, the one that connects and disconnects, the slow one) live in a
process of their own (:class:`TabHost`, at the tabs' priority), never in the viewer's: reading
and parsing everything the server sends, or connecting hundreds of times a minute, is the
clients' work, and inside the viewer's process it would take its CPU, its GIL and its memory and
be counted as the server's.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import threading
import time

from ...core.errors import LidarlocError
from .chromium import check_tab_priority
from .common import end_child


class SocketTab:
    """A tab as the server sees it, without a browser: a websocket client speaking viser's protocol
    that reports a camera (viser counts a tab as connected from its first camera message) and
    reads what the server sends — everything as it comes, or one message per ``every_s`` seconds
    (a client on a slow link). No WebGL: on a machine without a GPU a browser tab's software
    rendering takes a core of its own; this one costs the server what a tab costs it."""

    def __init__(self, port: int, every_s: float | None = None, open_timeout_s: float = 30.0):
        import msgspec
        import viser
        from viser._messages import ViewerCameraMessage
        from websockets.sync.client import connect

        self.ws = connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
            open_timeout=open_timeout_s,
        )
        camera = ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0),
            position=(0.0, 0.0, 10.0),
            fov=1.0,
            near=0.01,
            far=1000.0,
            image_height=600,
            image_width=800,
            look_at=(0.0, 0.0, 0.0),
            up_direction=(0.0, 0.0, 1.0),
        )
        self.ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        self.read = 0
        self._stop = threading.Event()
        self._every = every_s
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        try:
            if self._every is None:
                for _ in self.ws:
                    self.read += 1
            else:
                while not self._stop.wait(self._every):
                    self.ws.recv(timeout=5)
                    self.read += 1
        except Exception:  # closed
            pass

    def click(self, button) -> None:
        """Press a GUI button of the server's, as a browser does."""
        self.set(button, True)

    def set(self, handle, value) -> None:
        """Set a GUI input of the server's (a slider dragged, a button pressed), as a browser does."""
        import msgspec
        from viser._messages import GuiUpdateMessage

        self.ws.send(
            msgspec.msgpack.encode(GuiUpdateMessage(handle._impl.uuid, {"value": value}).as_serializable_dict())
        )

    def close(self) -> None:
        self._stop.set()
        self.ws.close()
        self._thread.join(timeout=5)


class TabHost:
    """Websocket tabs (:class:`SocketTab`) held by a process of their own, started at ``priority``
    (``idle``: ``SCHED_IDLE``, as the browsers), so that what the clients do costs the viewer's
    process nothing (the module docstring says why). ``open()`` returns a :class:`HostedTab`."""

    def __init__(self, port: int, priority: str = "idle", reply_timeout_s: float = 60.0):
        check_tab_priority(priority)
        ctx = multiprocessing.get_context("spawn")  # spawn: the viewer's process runs threads
        self._conn, theirs = ctx.Pipe()
        self._lock = threading.Lock()  # one request at a time on the pipe
        self._timeout = reply_timeout_s
        self._proc = ctx.Process(
            target=_host_tabs, args=(theirs, port, priority == "idle"), name="lidarloc-tabs", daemon=True
        )
        self._proc.start()
        theirs.close()
        self.stopped = False

    def open(self, every_s: float | None = None) -> HostedTab:
        """A new websocket tab, connected and its camera sent once this returns (the server
        counts it a moment later); reading everything as it comes, or one message per
        ``every_s`` seconds (a slow link)."""
        return HostedTab(self, self.ask("open", every_s))

    def ask(self, *request):
        with self._lock:
            if self.stopped:
                raise LidarlocError("bench clients: the tabs' process was already stopped")
            try:
                self._conn.send(request)
                deadline = time.perf_counter() + self._timeout
                while not self._conn.poll(0.5):
                    if not self._proc.is_alive():
                        break
                    if time.perf_counter() > deadline:
                        raise TimeoutError(
                            f"the tabs' process did not answer {request[0]!r} within {self._timeout:.0f} s"
                        )
                ok, value = self._conn.recv()
            except (OSError, EOFError):  # its end of the pipe closed: the process died
                self._proc.join(timeout=5)
                raise LidarlocError(
                    f"bench clients: the tabs' process ended with status {self._proc.exitcode}"
                ) from None
        if not ok:
            raise LidarlocError(f"bench clients: a websocket tab failed: {value}")
        return value

    def stop(self) -> None:
        """Close every tab still open and end the process (killed if it does not end within 10 s)."""
        with self._lock:
            if self.stopped:
                return
            self.stopped = True
            with contextlib.suppress(OSError):  # a process that died has closed its end
                self._conn.send(("stop",))
        end_child(self._proc)
        self._conn.close()

    def __enter__(self) -> TabHost:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class HostedTab:
    """One websocket tab of a :class:`TabHost`."""

    def __init__(self, host: TabHost, tab_id: int):
        self._host, self._id = host, tab_id
        self.read: int | None = None  # messages read, known once closed

    def close(self) -> int | None:
        """Disconnect (once); the messages the tab read, or None if its process was already stopped."""
        if self.read is None and not self._host.stopped:
            self.read = self._host.ask("close", self._id)
        return self.read


def _host_tabs(conn, port: int, idle: bool) -> None:
    """The tabs' process: opens and closes :class:`SocketTab` s as the pipe asks, until told to
    stop or the viewer's process is gone."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the parent stops us
    if idle:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    tabs: dict[int, SocketTab] = {}
    next_id = 0
    try:
        while True:
            try:
                request = conn.recv()
            except (EOFError, OSError):  # the viewer's process is gone
                break
            if request[0] == "stop":
                break
            try:
                if request[0] == "open":
                    tabs[next_id] = SocketTab(port, every_s=request[1])
                    reply, next_id = next_id, next_id + 1
                else:  # close
                    tab = tabs.pop(request[1])
                    tab.close()
                    reply = tab.read
                conn.send((True, reply))
            except Exception as exc:  # said to the parent in one line
                conn.send((False, f"{type(exc).__name__}: {exc}"))
    finally:
        for tab in tabs.values():
            tab.close()
