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

In a real browser too (Debian's headless Chromium through Playwright, as the browser tests):
the live viewer on the short town (its first 400 scans, mapped from 150) playing at 5 scans/s,
one tab open: ``first_surface_ms``, from the press on "Likelihood surface here" to a surface's
read-out in the page (its first, coarse pass; target ≤ 1000 ms) and ``full_surface_ms`` to the
full one's, each request on the scan then shown; ``kidnap_display_resume_s``, from the Kidnap click
to the status showing a scan past the jump (target ≤ 2 s), and ``top_down_ms``, from the
"Top-down view" click to the tab's camera having moved (target ≤ 500 ms); medians of three (the
run's very first surface is in ``first_surface_ms_each`` too). Each is timed on the page's own
clock, from the press's event (its time stamp) to the first frame or text that shows the answer:
what a user waits for after a click, without the time Playwright spends deciding where to click
(seconds on a busy page). Without Chromium or Playwright those fields are None and ``browser``
says why.
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


BROWSER_REPEATS = 3
KIDNAP_SKIP = 20
SETTLE_TIMEOUTS = 4  # how many of the page's time limits a kidnapped run may wait for S2M
JS_SCAN = "(() => { const m = document.body.innerText.match(/Scan (\\d+) of \\d+/); return m ? +m[1] : -1; })()"
JS_CAMERA = "window.__viserMutable.camera.position.toArray()"


def camera_moved_by(before, metres: float) -> str:
    """A condition in the page: its camera is more than ``metres`` from ``before`` (JS_CAMERA)."""
    x, y, z = before
    return (
        f"(() => {{ const p = window.__viserMutable.camera.position; "
        f"return Math.hypot(p.x - {x}, p.y - {y}, p.z - {z}) > {metres}; }})()"
    )


# in the page, on its clock (ms): the next press (window.__press), from its event's time stamp
JS_WATCH_PRESS = """window.__press = null;
document.addEventListener('mousedown', e => { window.__press = Math.min(e.timeStamp, performance.now()); },
                          {capture: true, once: true});
"""
# … each new scan the status shows, when it showed it ([ms, scan] in window.__scans) …
JS_WATCH_SCANS = """window.__scans = [];
new MutationObserver(() => {
    const m = document.body.textContent.match(/Scan (\\d+) of \\d+/);
    const s = window.__scans;
    if (m && (!s.length || s[s.length - 1][1] !== +m[1])) s.push([performance.now(), +m[1]]);
}).observe(document.body, {subtree: true, childList: true, characterData: true});
"""
# … and the first frame after the press whose camera is where MOVED says (window.__moved)
JS_WATCH_CAMERA = """window.__moved = null;
(function frame() {
    if (window.__press !== null && MOVED) { window.__moved = performance.now(); return; }
    requestAnimationFrame(frame);
})();
"""
# in the page: the time (page clock, ms) of the first press from now on, and of the first new
# surface read-out after it (its scan, maximum and cells differ from the one shown before) and
# of the first new one in the full cells (FULL)
JS_WATCH_SURFACE = """(() => {
    const re = /scan (\\d+): maximum at \\([^)]*\\)[\\s\\S]*?\\d+×\\d+ cells of ([\\d.]+) m/;
    const now = () => { const m = document.body.textContent.match(re); return m ? m : null; };
    const before = now();
    const w = window.__surface = {down: null, first: null, full: null};
    document.addEventListener('mousedown', e => {
        if (w.down === null) w.down = Math.min(e.timeStamp, performance.now());
    }, {capture: true, once: true});
    const obs = new MutationObserver(() => {
        const m = now();
        if (w.down === null || m === null || (before !== null && m[0] === before[0])) return;
        if (w.first === null) w.first = performance.now();
        if (m[2] === FULL) { w.full = performance.now(); obs.disconnect(); }
    });
    obs.observe(document.body, {subtree: true, childList: true, characterData: true});
})()"""


def _surface_ms(page, timeout_ms: float) -> tuple[float, float]:
    """Press "Likelihood surface here" once: (ms to the first surface's read-out, ms to the full
    one's), on the page's clock. The scans play: each press is on a newer scan than the last."""
    from ...core.filter.surface import CELL

    page.evaluate(JS_WATCH_SURFACE.replace("FULL", repr(f"{CELL:g}")))
    page.get_by_role("button", name="Likelihood surface here").click(timeout=timeout_ms)
    page.wait_for_function("window.__surface.full !== null", polling=50, timeout=timeout_ms)
    w = page.evaluate("window.__surface")
    return w["first"] - w["down"], w["full"] - w["down"]


def browser_figures(
    cache_root=None, n_particles: int = 1000, timeout_ms: float = 120_000, repeats: int = BROWSER_REPEATS
) -> dict:
    """The first likelihood surface (ms), Kidnap's display resume (s) and the Top-down view's
    answer (ms) in a real headless Chromium, medians of ``repeats`` presses each (see the
    module's docstring)."""
    from .chromium import CHROMIUM, CHROMIUM_ARGS

    none = {"first_surface_ms": None, "kidnap_display_resume_s": None, "top_down_ms": None}
    if not CHROMIUM.exists():
        return none | {"browser": f"skipped: {CHROMIUM} not found (apt-get install -y chromium)"}
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return none | {"browser": "skipped: Python Playwright not installed"}
    from ...core.config import Config
    from ...core.localizer import Localizer
    from ...core.sequences.factory import SourceSpec, open_sequence
    from ..viewer.serve import serve

    cfg = Config()
    cfg.town.n_scans = 150
    cfg.pf.n_particles = n_particles
    seq = open_sequence(SourceSpec(scans=400), cfg)
    loc = Localizer(seq, cfg, cache_root)
    handle = serve(loc, port=0, autoplay=True, speed="5")
    resume_s, top_down_ms, first_ms, full_ms = [], [], [], []
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(handle.url, timeout=timeout_ms)
            page.wait_for_selector("canvas", timeout=timeout_ms)
            page.wait_for_function(f"{JS_SCAN} >= 3", timeout=timeout_ms)
            v = handle.viewer
            # the likelihood surface while the scans play, the run's first one first
            page.get_by_text("Why", exact=True).click(timeout=timeout_ms)
            for _ in range(repeats):
                first, full = _surface_ms(page, timeout_ms)
                first_ms.append(first)
                full_ms.append(full)
            v.controls.kidnap_skip.value = KIDNAP_SKIP
            page.wait_for_function(
                f"[...document.querySelectorAll('input')].some(i => i.value === '{KIDNAP_SKIP}')", timeout=timeout_ms
            )
            for _ in range(repeats):
                kidnaps = sum(e.kind == "kidnap" for e in loc.events)
                page.evaluate(JS_WATCH_PRESS + JS_WATCH_SCANS)
                page.get_by_role("button", name="Kidnap").click(timeout=timeout_ms)
                deadline = time.monotonic() + timeout_ms / 1000
                while sum(e.kind == "kidnap" for e in loc.events) == kidnaps and time.monotonic() < deadline:
                    time.sleep(0.005)
                target = loc.k  # the scan the vehicle jumped to (or one past it)
                shown = f"window.__scans.find(s => s[1] >= {target})"
                page.wait_for_function(f"{shown} !== undefined", polling=20, timeout=timeout_ms)
                resume_s.append(page.evaluate(f"{shown}[0] - window.__press") / 1000.0)
                # playing again before the next one: on the replay clock a whole-map S2M match
                # after the jump can hold the scans for minutes on a busy machine
                page.wait_for_function(f"{JS_SCAN} >= {target + 3}", timeout=SETTLE_TIMEOUTS * timeout_ms)
            clients = v.server.get_clients()
            client = clients[max(clients)]
            tab = v.cameras._tabs[client.client_id]
            before = page.evaluate(JS_CAMERA)
            page.get_by_role("button", name="Top-down view").click(timeout=timeout_ms)  # 120 m above the vehicle
            page.wait_for_function(camera_moved_by(before, 30.0), polling=100, timeout=timeout_ms)
            for _ in range(repeats):
                # back behind the vehicle (where ticking Follow puts the camera), then straight down again
                before = page.evaluate(JS_CAMERA)
                v.cameras._follow_toggled(client, tab)
                page.wait_for_function(camera_moved_by(before, 30.0), polling=100, timeout=timeout_ms)
                before = page.evaluate(JS_CAMERA)
                page.evaluate(JS_WATCH_PRESS + JS_WATCH_CAMERA.replace("MOVED", camera_moved_by(before, 30.0)))
                page.get_by_role("button", name="Top-down view").click(timeout=timeout_ms)
                page.wait_for_function("window.__moved !== null", polling=20, timeout=timeout_ms)
                top_down_ms.append(page.evaluate("window.__moved - window.__press"))
            page.close()
            browser.close()
    finally:
        handle.stop()
        loc.close()
    return {
        "first_surface_ms": round(float(np.median(first_ms)), 0),
        "first_surface_ms_each": [round(x) for x in first_ms],
        "first_surface_ms_target": 1000.0,
        "full_surface_ms": round(float(np.median(full_ms)), 0),
        "kidnap_display_resume_s": round(float(np.median(resume_s)), 2),
        "kidnap_display_resume_s_target": 2.0,
        "top_down_ms": round(float(np.median(top_down_ms)), 0),
        "top_down_ms_target": 500.0,
        "browser": "headless Chromium (software WebGL), short town at 5 scans/s",
    }


def run(
    n_updates: int = 150,
    n_particles: int = 1000,
    n_scan: int = 25_000,
    map_points: int = 1_000_000,
    seed: int = 0,
    browser: bool = True,
) -> dict:
    rng = np.random.default_rng(seed)
    # viser prints its banner and "Server stopped" on stdout, which carries only the result
    with contextlib.redirect_stdout(sys.stderr):
        with_client, bare, plot_ms, received_mb, map_ms = _measure(rng, n_updates, n_particles, n_scan, map_points)
    u, b = np.asarray(with_client), np.asarray(bare)
    in_browser = {}
    if browser:
        with contextlib.redirect_stdout(sys.stderr):
            in_browser = browser_figures(n_particles=n_particles)
    return in_browser | {
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
