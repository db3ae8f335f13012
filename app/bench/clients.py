"""``lidarloc bench clients``: the live viewer with many browser tabs and bad clients.

The viewer runs in this process on the real-time clock, the drive in a loop; the phases follow
each other, ``phase_s`` seconds each: no client; five headless Chromium tabs; the five and a sixth
tab that connects, waits for the page and disconnects in a loop; the five and a websocket tab
that connects and disconnects in a loop (:func:`~.client_phases.socket_churn`: hundreds of
connections where a browser tab makes a few); the five and a slow client (a websocket that reads
one message a second). Per phase: the filter's scans per second and late
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
tabs instead (:class:`~.socket_tabs.SocketTab`: everything the server sends, read and not
drawn): with no browser on the machine, the phases show what serving the tabs costs the viewer itself
(``cpu_pct`` per phase: this process's CPU, every thread).

The viewer lets new websocket connections in at a bounded rate (:mod:`lidarloc.app.viewer.pacing`):
the tab that connects and disconnects as fast as it can is held in its opening handshake beyond
that rate, as any client in such a loop would be; ``connections_paced`` and
``connections_refused`` say how often.

The websocket clients (those tabs, the one that connects and disconnects, the slow one) live in a
process of their own, never in the viewer's (:mod:`.socket_tabs` says why).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time

import numpy as np

from .chromium import CHROMIUM, CHROMIUM_ARGS, check_tab_priority, chromium_at
from .client_phases import measure_phase, socket_churn, time_updates
from .common import load_avg, machine
from .socket_tabs import TabHost

LOAD_TIMEOUT_MS = 120_000
TAB_KINDS = ("chromium", "socket")


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
    ``tab_kind="socket"``: the tabs are websocket tabs (:class:`~.socket_tabs.SocketTab`:
    everything the server sends, read and not drawn), so the phases measure what serving them
    costs the viewer without any browser's rendering on the machine (no browser tab connecting and disconnecting then).
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
    time_updates(viewer, updates)
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
            phases.append(measure_phase(viewer, updates, "no client", phase_s))
            for _ in range(tabs):
                try:
                    pages.append(_open_tab(browser, handle) if browser is not None else host.open())
                except TimeoutError:  # said in the result: the phases run with the tabs that got through
                    failed += 1
            stack.callback(lambda: [page.close() for page in pages])
            tab_failures = failed
            kind = "tabs" if browser is not None else "websocket tabs"
            phases.append(measure_phase(viewer, updates, f"{len(pages)} {kind}", phase_s))
            if browser is not None:

                def churn():
                    nonlocal connects
                    nonlocal failed
                    try:
                        _open_tab(browser, handle).close()
                        connects += 1
                    except TimeoutError:  # counted: on a saturated machine a tab may not get through
                        failed += 1

                churned = measure_phase(
                    viewer, updates, f"{len(pages)} tabs + one connecting and disconnecting", phase_s, during=churn
                )
                churned["connects"] = connects
                churned["connects_timed_out"] = failed - tab_failures
                phases.append(churned)
                browser_growth = churned["rss_mb_end"] - churned["rss_mb_start"]
            sockets = measure_phase(
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
                slowed = measure_phase(viewer, updates, f"{len(pages)} {kind} + a slow client (1 message/s)", phase_s)
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
