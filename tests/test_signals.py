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


@pytest.fixture(scope="module")
def town_map(cache_root, tmp_path_factory):
    """The short town's map in the session cache (built once, by a short run)."""
    from helpers import record_run

    record_run(tmp_path_factory.mktemp("warm") / "run", cache_root, scans=2)
    return cache_root


def _ignore_sigint() -> None:  # what a shell without job control does to a command started with &
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.slow
@pytest.mark.parametrize(
    "sig, background", [(signal.SIGTERM, False), (signal.SIGHUP, False), (signal.SIGINT, True)], ids=str
)
def test_a_stop_signal_stops_a_run_like_ctrl_c(town_map, tmp_path, sig, background):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "lidarloc.app.cli", "run", "--out", str(out), "--scans", "60"]
    cmd += ["--set", f"town.n_scans={MAPPING_SCANS}", "--set", "pf.n_particles=300", "--cache", str(town_map)]
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
