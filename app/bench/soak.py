"""``lidarloc bench soak``: a long run of the live viewer, to see that it keeps working.

A real ``lidarloc demo`` (``view SOURCE`` with a source) is started in a child process with
``--autoplay --loop`` on the real-time clock, recording on (into the soak's own folder, kept to
the viewer's default budget), with one client attached: a headless Chromium tab (Playwright;
without it the soak runs with no client and says so), or a websocket tab that reads everything
the server sends without drawing it (``socket``: on a machine without a GPU the browser's
software rendering takes a core of its own, which on 2 cores makes every scan late whatever the
viewer does). Every ``sample_s`` seconds the process tree is sampled: resident memory (the viewer
and its child processes), open file descriptors, the viewer's threads, its child processes, and
the recordings' size. Each loop's line (``loop N: S scans, L late, …``) gives the late scans (a
step that started over one scan period after its scan arrived) and the viewer's full garbage
collections, how many and the longest (each holds the GIL while it runs).

Growth is measured from the first samples after the first loop ended (warm-up: caches filled,
the map drawn, the first recording opened) to the last ones: for memory, the median of the last
five minutes' samples minus the median of the first five minutes' (:data:`MEMORY_WINDOW_S`;
``rss_growth_mb_single_samples`` gives the same from two single samples); for file descriptors,
threads and child processes, the last sample minus the first. ``recording_mb_per_hour`` is what was
written per hour (each run folder at the largest size it was seen with), whatever the budget
removed since. After the stop, any process of the tree still alive is an orphan.
Targets: RSS growth ≤ 50 MB after the first loop, fds / threads / children constant, no late
scans beyond the first loop's.
"""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

from ...core.errors import LidarlocError
from ..viewer.token_gate import TOKEN_ENV
from .chromium import CHROMIUM, CHROMIUM_ARGS
from .common import load_avg, machine, median
from .socket_tabs import SocketTab

_URL = re.compile(r"(http://[0-9a-z.\-]+:\d+)")
_LOOP = re.compile(
    r"^loop (\d+): (\d+) scans, (\d+) late, largest lag ([0-9.]+) s"
    r"(?:, (\d+) full garbage collections \(longest ([0-9.]+) ms\))?"
)
FIELDS = ("t_s", "rss_mb", "viewer_rss_mb", "fds", "threads", "children", "recording_mb", "loops", "load_1min")


def parse_loop_line(line: str) -> dict | None:
    """The fields of a ``demo --loop`` loop line, or None if ``line`` is not one. The full
    collections' fields are None where the line has none (a viewer that does not count them)."""
    m = _LOOP.match(line)
    if m is None:
        return None
    return {
        "loop": int(m.group(1)),
        "scans": int(m.group(2)),
        "late": int(m.group(3)),
        "max_lag_s": float(m.group(4)),
        "full_collections": int(m.group(5)) if m.group(5) else None,
        "longest_full_collection_ms": float(m.group(6)) if m.group(6) else None,
    }


class _Output:
    """The demo's console, read on a thread: the URL, ``ready:``, each loop's line."""

    def __init__(self, proc: subprocess.Popen, t0: float):
        self.url: str | None = None
        self.ready = threading.Event()
        self.loops: list[dict] = []
        self.tail: list[str] = []
        self._t0 = t0
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc) -> None:
        for line in proc.stdout:
            line = line.rstrip()
            self.tail = (self.tail + [line])[-8:]
            m = _URL.search(line)
            if self.url is None and m:
                self.url = m.group(1)
            if line.startswith("ready:") or "the first scan failed" in line:
                self.ready.set()
            loop = parse_loop_line(line)
            if loop is not None:
                self.loops.append({**loop, "t_s": round(time.perf_counter() - self._t0, 1)})
        self.ready.set()  # the demo ended: nobody waits for it any longer


def _tree(pid: int):
    import psutil

    root = psutil.Process(pid)
    return root, root.children(recursive=True)


def sample(pid: int) -> dict:
    """The process tree of ``pid`` now: RSS (all, and the viewer's own), fds, threads, children."""
    import psutil

    root, kids = _tree(pid)
    rss, fds = root.memory_info().rss, root.num_fds()
    for k in kids:
        try:
            rss += k.memory_info().rss
            fds += k.num_fds()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return {
        "rss_mb": round(rss / 1e6, 1),
        "viewer_rss_mb": round(root.memory_info().rss / 1e6, 1),
        "fds": fds,
        "threads": root.num_threads(),
        "children": len(kids),
    }


def _written_mb(record_dir: Path, seen: dict) -> tuple[float, float]:
    """(size on disk now, written in all) in MB: each run folder counted at its largest size."""
    from ..viewer.budget import find_runs

    runs = find_runs(record_dir)
    for r in runs:
        seen[r.path] = max(seen.get(r.path, 0), r.bytes)
    return sum(r.bytes for r in runs) / 1e6, sum(seen.values()) / 1e6


def _open_client(url: str):
    """One headless Chromium tab on the viewer (None, with the reason, without Playwright or Chromium)."""
    if not CHROMIUM.exists():
        return None, "no /usr/bin/chromium"
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None, "Python Playwright not installed"

    pw = sync_playwright().start()
    browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
    page = browser.new_page()
    page.goto(url, timeout=120_000)
    return (pw, browser, page), "one headless Chromium tab"


def _close_client(client) -> None:
    if client is None:
        return
    if isinstance(client, SocketTab):
        client.close()
        return
    pw, browser, _ = client
    try:
        browser.close()
    finally:
        pw.stop()


def growth(rows: list[dict], since_s: float | None, key: str) -> float | None:
    """Last sample minus the first one at or after ``since_s`` (None: too few samples)."""
    after = [r for r in rows if since_s is None or r["t_s"] >= since_s]
    if len(after) < 2:
        return None
    return round(after[-1][key] - after[0][key], 1)


#: Memory is compared between windows of samples, not single samples: resident memory swings by
#: tens of MB within a loop (a sample taken while a scan-to-map match holds its GICP target, or
#: right after it was freed), so two single samples measure when they fell more than any leak.
MEMORY_WINDOW_S = 300.0


def memory_growth(rows: list[dict], since_s: float | None, key: str, window_s: float = MEMORY_WINDOW_S) -> float | None:
    """Median of the last ``window_s`` of samples minus the median of the first ``window_s`` at or
    after ``since_s`` (each window at most a third of the span, so they never overlap; None: too
    few samples)."""
    after = [r for r in rows if since_s is None or r["t_s"] >= since_s]
    if len(after) < 2:
        return None
    t0, t1 = after[0]["t_s"], after[-1]["t_s"]
    w = min(window_s, (t1 - t0) / 3.0)
    first = [r[key] for r in after if r["t_s"] <= t0 + w]
    last = [r[key] for r in after if r["t_s"] >= t1 - w]
    return round(median(last) - median(first), 1)


CLIENTS = ("chromium", "socket", "none")


def run(
    command: list[str],
    minutes: float,
    out_dir: Path,
    sample_s: float = 10.0,
    cache: str | None = None,
    client: str = "chromium",
    start_timeout_s: float = 900.0,
) -> dict:
    """Soak ``lidarloc <command>`` (``demo`` or ``view`` and its source options) for ``minutes``
    after it is ready; samples into ``out_dir/soak.csv``, a plot into ``out_dir/soak.png``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    record_dir = out_dir / "runs"
    cmd = [sys.executable, "-m", "lidarloc.app.cli", *command, "--autoplay", "--loop", "--port", "0"]
    cmd += ["--record-dir", str(record_dir), "--set", "localize.clock=realtime"]
    cmd += ["--cache", cache] if cache else []
    env = dict(os.environ, COLUMNS="200")
    env.pop(TOKEN_ENV, None)  # the bench's own loopback viewer: its client brings no token
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1, env=env, start_new_session=True
    )
    out = _Output(proc, t0)
    rows: list[dict] = []
    seen: dict = {}
    tree_pids: set[tuple[int, float]] = set()  # (pid, start time): a pid alone may be reused
    client_handle, client_note = None, "none"
    try:
        if not out.ready.wait(start_timeout_s) or proc.poll() is not None or out.url is None:
            raise LidarlocError(f"lidarloc {command[0]} did not become ready: " + " | ".join(out.tail))
        ready_s = time.perf_counter() - t0
        if client == "chromium":
            client_handle, client_note = _open_client(out.url)
        elif client == "socket":
            client_handle, client_note = SocketTab(urlsplit(out.url).port), "one websocket tab"
        end = time.perf_counter() + 60.0 * minutes
        next_t = time.perf_counter()
        while time.perf_counter() < end and proc.poll() is None:
            now = time.perf_counter()
            s = sample(proc.pid)
            tree_pids |= _identities(_tree(proc.pid)[1])
            on_disk, _ = _written_mb(record_dir, seen)
            rows.append(
                {
                    "t_s": round(now - t0, 1),
                    **s,
                    "recording_mb": round(on_disk, 1),
                    "loops": len(out.loops),
                    "load_1min": round(load_avg(), 2),
                }
            )
            _write_csv(out_dir / "soak.csv", rows[-1:], append=len(rows) > 1)  # a soak cut short keeps its samples
            next_t += sample_s
            time.sleep(max(0.0, min(next_t, end) - time.perf_counter()))
        crashed = proc.poll() is not None
        _, written = _written_mb(record_dir, seen)
    finally:
        _close_client(client_handle)
        stop_t = time.perf_counter()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)  # what a service manager sends: it must stop as Ctrl-C does
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        stop_s = time.perf_counter() - stop_t
    orphans = _alive(tree_pids)
    orphan_commands = [_command_line(p) for p in orphans]
    for p in orphans:  # do not leave them behind the benchmark either (the very process: pid and start time)
        try:
            p.kill()
        except Exception:  # gone meanwhile
            pass
    first_loop_s = out.loops[0]["t_s"] if out.loops else None
    _plot(out_dir / "soak.png", rows, first_loop_s)
    hours = (rows[-1]["t_s"] - ready_s) / 3600.0 if rows else 0.0
    after = out.loops[1:]
    return {
        "minutes": minutes,
        "client": client_note,
        "ready_s": round(ready_s, 1),
        "loops": len(out.loops),
        "loop_lines": out.loops,
        "samples": len(rows),
        "first_loop_end_s": first_loop_s,
        "rss_mb_after_first_loop": next((r["rss_mb"] for r in rows if first_loop_s and r["t_s"] >= first_loop_s), None),
        "rss_growth_mb": memory_growth(rows, first_loop_s, "rss_mb") if first_loop_s else None,
        "viewer_rss_growth_mb": memory_growth(rows, first_loop_s, "viewer_rss_mb") if first_loop_s else None,
        # the same from two single samples (the last one and the first after the first loop)
        "rss_growth_mb_single_samples": growth(rows, first_loop_s, "rss_mb") if first_loop_s else None,
        "fd_growth": growth(rows, first_loop_s, "fds") if first_loop_s else None,
        "thread_growth": growth(rows, first_loop_s, "threads") if first_loop_s else None,
        "children_growth": growth(rows, first_loop_s, "children") if first_loop_s else None,
        "late_scans_first_loop": out.loops[0]["late"] if out.loops else None,
        "late_scans_after_first_loop": sum(x["late"] for x in after) if after else None,
        # the viewer's full garbage collections (each holds the GIL; see app/viewer/collector.py)
        "full_collections_after_first_loop": _total(after, "full_collections"),
        "longest_full_collection_ms_after_first_loop": _largest(after, "longest_full_collection_ms"),
        "recording_mb_per_hour": round(written / hours, 1) if hours > 0 else None,
        "recording_mb_on_disk": rows[-1]["recording_mb"] if rows else None,
        "crashed": crashed,
        "stop_s": round(stop_s, 2),
        "exit_code": proc.returncode,
        "orphans_after_stop": len(orphans),
        "orphan_commands": orphan_commands,
        "targets": {"rss_growth_mb": 50.0, "fd_growth": 0, "thread_growth": 0, "children_growth": 0},
        "load_average_1min": round(load_avg(), 2),
        "load_average_max": max((r["load_1min"] for r in rows), default=None),
        "machine": machine(),
        "csv": str(out_dir / "soak.csv"),
        "plot": str(out_dir / "soak.png"),
    }


def _total(loops: list[dict], key: str) -> int | None:
    values = [x[key] for x in loops if x.get(key) is not None]
    return sum(values) if values else None


def _largest(loops: list[dict], key: str) -> float | None:
    values = [x[key] for x in loops if x.get(key) is not None]
    return max(values) if values else None


def _identities(procs) -> set[tuple[int, float]]:
    import psutil

    out = set()
    for p in procs:
        try:
            out.add((p.pid, p.create_time()))
        except psutil.Error:  # ended meanwhile
            pass
    return out


def _command_line(p) -> str:
    """What an orphan runs (its command line), to say which block left it behind."""
    import psutil

    try:
        return " ".join(p.cmdline())
    except psutil.Error:  # ended meanwhile
        return f"pid {p.pid} (ended)"


def _alive(seen: set[tuple[int, float]]) -> list:
    """The processes of the demo's tree still running: the same pid and the same start time (on a
    shared machine a pid freed during a long soak is soon another user's process)."""
    import psutil

    alive = []
    for pid, started in seen:
        try:
            p = psutil.Process(pid)
            if p.create_time() == started and p.status() != psutil.STATUS_ZOMBIE:
                alive.append(p)
        except psutil.Error:
            pass
    return alive


def _write_csv(path: Path, rows: list[dict], append: bool = False) -> None:
    with open(path, "a" if append else "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        if not append:
            w.writeheader()
        w.writerows(rows)


def _plot(path: Path, rows: list[dict], first_loop_s: float | None) -> None:
    if not rows:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["t_s"] / 60.0 for r in rows]
    fig, axes = plt.subplots(5, 1, figsize=(8, 10), sharex=True)
    for ax, key, label in zip(
        axes,
        ("rss_mb", "fds", "threads", "children", "recording_mb"),
        ("RSS, viewer + children (MB)", "open fds", "viewer threads", "child processes", "recordings on disk (MB)"),
        strict=True,
    ):
        ax.plot(t, [r[key] for r in rows])
        ax.set_ylabel(label, fontsize=8)
        if first_loop_s is not None:
            ax.axvline(first_loop_s / 60.0, color="grey", linestyle=":", linewidth=1)
    axes[-1].set_xlabel("minutes since launch (dotted: end of the first loop)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
