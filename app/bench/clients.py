"""``lidarloc bench clients``: the live viewer with many browser tabs and bad clients.

The viewer runs in this process on the real-time clock, the drive in a loop; the phases follow
each other, ``phase_s`` seconds each: no client; five headless Chromium tabs; the five and a sixth
tab that connects, waits for the page and disconnects in a loop; the five and a websocket tab
that connects and disconnects in a loop (:func:`socket_churn`: hundreds of connections where a
browser tab makes a few); the five and a slow client (a websocket that reads one message a
second). Per phase: the filter's scans per second and late
scans (the player's counts), the server-side display update (median, p95 ms: the whole
``update_display`` on the display thread, for the updates that drew a new snapshot), this
process's RSS, and where the CPU went (% of one core): this process, the localizer's child
processes, the clients (browsers, Playwright's driver, the websocket tabs' process; processes that
ended within the phase are not counted), and the whole machine (``machine_busy_pct``, 200 on two
busy cores). ``rss_mb_per_connection`` is the slope of the RSS against the websocket tab's
connections over their second half (``rss_mb_per_browser_connection``: the browser tab's phase's RSS growth divided by
its few connections).
Targets: the real-time rate kept, the update ≤ 20 ms, no memory growth per connection, a slow
client slows nothing (viser keeps only the newest message per scene node for it).

The tabs are Debian's Chromium through Playwright (the soak opens its one tab with the same
flags); WebGL is software-rendered (no GPU), so a tab costs CPU of its own: measured on a 2-core
machine, five tabs at normal priority take the cores from the viewer they measure (load 8–9, the
filter up to 3 s behind its clock while the server-side update stays at 5 ms). Five people
watching a run sit at five machines of their own, so by default the tabs run at the idle CPU
priority (``SCHED_IDLE``, through ``chrt``): they get only the CPU the viewer leaves, and the
phases measure what serving them costs the viewer. ``tab_priority="normal"`` runs them as any
other process (browser and viewer on one small machine). ``tab_kind="socket"`` opens websocket
tabs instead (:class:`SocketTab`: everything the server sends, read and not drawn): with no
browser on the machine, the phases show what serving the tabs costs the viewer itself
(``cpu_pct`` per phase: this process's CPU, every thread).

The viewer lets new websocket connections in at a bounded rate (:mod:`lidarloc.app.viewer.pacing`):
the tab that connects and disconnects as fast as it can is held in its opening handshake beyond
that rate, as any client in such a loop would be; ``connections_paced`` and
``connections_refused`` say how often.

The websocket clients (those tabs, the one that connects and disconnects, the slow one) live in a
process of their own (:class:`TabHost`, at the tabs' priority), never in the viewer's: reading
and parsing everything the server sends, or connecting hundreds of times a minute, is the
clients' work, and inside the viewer's process it would take its CPU, its GIL and its memory and
be counted as the server's.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from .common import end_child, load_avg, machine, rss_mb

CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--headless",
]


CHROMIUM = Path("/usr/bin/chromium")
LOAD_TIMEOUT_MS = 120_000
TAB_PRIORITIES = ("idle", "normal")
TAB_KINDS = ("chromium", "socket")


def check_tab_priority(priority: str) -> None:
    """Refuse a tab priority the benchmark does not know, naming those it does."""
    if priority not in TAB_PRIORITIES:
        raise ValueError(f"tab priority must be one of {', '.join(TAB_PRIORITIES)}; got {priority!r}")


@contextlib.contextmanager
def chromium_at(priority: str):
    """The Chromium executable to launch at ``priority``: ``normal`` is Chromium itself; ``idle``
    a wrapper that starts it under ``chrt --idle 0`` (every process it starts inherits the
    policy: a scheduling policy, unlike a nice value, is not undone by Chromium raising its GPU
    process's priority)."""
    check_tab_priority(priority)
    if priority == "normal":
        yield CHROMIUM
        return
    chrt = shutil.which("chrt")
    if chrt is None:
        raise RuntimeError("idle-priority tabs need chrt (util-linux); use --tab-priority normal")
    with tempfile.TemporaryDirectory(prefix="lidarloc-chromium-") as tmp:
        wrapper = Path(tmp) / "chromium-idle"
        wrapper.write_text(f'#!/bin/sh\nexec {chrt} --idle 0 {CHROMIUM} "$@"\n')
        wrapper.chmod(0o755)
        yield wrapper


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


def _timed(viewer, out: list) -> None:
    """Time every display update of ``viewer`` (the display thread's calls) into ``out`` (ms)."""
    inner = viewer.update_display

    def update_display(force_plots: bool = False) -> float:
        t0 = time.perf_counter()
        ms = inner(force_plots)
        if ms > 0:  # a new snapshot drawn (the display also wakes for progress and play-state changes)
            out.append((time.perf_counter() - t0) * 1000.0)
        return ms

    setattr(viewer, "update_display", update_display)  # noqa: B010  (this viewer only)


def _cpu_by_role() -> dict[int, tuple[str, float]]:
    """pid → (role, CPU seconds) of this process's descendants: ``localizer`` for the localizer's
    own child processes (KISS-ICP, S2M), ``clients`` for the rest (the browsers and Playwright's
    driver, the websocket tabs' process)."""
    import psutil

    out = {}
    for child in psutil.Process().children(recursive=True):
        try:
            times = child.cpu_times()
            role = "localizer" if any(".core." in part for part in child.cmdline()) else "clients"
        except psutil.Error:  # gone meanwhile
            continue
        out[child.pid] = (role, times.user + times.system)
    return out


def _cpu_pct_of_roles(before: dict, after: dict, elapsed: float) -> dict[str, float]:
    """The CPU (% of one core) each role's processes used between two :func:`_cpu_by_role`
    readings: those alive at the end, from their first reading (a process that ended within the
    phase is not counted, so the figures are lower bounds)."""
    used = {"localizer": 0.0, "clients": 0.0}
    for pid, (role, seconds) in after.items():
        start = before.get(pid)
        used[role] += seconds - (start[1] if start is not None and start[0] == role else 0.0)
    return {role: round(100.0 * s / elapsed, 1) for role, s in used.items()}


def _phase(viewer, updates: list, name: str, seconds: float, during=None) -> dict:
    """Run for ``seconds`` (``during()`` called in a loop meanwhile): the phase's figures."""
    import psutil

    updates.clear()
    viewer.player.take_counts()
    machine0, roles0 = psutil.cpu_times(), _cpu_by_role()
    rss0, t0, cpu0 = rss_mb(), time.perf_counter(), time.process_time()
    loops = 0
    while time.perf_counter() - t0 < seconds:
        if during is not None:
            during()
            loops += 1
        else:
            time.sleep(0.5)
    elapsed = time.perf_counter() - t0
    cpu_pct = (time.process_time() - cpu0) / elapsed * 100.0  # this process, every thread
    roles = _cpu_pct_of_roles(roles0, _cpu_by_role(), elapsed)
    machine1 = psutil.cpu_times()
    idle = (machine1.idle - machine0.idle) + (getattr(machine1, "iowait", 0.0) - getattr(machine0, "iowait", 0.0))
    busy_pct = 100.0 * (psutil.cpu_count() - idle / elapsed)  # % of one core: 200 is two cores
    counts = viewer.player.take_counts()
    ms = np.array(updates) if updates else np.array([np.nan])
    return {
        "phase": name,
        "seconds": round(elapsed, 1),
        "scans_per_s": round(counts["steps"] / elapsed, 2),
        "late_scans": counts["late"],
        "max_lag_s": counts["max_lag_s"],
        "update_ms_median": round(float(np.nanmedian(ms)), 1),
        "update_ms_p95": round(float(np.nanpercentile(ms, 95)), 1),
        "updates": len(updates),
        "rss_mb_start": round(rss0, 1),
        "rss_mb_end": round(rss_mb(), 1),
        "loops": loops,
        "cpu_pct": round(cpu_pct, 1),
        "localizer_children_cpu_pct": roles["localizer"],
        "clients_cpu_pct": roles["clients"],
        "machine_busy_pct": round(busy_pct, 1),
        "load_1min": round(load_avg(), 2),
    }


def socket_churn(handle, seconds: float, open_tab=None) -> dict:
    """A websocket tab that connects, is counted by the server, disconnects and is let go by it,
    in a loop for ``seconds``: the connections made and this process's RSS after each one was
    let go. ``open_tab()`` opens the tab (default: a :class:`SocketTab` in this process;
    ``bench clients`` passes its :class:`TabHost`'s, so that the RSS is the server's alone).

    ``rss_mb_per_connection`` is the least-squares slope of that RSS against the connection's
    number over the second half of the connections; ``rss_mb_first_half`` what the RSS rose
    over the first half. Measured on the town with five more tabs attached, the first few
    hundred connections raise the RSS once by ~200 MB and the next ones by a few kB each:
    every connection is sent the whole scene, and tabs that come and go 30 times a second have
    many of those sends in flight at once, a high-water mark the allocator keeps (about half of
    it is given back by ``malloc_trim``) and not a growth per connection; no client handle
    outlives its connection (tested).
    """
    server = handle.server
    if open_tab is None:
        open_tab = lambda: SocketTab(handle.port)  # noqa: E731
    rss: list[float] = []
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        before = set(server.get_clients())
        tab = open_tab()
        try:
            _wait(lambda: set(server.get_clients()) - before, "the server to count the websocket tab")
        finally:
            tab.close()
        _wait(lambda: not set(server.get_clients()) - before, "the server to let the websocket tab go")
        rss.append(rss_mb())
    half = len(rss) // 2
    later = rss[half:]
    slope = float(np.polyfit(np.arange(len(later)), later, 1)[0]) if len(later) >= 10 else None
    return {
        "connects": len(rss),
        "rss_mb_start": round(rss[0], 1) if rss else None,
        "rss_mb_end": round(rss[-1], 1) if rss else None,
        "rss_mb_per_connection": round(slope, 4) if slope is not None else None,
        "rss_mb_first_half": round(float(np.median(rss[max(half - 5, 0) : half]) - rss[0]), 1) if half else None,
        "rss_mb_second_half": round(float(np.median(rss[-5:]) - np.median(rss[half : half + 5])), 1) if half else None,
    }


def _wait(condition, what: str, timeout_s: float = 30.0) -> None:
    deadline = time.perf_counter() + timeout_s
    while not condition():
        if time.perf_counter() > deadline:
            raise TimeoutError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.01)  # polls the server's client table: no event to wait on


def _open_tab(browser, handle):
    """A new tab on the viewer, returned once the server counts its connection (the page's
    canvas may still be laying out in software WebGL)."""
    before = set(handle.server.get_clients())
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(handle.url, timeout=LOAD_TIMEOUT_MS)
    deadline = time.perf_counter() + LOAD_TIMEOUT_MS / 1000
    while not set(handle.server.get_clients()) - before:
        if time.perf_counter() > deadline:
            page.close()
            raise TimeoutError(f"a tab did not connect to the viewer within {LOAD_TIMEOUT_MS / 1000:.0f} s")
        page.wait_for_timeout(100)  # lets Playwright's event loop run while the page connects
    return page


def run(
    loc,
    tabs: int = 5,
    phase_s: float = 45.0,
    tab_priority: str = "idle",
    tab_kind: str = "chromium",
    churn_s: float | None = None,
) -> dict:
    """The phases above on a ready Localizer ``loc`` (closed by the caller); the tabs' Chromium and
    the websocket clients' process at ``tab_priority`` (see the module docstring).
    ``tab_kind="socket"``: the tabs are websocket tabs (:class:`SocketTab`: everything the server
    sends, read and not drawn), so the phases measure what serving them costs the viewer without
    any browser's rendering on the machine (no browser tab connecting and disconnecting then).
    ``churn_s`` (default ``phase_s``): the length of the websocket tab's connect/disconnect phase
    alone: the allocator's pages come and go by tens of MB, so only thousands of connections pin
    the growth per connection down."""
    from ..viewer.serve import serve

    if tab_kind not in TAB_KINDS:
        raise ValueError(f"tab kind {tab_kind!r} is not one of {', '.join(TAB_KINDS)}")
    check_tab_priority(tab_priority)
    if tab_kind == "chromium" and not CHROMIUM.exists():
        raise RuntimeError("bench clients needs /usr/bin/chromium (apt-get install -y chromium)")
    with contextlib.redirect_stdout(sys.stderr):  # viser's banner: stdout carries --json
        handle = serve(loc, port=0, autoplay=False)
    viewer = handle.viewer
    updates: list = []
    _timed(viewer, updates)
    viewer.on_finished = viewer.play_again
    loc.set_params(clock="realtime")
    viewer.player.set_clock("realtime")
    churn_s = phase_s if churn_s is None else churn_s
    phases, connects, failed, pages = [], 0, 0, []
    churn_stats: dict = {}
    browser_growth = None  # RSS over the browser tab's connect/disconnect phase
    try:
        viewer.play()
        with contextlib.ExitStack() as stack:
            host = stack.enter_context(TabHost(handle.port, tab_priority))
            browser = None
            if tab_kind == "chromium":
                from playwright.sync_api import sync_playwright

                pw = stack.enter_context(sync_playwright())
                executable = stack.enter_context(chromium_at(tab_priority))
                browser = pw.chromium.launch(executable_path=str(executable), args=CHROMIUM_ARGS)
                stack.callback(browser.close)
            phases.append(_phase(viewer, updates, "no client", phase_s))
            for _ in range(tabs):
                try:
                    pages.append(_open_tab(browser, handle) if browser is not None else host.open())
                except TimeoutError:  # said in the result: the phases run with the tabs that got through
                    failed += 1
            stack.callback(lambda: [page.close() for page in pages])
            tab_failures = failed
            kind = "tabs" if browser is not None else "websocket tabs"
            phases.append(_phase(viewer, updates, f"{len(pages)} {kind}", phase_s))
            if browser is not None:

                def churn():
                    nonlocal connects
                    nonlocal failed
                    try:
                        _open_tab(browser, handle).close()
                        connects += 1
                    except TimeoutError:  # counted: on a saturated machine a tab may not get through
                        failed += 1

                churned = _phase(
                    viewer, updates, f"{len(pages)} tabs + one connecting and disconnecting", phase_s, during=churn
                )
                churned["connects"] = connects
                churned["connects_timed_out"] = failed - tab_failures
                phases.append(churned)
                browser_growth = churned["rss_mb_end"] - churned["rss_mb_start"]
            sockets = _phase(
                viewer,
                updates,
                f"{len(pages)} {kind} + a websocket tab connecting and disconnecting",
                churn_s,
                during=lambda: churn_stats.update(socket_churn(handle, churn_s, open_tab=host.open)),
            )
            sockets.update({f"socket_{k}": v for k, v in churn_stats.items()})
            phases.append(sockets)
            slow = host.open(every_s=1.0)
            try:
                slowed = _phase(viewer, updates, f"{len(pages)} {kind} + a slow client (1 message/s)", phase_s)
            finally:
                slow.close()
            slowed["slow_client_read"] = slow.read
            phases.append(slowed)
    finally:
        with contextlib.redirect_stdout(sys.stderr):  # viser's "Server stopped": stdout carries --json
            handle.stop()
    pacer = handle.server.lidarloc_pacer
    base = phases[0]["scans_per_s"]
    late_with_tabs = sum(p["late_scans"] for p in phases[1:])
    return {
        "phases": phases,
        "tabs": tabs,
        "tab_kind": tab_kind,
        "tab_priority": tab_priority,
        "tabs_connected": len(pages),
        "phase_s": phase_s,
        "churn_s": churn_s,
        "realtime_scans_per_s": round(1.0 / float(np.median(np.diff(np.asarray(loc.seq.timestamps, float)))), 2),
        # kept: the rate of the phase with no client, and no scan late that was not late without them
        "rate_kept_with_tabs": bool(
            min(p["scans_per_s"] for p in phases[1:]) >= 0.95 * base and late_with_tabs <= phases[0]["late_scans"]
        ),
        "late_scans_with_tabs": late_with_tabs,
        "update_ms_median_max": max(p["update_ms_median"] for p in phases),
        # what serving the tabs costs this process: its CPU with the tabs against without them
        "cpu_pct_no_client": phases[0]["cpu_pct"],
        "cpu_pct_with_tabs": phases[1]["cpu_pct"],
        # the websocket tab's many connections give the figure; the browser tab's few, a check
        "rss_mb_per_connection": churn_stats.get("rss_mb_per_connection"),
        "connections": churn_stats.get("connects"),
        "rss_mb_first_half_of_connections": churn_stats.get("rss_mb_first_half"),
        "rss_mb_second_half_of_connections": churn_stats.get("rss_mb_second_half"),
        "rss_mb_per_browser_connection": round(browser_growth / connects, 2) if connects else None,
        # the server's pacing of new websocket connections (app/viewer/pacing.py), over the run
        "connections_admitted": pacer.admitted,
        "connections_paced": pacer.delayed,
        "connections_refused": pacer.refused,
        "targets": {"update_ms_median": 20.0, "rss_mb_per_connection": 0.0},
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
        "pid": os.getpid(),
    }
