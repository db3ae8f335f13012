"""Server-level tests of the live viewer: every control changes the localizer as it says, invalid
values are refused with a message and the server keeps running. GUI handles are driven
programmatically: assigning ``.value`` runs the same callbacks a browser edit runs."""

from __future__ import annotations

import math
import time
import urllib.request

import numpy as np
import pytest

from lidarloc.core.config import DEG, Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.geometry import pose_matrix, transform_points
from lidarloc.core.mapping import build_prior_map
from lidarloc.core.sequences.base import Sequence
from lidarloc.core.snapshot import Event, S2MView, Snapshot


# ------------------------------------------------------------------------------ a small street
class StreetSequence(Sequence):
    """A straight street with building façades, poles and a flat road, scanned from a car driving
    along it at 8 m/s, 10 Hz. Small and fast: tests of the viewer need a real map, not a big one."""

    name = "test-street"

    def __init__(self, n: int = 24, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.n = n
        walls = []
        for side in (-1, 1):
            for x0 in np.arange(-20, 260, 14.0):           # façades with gaps and varying depth
                depth = rng.uniform(7, 11)
                h = rng.uniform(6, 15)
                xs = rng.uniform(x0, x0 + 11, 2500)
                zs = rng.uniform(-1.7, h - 1.7, 2500)
                walls.append(np.stack([xs, np.full_like(xs, side * depth), zs], 1))
        poles = []
        for x in np.arange(0, 250, 9.0):
            z = rng.uniform(-1.7, 3.5, 120)
            poles.append(np.stack([np.full_like(z, x), np.full_like(z, 5.5), z], 1))
        road = np.stack([rng.uniform(-20, 260, 40000), rng.uniform(-10, 10, 40000), np.full(40000, -1.73)], 1)
        self.world = np.concatenate(walls + poles + [road])
        t = np.arange(n) * 0.1
        x = 8.0 * t
        y = 0.8 * np.sin(x / 40.0)
        yaw = np.arctan2(0.8 / 40.0 * np.cos(x / 40.0), 1.0)
        self._poses = pose_matrix(x, y, np.zeros(n), yaw, np.zeros(n), np.zeros(n))
        self._t = t

    def __len__(self):
        return self.n

    def _read_scan(self, i):
        T = self._poses[i]
        local = transform_points(np.linalg.inv(T), self.world)
        r = np.linalg.norm(local, axis=1)
        local = local[(r > 2.5) & (r < 50)]
        rng = np.random.default_rng(i)
        local = local + rng.normal(0, 0.02, local.shape)
        return np.concatenate([local, np.ones((len(local), 1))], 1).astype(np.float32)

    def _describe_scan(self, i):
        return f"test street scan {i}"

    @property
    def timestamps(self):
        return self._t

    @property
    def poses(self):
        return self._poses


_LIVE = {
    "d_max": lambda v: v > 0, "sigma": lambda v: v > 0,
    "q_std": lambda v: len(v) == 11 and all(math.isfinite(q) and q >= 0 for q in v),
    "s2m_enabled": lambda v: isinstance(v, bool), "region_x": lambda v: v > 0, "region_y": lambda v: v > 0,
    "match_resolution": lambda v: 0.1 <= v <= 10, "angle_step": lambda v: 0 < v <= math.pi,
    "n_particles": lambda v: int(v) == v and 1 <= v <= 200_000, "scan_voxel": lambda v: 0.05 <= v <= 10,
    "clock": lambda v: v in ("replay", "realtime"),
}
_CFG_PATH = {"d_max": ("pf", "d_max"), "sigma": ("pf", "sigma"), "q_std": ("pf", "q_std"),
             "s2m_enabled": ("s2m", "enabled"), "region_x": ("s2m", "region_x"), "region_y": ("s2m", "region_y"),
             "match_resolution": ("s2m", "match_resolution"), "angle_step": ("s2m", "angle_step"),
             "n_particles": ("pf", "n_particles"), "scan_voxel": ("pf", "scan_voxel"), "clock": ("localize", "clock")}


class StandInLocalizer:
    """The Localizer API the viewer codes against, with ground-truth-driven fake filtering:
    particles shrink around the true pose over a few scans. For viewer tests only."""

    def __init__(self, seq, cfg: Config, prior_map=None):
        from lidarloc.core.bev import BEVPyramid

        self.seq, self.cfg = seq, cfg
        self.n_scans = len(seq)
        self.prior_map = prior_map if prior_map is not None else build_prior_map(seq, cfg.map)
        self.pyramid = BEVPyramid.build(self.prior_map.points_bev, cfg.s2m.match_resolution)
        self.rebuild_progress = None
        self.calls: list = []
        self.restart(cfg.seed)

    def restart(self, seed=None):
        if seed is not None:
            self.cfg.seed = int(seed)
        self.rng = np.random.default_rng(self.cfg.seed)
        self.k = 0
        self.events: list[Event] = []
        self.spread = 80.0
        self._init_particles()
        self._snap = self._make(-1)
        self.calls.append(("restart", seed))

    def _init_particles(self, center=None, region=None):
        n = self.cfg.pf.n_particles
        P = np.zeros((n, 11))
        lo, hi = self.prior_map.bounds
        if region is not None:
            P[:, 0] = self.rng.uniform(region[0], region[2], n)
            P[:, 1] = self.rng.uniform(region[1], region[3], n)
        elif center is not None:
            P[:, :2] = center[:2] + self.rng.normal(0, 3.0, (n, 2))
        else:
            P[:, 0] = self.rng.uniform(lo[0], hi[0], n)
            P[:, 1] = self.rng.uniform(lo[1], hi[1], n)
        P[:, 3] = self.rng.uniform(-np.pi, np.pi, n)
        self.P = P

    @property
    def done(self):
        return self.k >= self.n_scans

    def step(self) -> Snapshot:
        if self.done:
            return self._snap
        k = self.k
        gt = self.seq.pose(k)
        self.spread = max(0.3, self.spread * 0.6)
        n = self.cfg.pf.n_particles
        if len(self.P) != n:
            self._init_particles()
        self.P[:, :2] = gt[:2, 3] + self.rng.normal(0, self.spread, (n, 2))
        self.P[:, 2] = gt[2, 3]
        self.P[:, 3] = math.atan2(gt[1, 0], gt[0, 0]) + self.rng.normal(0, 0.2, n)
        self.k += 1
        self._snap = self._make(k)
        time.sleep(0.005)
        return self._snap

    def _make(self, k) -> Snapshot:
        P = self.P
        w = self.rng.random(len(P))
        w /= w.sum()
        best = int(np.argmax(w))
        mean = (w[:, None] * P[:, :3]).sum(0)
        cov = np.cov(P[:, :3].T, aweights=w) + 1e-9 * np.eye(3)
        std = np.sqrt(np.diag(cov))
        ev, evec = np.linalg.eigh(cov[:2, :2])
        ellipse = (2 * math.sqrt(ev[1]), 2 * math.sqrt(ev[0]), math.atan2(evec[1, 1], evec[0, 1]))
        T = pose_matrix(mean[0], mean[1], mean[2], float(np.angle((w * np.exp(1j * P[:, 3])).sum())), 0, 0)
        gt = self.seq.pose(k) if k >= 0 else None
        scan = np.zeros((0, 3), np.float32)
        s2m = self._snap.s2m if k > 0 else None
        if k >= 0:
            pts = self.seq.scan(k)[::8, :3]
            scan = transform_points(T, pts).astype(np.float32)
            if k % 3 == 2:
                s2m = S2MView(started_at=k - 2, landed_at=k, accepted=bool(k % 2), score=120.0 + k, start_score=40.0,
                              pose=gt, scan_world=transform_points(gt, pts[::2]).astype(np.float32),
                              region=(gt[0, 3] - self.cfg.s2m.region_x, gt[1, 3] - self.cfg.s2m.region_y,
                                      gt[0, 3] + self.cfg.s2m.region_x, gt[1, 3] + self.cfg.s2m.region_y),
                              ms=35.0, reason="" if k % 2 else "score below start")
                self.events.append(Event(k, "s2m_accepted" if k % 2 else "s2m_rejected", ""))
        err = None if gt is None else float(np.linalg.norm(T[:3, 3] - gt[:3, 3]))
        localized = bool(std.max() < 1.0)
        return Snapshot(scan_index=k, n_scans=self.n_scans, timestamp=0.1 * max(k, 0), particles=P.copy(),
                        weights=w, best_index=best, mean_pose=T, cov_xyz=cov, std_xyz=std, ellipse_xy=ellipse,
                        n_eff=float(1.0 / (w ** 2).sum()), localized=localized, localized_since=2 if localized else None,
                        scan_world=scan, gt_pose=gt, error_m=err, pf_ms=3.0, s2m=s2m, s2m_running=False,
                        s2m_acceptance=0.5, events=tuple(self.events[-50:]), done=self.k >= self.n_scans)

    def snapshot(self):
        return self._snap

    def reset(self, pose=None, region=None):
        self.calls.append(("reset", pose, region))
        self._init_particles(center=None if pose is None else pose[:3, 3], region=region)
        self.spread = 80.0
        self.events.append(Event(self.k - 1, "reset", ""))
        self._snap = self._make(self.k - 1)

    def kidnap(self, skip=100):
        if skip < 1:
            raise LidarlocError("kidnap skip must be ≥ 1 scan")
        self.calls.append(("kidnap", skip))
        self.k = min(self.k + skip, self.n_scans - 1)
        return self.k

    def set_params(self, **params):
        for name, value in params.items():
            if name not in _LIVE or not _LIVE[name](value):
                raise LidarlocError(f"invalid value for {name}: {value!r}")
        for name, value in params.items():
            section, attr = _CFG_PATH[name]
            setattr(getattr(self.cfg, section), attr, value)
        self.calls.append(("set_params", params))

    def close(self):
        self.calls.append(("close",))


# ---------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def street():
    return StreetSequence()


@pytest.fixture(scope="module")
def street_map(street):
    return build_prior_map(street, Config().map)


def browser_localizer():
    """The localizer the browser test drives: long enough to pause mid-run."""
    seq = StreetSequence(n=120)
    cfg = Config()
    cfg.pf.n_particles = 1000
    return StandInLocalizer(seq, cfg)


def make_localizer(street, street_map, **cfg_kw):
    cfg = Config()
    cfg.pf.n_particles = cfg_kw.get("n_particles", 300)
    return StandInLocalizer(street, cfg, street_map)


@pytest.fixture
def viewer(street, street_map):
    from lidarloc.app.viewer import serve

    loc = make_localizer(street, street_map)
    handle = serve(loc, port=0, autoplay=False)
    yield handle
    handle.stop()


def wait_for(cond, timeout=10.0, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


# ---------------------------------------------------------------------------------- tests
def test_page_is_served_and_map_sent_once(viewer):
    html = urllib.request.urlopen(viewer.url, timeout=5).read().decode()
    assert "<html" in html.lower()
    v = viewer.viewer
    assert v.scene._map is not None and v.scene._map.precision == "float32"
    assert v.scene._map.points.dtype == np.float32


def test_step_advances_exactly_one_scan_and_pause_holds(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    assert loc.k == 0
    c.step.value = True                    # a click: runs the button's callbacks
    wait_for(lambda: v.player.idle and loc.k == 1, what="one step")
    assert loc.k == 1
    c.step.value = True
    c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 3, what="two more steps")
    time.sleep(0.3)
    assert loc.k == 3                       # paused: nothing else happens
    c.play.value = True                     # play …
    wait_for(lambda: loc.k >= 6, what="playing")
    c.play.value = True                     # … and pause
    wait_for(lambda: v.player.idle, what="pause")
    k = loc.k
    time.sleep(0.3)
    assert loc.k == k


def test_display_shows_latest_snapshot(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1)
    v.update_display(force_plots=True)
    assert v._drawn is loc.snapshot()
    assert "Scan 0 of 24" in v._status.content
    assert len(v.scene._particles.points) == 300


def test_numeric_params_reach_the_localizer(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    c.params["d_max"].value = 7.5
    c.params["sigma"].value = 0.8
    c.params["region_x"].value = 12.0
    c.params["region_y"].value = 18.0
    c.params["angle_step"].value = 5.0          # degrees in the GUI
    c.params["n_particles"].value = 500
    c.params["scan_voxel"].value = 0.7
    assert c.apply.label == "Apply 7 changes" and not c.apply.disabled
    assert loc.cfg.pf.sigma == 0.5                 # nothing sent before Apply
    c.apply.value = True
    assert loc.cfg.pf.d_max == 7.5
    assert loc.cfg.pf.sigma == 0.8
    assert loc.cfg.s2m.region_x == 12.0 and loc.cfg.s2m.region_y == 18.0
    assert loc.cfg.s2m.angle_step == pytest.approx(5.0 * DEG)
    assert loc.cfg.pf.n_particles == 500 and isinstance(loc.cfg.pf.n_particles, int)
    assert loc.cfg.pf.scan_voxel == 0.7
    assert c.apply.disabled and "applied" in v.message


def test_q_is_shown_and_set_in_paper_units(viewer):
    v, loc = viewer.viewer, viewer.localizer
    q = v.controls.q
    assert q[3].value == pytest.approx(5.0)          # yaw: 5°
    assert q[9].value == pytest.approx(0.02)         # roll rate: 0.02°/s
    assert q[0].value == pytest.approx(0.5)          # x: 0.5 m
    q[3].value = 8.0
    q[6].value = 0.3
    v.controls.apply.value = True
    assert loc.cfg.pf.q_std[3] == pytest.approx(8.0 * DEG)
    assert loc.cfg.pf.q_std[6] == pytest.approx(0.3)
    assert loc.cfg.pf.q_std[0] == pytest.approx(0.5)


def test_s2m_switch_and_clock(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.s2m_enabled.value = False
    assert loc.cfg.s2m.enabled is False
    v.controls.s2m_enabled.value = True
    assert loc.cfg.s2m.enabled is True
    v.controls.clock.value = "realtime"
    assert loc.cfg.localize.clock == "realtime" and v.player.clock == "realtime"
    assert v.controls.speed.disabled


@pytest.mark.parametrize("key,value", [("sigma", 0.0), ("sigma", -1.0), ("d_max", -2.0), ("n_particles", 0),
                                       ("region_x", 0.0), ("match_resolution", 50.0), ("angle_step", 0.0)])
def test_invalid_values_are_refused_with_a_message(viewer, key, value):
    v, loc = viewer.viewer, viewer.localizer
    before = Config().to_dict()
    v.controls.params["sigma"].value = 0.9 if key != "sigma" else value
    v.controls.params[key].value = value
    v.controls.apply.value = True
    assert v.message.startswith("refused:"), v.message
    assert v._message_md.visible
    # all or nothing: the valid σ change in the same batch was not applied either
    assert loc.cfg.pf.sigma == before["pf"]["sigma"]
    assert not any(call[0] == "set_params" for call in loc.calls)
    # the server still answers and the controls still work
    urllib.request.urlopen(viewer.url, timeout=5).read()
    v.controls.params[key].value = v._applied[key]
    v.controls.params["sigma"].value = 0.6
    v.controls.apply.value = True
    assert loc.cfg.pf.sigma == 0.6


def test_invalid_q_refused(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.q[4].value = -1.0
    v.controls.apply.value = True
    assert "refused" in v.message and "pitch" in v.message
    assert loc.cfg.pf.q_std[4] == pytest.approx(2.0 * DEG)


def test_reset_global_point_and_rectangle(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.reset.value = True
    assert loc.calls[-1] == ("reset", None, None)
    # a shift-click: a ray from above onto the road at (30, 2)
    ground = v.scene.ground
    target = np.array([30.0, 2.0, ground.at(30.0, 2.0)])
    origin = target + np.array([-20.0, -5.0, 60.0])

    class Click:
        client = None
        ray_origin = tuple(origin)
        ray_direction = tuple((target - origin) / np.linalg.norm(target - origin))
    v._on_shift_click(Click())
    kind, pose, region = loc.calls[-1]
    assert kind == "reset" and region is None
    assert pose[:2, 3] == pytest.approx([30.0, 2.0], abs=0.05)
    assert pose[2, 3] == pytest.approx(ground.at(30, 2) + loc.cfg.pf.sensor_height, abs=1e-6)
    # a rectangle dragged in a top-down view: its corners land where the camera model says
    snap = loc.snapshot()
    assert np.abs(snap.particles[:, :2] - [30.0, 2.0]).max() < 20

    class Camera:   # straight down from 100 m over (50, 0); image "up" = +y
        position = np.array([50.0, 0.0, 100.0])
        wxyz = np.array([0.0, 1.0, 0.0, 0.0])          # 180° about x: z forward = down, y down = -y
        fov = 2 * math.atan(0.5)                       # tan(fov/2) = 0.5: 100 m up sees ±50 m vertically
        aspect = 1.0

    class Client:
        camera = Camera()

    class Rect:
        client = Client()
        screen_min = (0.5, 0.25)
        screen_max = (0.75, 0.5)
    v._on_shift_rect(Rect())
    kind, pose, region = loc.calls[-1]
    assert kind == "reset" and pose is None
    z0 = ground.z_default
    # half-height of view at the ground is 0.5·(100 − z0); u from 0.5 to 0.75 → x from 50 to 50 + quarter width
    half = 0.5 * (100 - z0)
    assert region == pytest.approx((50.0, 0.0, 50.0 + 0.5 * half, 0.5 * half), abs=1.0)


def test_kidnap_and_restart(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1)
    v.controls.kidnap_skip.value = 5
    v.controls.kidnap.value = True
    assert loc.k == 6 and "kidnapped" in v.message
    v.controls.kidnap_skip.value = 0
    v.controls.kidnap.value = True
    assert v.message.startswith("refused") and loc.k == 6
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 7)
    v.update_display(force_plots=True)
    # the ground-truth line breaks at the jump: scans 0 and 6 are not joined
    assert v.history.n == 2
    v.controls.seed.value = 7
    v.controls.restart.value = True
    assert loc.k == 0 and loc.cfg.seed == 7
    assert v.history.n == 0


def test_layers_and_bev_level(viewer):
    v = viewer.viewer
    c = v.controls
    assert c.layers["bev_level"].visible      # the stand-in has a pyramid: the toggle is offered
    c.layers["map"].value = False
    assert v.scene._map.visible is False
    c.layers["map_bev"].value = True
    assert v.scene._map_bev.visible is True
    c.layers["bev_level"].value = True
    assert v.scene._bev_image is not None and v.scene._bev_image.visible
    c.bev_level.value = 0
    assert v.scene._bev_level_shown == 0


def test_factory_shows_progress_then_attaches(street, street_map):
    from lidarloc.app.viewer import serve

    import threading
    go = threading.Event()

    def factory(progress=None):
        progress("map", 0.5)
        go.wait(5)
        return make_localizer(street, street_map)

    handle = serve(factory, port=0, autoplay=True)
    try:
        wait_for(lambda: handle.viewer._progress_text.content.startswith("Building the prior map"), what="progress")
        assert handle.viewer._progress.visible
        handle.viewer.controls.reset.value = True
        assert "still starting" in handle.viewer.message
        go.set()
        assert handle.wait_ready(10)
        wait_for(lambda: handle.localizer.k >= 3, what="autoplay")
        wait_for(lambda: not handle.viewer._progress.visible, what="progress bar hidden")
    finally:
        t0 = time.perf_counter()
        handle.stop()
        assert time.perf_counter() - t0 < 2.0
    assert ("close",) in handle.localizer.calls      # the viewer built it, so it closes it


def test_factory_failure_is_shown(street):
    from lidarloc.app.viewer import serve

    def factory():
        raise LidarlocError("/nowhere: no such sequence")

    handle = serve(factory, port=0)
    try:
        wait_for(lambda: "could not start" in handle.viewer.message, what="startup failure message")
        urllib.request.urlopen(handle.url, timeout=5).read()
    finally:
        handle.stop()


def test_two_viewers_two_ports(street, street_map):
    from lidarloc.app.viewer import serve

    a = serve(make_localizer(street, street_map), port=0, autoplay=False)
    b = serve(make_localizer(street, street_map), port=0, autoplay=False)
    try:
        assert a.port != b.port
    finally:
        a.stop()
        b.stop()


def test_speed_and_clock_controls_reach_the_player(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    c.speed.value = "5"
    assert v.player.speed == 5.0
    c.speed.value = "max"
    assert v.player.speed is None
    c.clock.value = "realtime"
    assert v.player.clock == "realtime" and loc.cfg.localize.clock == "realtime"
    c.clock.value = "replay"
    assert v.player.clock == "replay" and not c.speed.disabled


class _InstantSteps:
    """What the Player needs of a localizer, with 1 ms steps: the pacing is all the player's."""

    def __init__(self, n=100_000, dt=0.1):
        self.k, self.n = 0, n
        self.seq = type("Seq", (), {"timestamps": np.arange(n) * dt})()
        self.lock = __import__("threading").Lock()

    @property
    def done(self):
        return self.k >= self.n

    def step(self):
        time.sleep(0.001)
        self.k += 1
        return self.k


def _time_scans(player, loc, n):
    k0, t0 = loc.k, time.perf_counter()
    player.play()
    wait_for(lambda: loc.k >= k0 + n, what=f"{n} scans")
    elapsed = time.perf_counter() - t0
    player.pause()
    assert player.wait_idle(5)
    return elapsed


def test_player_pacing():
    from lidarloc.app.player import Player

    loc = _InstantSteps()
    player = Player(loc, lambda s: None, lambda m: None, speed=20.0)
    player.start()
    try:
        # replay at 20 scans/s: 6 scans are 5 intervals of 50 ms after the first
        assert 0.23 <= _time_scans(player, loc, 6) < 0.6
        player.set_speed(None)                    # max: as fast as the localizer goes
        assert _time_scans(player, loc, 50) < 0.5
        # realtime at the sequence's timestamps (0.1 s apart), whatever the speed says
        player.set_clock("realtime")
        player.set_speed(100.0)
        assert 0.38 <= _time_scans(player, loc, 5) < 0.9
        # step: exactly one scan, then idle
        k = loc.k
        player.step_once()
        assert player.wait_idle(5) and loc.k == k + 1
        with pytest.raises(LidarlocError):
            player.set_speed(0)
        with pytest.raises(LidarlocError):
            player.set_clock("fast")
    finally:
        t0 = time.perf_counter()
        player.stop()
        assert time.perf_counter() - t0 < 1.0


def test_player_survives_a_failing_step():
    from lidarloc.app.player import Player

    class Failing(_InstantSteps):
        def step(self):
            if self.k == 2:
                raise LidarlocError("scan 2: corrupt file")
            return super().step()

    loc, errors = Failing(), []
    player = Player(loc, lambda s: None, errors.append, speed=None)
    player.start()
    try:
        player.play()
        wait_for(lambda: errors, what="the error")
        assert errors == ["scan 2: corrupt file"] and not player.playing
        loc.k = 3                                     # past the bad scan: playback resumes
        player.play()
        wait_for(lambda: loc.k >= 10, what="playing again")
    finally:
        player.stop()


def test_rebuild_progress_shows_in_the_page(viewer):
    v, loc = viewer.viewer, viewer.localizer
    loc.rebuild_progress = 0.4
    v.update_display()
    assert v._progress.visible and v._progress.value == pytest.approx(40.0)
    assert "Rebuilding" in v._progress_text.content
    loc.rebuild_progress = None
    v.update_display()
    assert not v._progress.visible


def test_status_and_plots_follow_the_run(viewer):
    v, loc = viewer.viewer, viewer.localizer
    for _ in range(4):
        v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 4)
    v.update_display(force_plots=True)
    text = v._status.content
    assert "Scan 3 of 24" in text and "paused" in text
    assert "N_eff" in text and "S2M" in text and "error to truth" in text
    assert "s2m accepted" in text or "s2m rejected" in text      # recent events
    x, std, err = v._plot_std.data
    assert list(x) == [0, 1, 2, 3] and (std > 0).all() and (err > 0).all()
    x, pf_ms, s2m_ms = v._plot_ms.data
    assert len(pf_ms) == 4 and s2m_ms[-1] == pytest.approx(35.0)
    # the scene shows this scan: its points in green at the estimate, the S2M match with its label
    snap = loc.snapshot()
    assert np.array_equal(v.scene._scan.points, snap.scan_world)
    assert "started at scan 0, landed at 2" in v.scene._s2m_label.text
