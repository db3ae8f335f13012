"""``lidarloc bench viewer``: server-side cost of one display update of the live viewer.

What is timed: :meth:`Viewer.update_display` for a new snapshot — particles (heading arrows and
dots, the best one marked), 2σ ellipse, the current scan at the estimate, the S2M match when one
lands, the trajectories and the status panel — with the viewer's own scene on a real viser
server. The plots are rate-limited to a few updates per second and timed separately.

viser serialises and sends messages on its event-loop thread, per client, not on the caller's
thread; so the update is timed twice: with no client, and with one websocket client connected
and reading everything (the sends then compete with the display thread for the GIL). The second
number is the one that matters for a viewer someone is looking at.

Inputs are synthetic but sized like the real thing: a ~1M-point map, 1000 particles, a current
scan of 25 000 points (a KITTI scan after the 0.5 m random voxel filter is 15–30k), an S2M match
landing every third scan, a trajectory growing by one point per update.
Target: median ≤ 20 ms. No sequence is read: the source options do not apply.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time

import numpy as np

from ...core.geometry import pose_matrix
from ...core.maps.mapping import PriorMap
from ...core.snapshot import Event, S2MView, Snapshot
from .common import machine


def synthetic_map(rng: np.random.Generator, n: int = 1_000_000, size: float = 400.0) -> PriorMap:
    """A road grid with building walls: flat ground plus vertical façades along the streets."""
    n_ground = n // 3
    ground = np.stack(
        [rng.uniform(0, size, n_ground), rng.uniform(0, size, n_ground), rng.normal(0, 0.05, n_ground)], axis=1
    )
    n_wall = n - n_ground
    along = rng.uniform(0, size, n_wall)
    street = rng.integers(0, 8, n_wall) * (size / 8) + rng.choice([-8.0, 8.0], n_wall) + size / 16
    vertical = rng.random(n_wall) < 0.5
    x = np.where(vertical, street, along)
    y = np.where(vertical, along, street)
    walls = np.stack([x, y, rng.uniform(0, 15, n_wall)], axis=1)
    pts = np.concatenate([ground, walls]).astype(np.float32)
    return PriorMap(points=pts, points_bev=walls.astype(np.float32), voxel_size=0.2, source="bench")


def synthetic_snapshot(
    rng: np.random.Generator, k: int, n_particles: int, n_scan: int, n_scans: int, last_s2m: S2MView | None
) -> Snapshot:
    t = 0.1 * k
    x, y, yaw = 50 + 8 * t, 50 + 20 * math.sin(t / 10), math.atan2(2 * math.cos(t / 10), 8)
    T = pose_matrix(x, y, 1.73, yaw, 0.0, 0.0)
    P = np.zeros((n_particles, 11))
    P[:, :2] = (x, y) + rng.normal(0, 3.0, (n_particles, 2))
    P[:, 2] = 1.73
    P[:, 3] = yaw + rng.normal(0, 0.1, n_particles)
    w = rng.random(n_particles)
    w /= w.sum()
    r = rng.uniform(3, 50, n_scan)
    a = rng.uniform(-np.pi, np.pi, n_scan)
    scan = np.stack([x + r * np.cos(a), y + r * np.sin(a), rng.uniform(0, 10, n_scan)], axis=1).astype(np.float32)
    s2m = last_s2m
    if k % 3 == 2:
        s2m = S2MView(
            started_at=k - 2,
            landed_at=k,
            accepted=bool(k % 2),
            score=150.0,
            start_score=60.0,
            pose=T,
            scan_world=scan[::4].copy(),
            region=(x - 25, y - 25, x + 25, y + 25),
            ms=40.0,
        )
    cov = np.diag([9.0, 9.0, 0.01])
    return Snapshot(
        scan_index=k,
        n_scans=n_scans,
        timestamp=t,
        particles=P,
        weights=w,
        best_index=int(np.argmax(w)),
        mean_pose=T,
        cov_xyz=cov,
        std_xyz=np.sqrt(np.diag(cov)),
        ellipse_xy=(6.0, 6.0, 0.0),
        n_eff=float(1 / (w**2).sum()),
        localized=k > 20,
        localized_since=20 if k > 20 else None,
        scan_world=scan,
        gt_pose=T,
        error_m=0.3,
        pf_ms=45.0,
        s2m=s2m,
        s2m_running=k % 3 != 2,
        s2m_acceptance=0.5,
        events=(Event(k, "s2m_accepted" if k % 2 else "s2m_rejected"),),
    )


class _DrainingClient:
    """A websocket client that speaks viser's subprotocol and reads (and drops) every message."""

    def __init__(self, port: int):
        import threading

        import viser
        from websockets.sync.client import connect

        self.ws = connect(
            f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None, open_timeout=10
        )
        self.bytes = 0
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self):
        try:
            for msg in self.ws:
                self.bytes += len(msg)
        except Exception:  # closed at the end of the run
            pass

    def close(self):
        self.ws.close()
        self._thread.join(timeout=2)


def _time_updates(viewer, rng, n_updates, n_particles, n_scan) -> tuple[list, list]:
    update_ms, plot_ms = [], []
    s2m = None
    for k in range(n_updates):
        snap = synthetic_snapshot(rng, k, n_particles, n_scan, n_updates, s2m)
        s2m = snap.s2m
        viewer.publish(snap)
        update_ms.append(viewer.update_display())
        t1 = time.perf_counter()
        viewer.readouts.update_plots(force=True)
        plot_ms.append((time.perf_counter() - t1) * 1000.0)
        time.sleep(0.01)  # 100 Hz at most, like a fast replay; lets the sends go out in between
    return update_ms[5:], plot_ms  # the first few updates create the nodes


def _measure(rng, n_updates: int, n_particles: int, n_scan: int, map_points: int) -> tuple:
    from ..viewer.app import Viewer
    from ..viewer.token_gate import start_server

    server = start_server(None, host="127.0.0.1", port=0, verbose=False)  # as the viewer's own
    client = None
    try:
        viewer = Viewer(server, autoplay=False, display_thread=False)
        t0 = time.perf_counter()
        viewer.scene.set_map(synthetic_map(rng, map_points))
        map_ms = (time.perf_counter() - t0) * 1000.0
        bare, _ = _time_updates(viewer, rng, n_updates, n_particles, n_scan)
        client = _DrainingClient(server.get_port())
        with_client, plot_ms = _time_updates(viewer, rng, n_updates, n_particles, n_scan)
        received_mb = client.bytes / 1e6
        viewer.stop()
    finally:
        if client is not None:
            client.close()
        server.stop()
    return with_client, bare, plot_ms, received_mb, map_ms


def run(
    n_updates: int = 150, n_particles: int = 1000, n_scan: int = 25_000, map_points: int = 1_000_000, seed: int = 0
) -> dict:
    rng = np.random.default_rng(seed)
    # viser prints its banner and "Server stopped" on stdout, which carries only the result
    with contextlib.redirect_stdout(sys.stderr):
        with_client, bare, plot_ms, received_mb, map_ms = _measure(rng, n_updates, n_particles, n_scan, map_points)
    u, b = np.asarray(with_client), np.asarray(bare)
    return {
        "update_ms_median": round(float(np.median(u)), 2),
        "update_ms_p90": round(float(np.percentile(u, 90)), 2),
        "update_ms_max": round(float(u.max()), 2),
        "update_ms_median_no_client": round(float(np.median(b)), 2),
        "plots_ms_median": round(float(np.median(plot_ms)), 2),
        "client_received_mb": round(received_mb, 1),
        "map_send_ms": round(map_ms, 1),
        "target_ms": 20.0,
        "n_updates": n_updates,
        "n_particles": n_particles,
        "scan_points": n_scan,
        "map_points": map_points,
        "machine": machine(),
    }
