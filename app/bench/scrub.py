"""``lidarloc bench scrub``: the server-side cost of moving the viewer's timeline slider.

A recorded run (``--run DIR``, else one recorded here: the source's scans, default the town's
first 1000, 1000 particles, into ``--out`` or a temporary folder) is opened as ``lidarloc view
--run`` opens it, on a real viser server with one websocket client connected and reading
everything (viser sends on its event-loop thread, competing with the redraw for the GIL). Then
the slider is moved ``moves`` times to random steps, and each move is timed from the slider's
new value to the scene and the status redrawn (``move_ms``): the step read from the recording
(particles, estimate, S2M match, figures) and :meth:`Viewer.update_display` drawing it. The
step's scan is recomputed from the source (read or ray-cast, then the filter's random voxel
subsample: the slow part) on the viewer's scan thread and drawn when ready: ``with_scan_ms`` is
the time from the move until it is on the scene. The plots' cursor (rate-limited to a few
updates per second in the viewer: every plot's series is resent) is timed separately.

Target: median ``move_ms`` ≤ 50 ms.
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import load_avg, machine, record_run

TARGET_MS = 50.0


def _wait_quiet(client, quiet_s: float = 0.3, limit_s: float = 20.0) -> None:
    """Until the client has received something and then nothing more for ``quiet_s``."""
    deadline = time.perf_counter() + limit_s
    last, since = -1, time.perf_counter()
    while time.perf_counter() < deadline:
        n = client.bytes
        if n != last:
            last, since = n, time.perf_counter()
        elif n > 0 and time.perf_counter() - since >= quiet_s:
            return
        time.sleep(0.02)


def _time_moves(viewer, steps: np.ndarray) -> tuple[list, list, list]:
    tl = viewer.travel.timeline
    move_ms, scan_ms, plot_ms = [], [], []
    for step in steps:
        t0 = time.perf_counter()
        tl.slider.value = int(step)  # the callbacks a drag in the browser runs
        viewer.update_display()  # the step's particles, estimate, S2M match, status
        t1 = time.perf_counter()
        viewer.readouts.update_plots(force=True)
        plot_ms.append((time.perf_counter() - t1) * 1000.0)
        move_ms.append((t1 - t0) * 1000.0)
        # the scan, recomputed on the scan thread, then drawn: as the display thread polls
        deadline = t0 + 10.0
        while not viewer.travel.scan_shown and time.perf_counter() < deadline:
            viewer.update_display()
            time.sleep(0.002)
        scan_ms.append((time.perf_counter() - t0) * 1000.0)
        time.sleep(0.02)  # a drag reports ~50 positions a second
    return move_ms, scan_ms, plot_ms


def scrub(
    run_dir: Path | None = None,
    spec=None,
    seq=None,
    cfg=None,
    cache_root: Path | None = None,
    moves: int = 200,
    seed: int = 0,
    out: Path | None = None,
    progress=None,
) -> dict:
    """Time ``moves`` slider moves over the recorded run ``run_dir`` (else one recorded from ``seq``
    with ``cfg``, see the module docstring)."""
    from ..viewer.app import Viewer
    from ..viewer.runs import load_run, show_runs
    from ..viewer.token_gate import start_server
    from .viewer import _DrainingClient

    with contextlib.ExitStack() as stack:
        if run_dir is None:
            if seq is None:
                raise ValueError("scrub() needs a recorded run or a sequence to record")
            target = (
                out
                if out is not None
                else Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="lidarloc-scrub-")))
            )
            t0 = time.perf_counter()
            run_dir = record_run(spec, seq, cfg, target, cache_root, progress)
            record_s = time.perf_counter() - t0
        else:
            record_s = None
        t0 = time.perf_counter()
        run, context = load_run(run_dir, cache_root)
        open_s = time.perf_counter() - t0
        # viser prints its banner and "Server stopped" on stdout, which carries only the result
        with contextlib.redirect_stdout(sys.stderr):
            server = start_server(None, host="127.0.0.1", port=0, verbose=False)  # as the viewer's own
            client = None
            try:
                viewer = Viewer(server, autoplay=False, display_thread=False)
                show_runs(viewer, run, context)
                viewer.update_display(force_plots=True)
                client = _DrainingClient(server.get_port())
                _wait_quiet(client)  # the map goes out to the new client first
                rng = np.random.default_rng(seed)
                steps = rng.integers(0, run.n, moves)
                move_ms, scan_ms, plot_ms = _time_moves(viewer, steps)
                viewer.stop()
            finally:
                if client is not None:
                    client.close()
                server.stop()
    m, r, p = (np.asarray(a) for a in (move_ms, scan_ms, plot_ms))
    return {
        "move_ms_median": round(float(np.median(m)), 2),
        "move_ms_p90": round(float(np.percentile(m, 90)), 2),
        "move_ms_max": round(float(m.max()), 2),
        "with_scan_ms_median": round(float(np.median(r)), 2),
        "with_scan_ms_p90": round(float(np.percentile(r, 90)), 2),
        "plots_cursor_ms_median": round(float(np.median(p)), 2),
        "target_ms": TARGET_MS,
        "moves": int(moves),
        "steps": int(run.n),
        "particles_median": int(np.median(run.rec.n_particles)),
        "open_run_s": round(open_s, 2),
        "record_run_s": None if record_s is None else round(record_s, 1),
        "source": run.meta.get("source_description"),
        "load_average_1min": load_avg(),
        "machine": machine(),
    }
