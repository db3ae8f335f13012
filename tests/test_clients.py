"""A client on a slow link does not slow the filter: a websocket that reads one message a second
is connected while the viewer plays and draws every step; the player and the display go on at
their own pace, and the slow client is still connected (its updates were dropped, not queued for
the filter to wait on)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import pytest
from helpers import wait_for
from lidarloc.app.bench import chromium, clients
from lidarloc.app.bench.client_phases import socket_churn, time_updates
from lidarloc.app.bench.socket_tabs import SocketTab, TabHost
from lidarloc.app.viewer import heap as heap_module


def test_a_slow_client_does_not_slow_the_filter_or_the_display(viewer):
    v, loc = viewer.viewer, viewer.localizer
    updates: list = []
    time_updates(v, updates)
    slow = SocketTab(viewer.port, every_s=1.0)
    try:
        v.controls.s2m_enabled.value = False  # the filter alone: its pace is the one that matters here
        v.controls.speed.value = "max"
        t0 = time.perf_counter()
        v.controls.play.value = True
        wait_for(lambda: loc.k >= 12, timeout=120, what="12 scans played")
        played_s = time.perf_counter() - t0
        wait_for(lambda: len(updates) >= 5, what="display updates meanwhile")
        # the slow client read a message a second at most: far fewer than the updates sent to it
        assert slow.read <= played_s + 2
        assert not v.step_failed and v.display_faults.count == 0
    finally:
        slow.close()
    assert sorted(updates)[len(updates) // 2] < 1000.0  # the median update did not wait on the slow client


def test_idle_tabs_run_at_the_idle_cpu_priority(tmp_path, monkeypatch):
    """The benchmark's tabs at ``idle`` start Chromium (here a stand-in that reports its own
    scheduling policy) under SCHED_IDLE; at ``normal`` as any other process."""
    if shutil.which("chrt") is None:
        pytest.skip("chrt (util-linux) is not installed")
    stand_in = tmp_path / "chromium"
    stand_in.write_text(f"#!{sys.executable}\nimport os\nprint(os.sched_getscheduler(0))\n")
    stand_in.chmod(0o755)
    monkeypatch.setattr(chromium, "CHROMIUM", stand_in)
    policies = {}
    for priority in chromium.TAB_PRIORITIES:
        with chromium.chromium_at(priority) as executable:
            out = subprocess.run([str(executable), "--headless"], capture_output=True, text=True, check=True)
            policies[priority] = int(out.stdout)
    assert policies == {"idle": os.SCHED_IDLE, "normal": os.SCHED_OTHER}
    with pytest.raises(ValueError, match="tab priority"):
        with chromium.chromium_at("high"):
            pass


def test_hosted_tabs_are_clients_of_another_process_at_the_idle_priority(viewer):
    """The benchmark's websocket tabs live in a process of their own at the idle CPU priority (their
    reading is the clients' work, not the server's): a hosted tab is counted by the server, reads
    what it sends and is let go when closed; a host whose process died says so in one line."""
    from lidarloc.core.errors import LidarlocError

    with TabHost(viewer.port, "idle") as host:
        tab = host.open()  # answered: the process has set itself up
        assert host._proc.pid != os.getpid()
        assert os.sched_getscheduler(host._proc.pid) == os.SCHED_IDLE
        wait_for(lambda: len(viewer.server.get_clients()) == 1, what="the server to count the hosted tab")
        read = tab.close()
        assert read is not None and read > 0  # the scene, sent to every new tab
        assert tab.close() == read  # closed once
        wait_for(lambda: viewer.server.get_clients() == {}, what="the server to let the hosted tab go")
        host._proc.kill()
        host._proc.join()
        with pytest.raises(LidarlocError, match="tabs' process ended with status -9"):
            host.open()
    assert host.stopped and not host._proc.is_alive()
    with pytest.raises(ValueError, match="tab priority"):
        TabHost(viewer.port, "high")


def test_a_tab_that_comes_and_goes_leaves_nothing_behind(viewer):
    """Every connection's server-side state (viser's client handle, the viewer's camera folder for
    it) is let go when the tab disconnects: a websocket tab connecting and disconnecting in a loop
    leaves no client handle alive and no camera folder behind."""
    import gc
    import weakref

    handles: list = []
    viewer.server.on_client_connect(lambda client: handles.append(weakref.ref(client)))
    heap = viewer.viewer.heap
    trims_before = heap.trims
    t0 = time.perf_counter()
    r = socket_churn(viewer, seconds=6.0)
    if heap.available:  # what the tabs freed went back to the system, at most once per interval
        wait_for(lambda: heap.trims > trims_before, what="a heap trim after the tabs left")
        elapsed = time.perf_counter() - t0
        assert heap.trims - trims_before <= 1 + elapsed / heap_module.MIN_INTERVAL_S, (heap.trims, elapsed)
    assert r["connects"] >= 15 and r["rss_mb_per_connection"] is not None, r
    # viser runs the connect callbacks on its own threads: the last ones may still be running
    wait_for(lambda: len(handles) == r["connects"], what="every connection's callback")
    assert viewer.server.get_clients() == {}
    wait_for(lambda: viewer.viewer.cameras._tabs == {}, what="no camera folder left")
    gc.collect()
    alive = [ref for ref in handles if ref() is not None]
    assert not alive, f"{len(alive)} of {len(handles)} disconnected tabs' client handles are still referenced"


@pytest.mark.slow
def test_bench_clients_with_websocket_tabs_measures_every_phase(street, cache_root):
    """``bench clients --tab-kind socket``: the phases run with websocket tabs (no browser), each
    with the filter's rate, the process's CPU and the display update; the websocket tab's many
    connections give the memory per connection, over a phase of its own length (``--churn-s``)."""
    from helpers import make_localizer

    loc = make_localizer(street, cache_root)
    try:
        # phases as short as still let each phase see scans and S2M's work (the figures
        # themselves are `lidarloc bench clients`'s, at its default 45 s a phase); the churn long
        # enough for the 20 connections the per-connection slope needs
        r = clients.run(loc, tabs=2, phase_s=3.0, tab_kind="socket", churn_s=9.0)
    finally:
        loc.close()
    names = [p["phase"] for p in r["phases"]]
    assert names == [
        "no client",
        "2 websocket tabs",
        "2 websocket tabs + a websocket tab connecting and disconnecting",
        "2 websocket tabs + a slow client (1 message/s)",
    ]
    assert r["tabs_connected"] == 2 and r["tab_priority"] == "idle"
    seconds = [p["seconds"] for p in r["phases"]]
    assert seconds[2] >= 9.0 and max(seconds[:2] + seconds[3:]) < 9.0, seconds
    assert r["connections"] >= 10 and r["rss_mb_per_connection"] is not None, r
    assert all(p["cpu_pct"] > 0 and p["scans_per_s"] > 0 for p in r["phases"]), r["phases"]
    # where the CPU went: the clients' process works while the tab churns (it is none of the
    # localizer's children, which register scans in every phase), and the machine is busier than
    # the viewer's process alone
    import os

    churn = r["phases"][2]
    assert churn["clients_cpu_pct"] > 0, churn
    assert all(p["localizer_children_cpu_pct"] > 0 for p in r["phases"]), r["phases"]
    assert all(p["cpu_pct"] * 0.5 < p["machine_busy_pct"] <= 100.0 * os.cpu_count() + 5 for p in r["phases"]), r[
        "phases"
    ]
    assert r["connections_admitted"] >= r["connections"] and r["connections_refused"] == 0, r
    assert r["rss_mb_per_browser_connection"] is None  # no browser tab came and went
    with pytest.raises(ValueError, match="tab kind"):
        clients.run(loc, tab_kind="firefox")


def test_the_viewer_caps_its_malloc_arenas_unless_the_user_did():
    """``view``/``demo`` cap glibc's arenas (heap.py: the high-water mark under many connections
    is a fifth); a ``MALLOC_ARENA_MAX`` of the user's own is left as it is. Run in a fresh process
    so that the cap does not reach the test session's own allocator."""
    code = "from lidarloc.app.viewer.heap import limit_arenas; print(limit_arenas())"
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    if getattr(heap_module._libc(), "mallopt", None) is None:
        pytest.skip("not glibc: no arenas to cap")
    capped = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert capped.stdout.strip() == "True"
    env["MALLOC_ARENA_MAX"] = "4"
    left = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert left.stdout.strip() == "False"
