"""SIGTERM and SIGHUP stop ``lidarloc run`` as Ctrl-C does (app/console.py's stop_signals_like_ctrl_c),
Ctrl-C works in a run started in the background (SIGINT ignored at its start), and no child
process outlives the stop."""

import json
import signal
import subprocess
import sys

import psutil
import pytest
from helpers import MAPPING_SCANS, process_gone, wait_for

# Only bounds a hang: a stop takes well under 2 s.
STOP_BOUND_S = 60


def _ignore_sigint() -> None:  # what a shell without job control does to a command started with &
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.slow
@pytest.mark.parametrize(
    "sig, background", [(signal.SIGTERM, False), (signal.SIGHUP, False), (signal.SIGINT, True)], ids=str
)
def test_a_stop_signal_stops_a_run_like_ctrl_c(town_cache, tmp_path, sig, background):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "lidarloc.app.cli", "run", "--out", str(out), "--scans", "60"]
    cmd += ["--set", f"town.n_scans={MAPPING_SCANS}", "--set", "pf.n_particles=300", "--cache", str(town_cache)]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_ignore_sigint if background else None,
    )
    try:
        for line in proc.stderr:  # type: ignore[union-attr]
            if "localizing" in line:
                break
        parent = psutil.Process(proc.pid)
        # both blocks' child processes are up before the signal
        wait_for(lambda: len(parent.children(recursive=True)) >= 2, timeout=STOP_BOUND_S, what="the child processes")
        children = [c.pid for c in parent.children(recursive=True)]
        proc.send_signal(sig)
        _, rest = proc.communicate(timeout=STOP_BOUND_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, rest
    assert "Traceback" not in rest
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True
    for pid in children:
        wait_for(lambda pid=pid: process_gone(pid), timeout=5, what=f"child {pid} to end")


@pytest.mark.timeout(30)
def test_the_viewers_wait_for_a_stop_signal_ends_when_another_thread_takes_the_signal():
    """A signal sent to the process may be taken by any of its threads; Python then runs the
    handler only when the main thread next runs Python code. ``wait_for_stop`` must return all
    the same (an untimed ``Event.wait()`` here never returned: the viewer outlived its SIGTERM)."""
    import threading
    import time

    from lidarloc.app.console import wait_for_stop

    stop = threading.Event()
    previous = signal.signal(signal.SIGUSR1, lambda *_: stop.set())
    idle = threading.Event()
    other = threading.Thread(target=idle.wait, daemon=True)  # a thread of the process, not the main one
    other.start()
    try:
        # the signal goes to that thread: its C handler notes it, the main thread runs the handler
        threading.Timer(0.3, signal.pthread_kill, args=(other.ident, signal.SIGUSR1)).start()
        t0 = time.perf_counter()
        wait_for_stop(stop)
        waited = time.perf_counter() - t0
    finally:
        idle.set()
        signal.signal(signal.SIGUSR1, previous)
    assert stop.is_set() and waited < 5.0, waited
