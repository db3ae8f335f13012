"""One phase of ``lidarloc bench clients`` and its figures: the display updates timed, the CPU
each role's processes used, the RSS per connection of a websocket tab that comes and goes."""

from __future__ import annotations

import time

import numpy as np

from .common import load_avg, rss_mb
from .socket_tabs import SocketTab


def time_updates(viewer, out: list) -> None:
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


def measure_phase(viewer, updates: list, name: str, seconds: float, during=None) -> dict:
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


#: The connections the churn makes at least, however long they take: the slope of the RSS is
#: fitted over the second half of them, and ten points are the fewest it is fitted over.
MIN_CONNECTS = 20


def socket_churn(handle, seconds: float, open_tab=None) -> dict:
    """A websocket tab that connects, is counted by the server, disconnects and is let go by it,
    in a loop for ``seconds`` and until it made :data:`MIN_CONNECTS` connections (on a busy
    machine one may take a second): the connections made and this process's RSS after each one
    was let go. ``open_tab()`` opens the tab (default: a :class:`SocketTab` in this process;
    ``bench clients`` passes its :class:`~.socket_tabs.TabHost`'s, so that the RSS is the server's alone).

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
    while time.perf_counter() - t0 < seconds or len(rss) < MIN_CONNECTS:
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
