"""Each tab's camera: where a new tab looks first, the tab's own camera folder (follow the
vehicle, top-down view, whole map), and the following cameras moved along with every drawn scan.
The scene is shared by all tabs; cameras are not."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable

import numpy as np
import viser

from ...core.snapshot import Snapshot
from .panel import CameraControls, add_camera_folder
from .scene import SceneView

#: the browser's view distance (m) and its nearest distance drawn, viser's defaults …
DEFAULT_FAR, DEFAULT_NEAR = 1000.0, 0.01
#: … the far one moved out to this many times the extent of a map wider than LARGE_MAP_M (m)
VIEW_DISTANCE_EXTENTS = 3.0
LARGE_MAP_M = 500.0
#: a tab's camera placed by a button waits this long (s) at most for the tab to report it there …
PLACED_WAIT_S = 5.0
#: … within this distance of where it was placed relative to its look-at (m)
PLACED_TOLERANCE_M = 1.0


def _vehicle(snap: Snapshot | None) -> np.ndarray | None:
    """The pose (4×4) a following camera keeps in view: the estimate once the filter converged;
    before, the truth where known (the mean of a cloud spread over the map is no place on it,
    and the camera would leave the vehicle behind), else the estimate."""
    if snap is None:
        return None
    if not snap.converged and snap.gt_pose is not None:
        gt = np.asarray(snap.gt_pose, float)
        if np.isfinite(gt).all():
            return gt
    T = np.asarray(snap.mean_pose, float)
    return T if np.isfinite(T[:3, 3]).all() else None


def tab_may_close(client: viser.ClientHandle):
    """A scope for writes to one tab that may close meanwhile: what it writes after the tab closed is
    dropped, as viser drops its own removal messages, without the warning meant for writes through
    forgotten handles (a no-op scope where a viser version has no such scope)."""
    conn = getattr(client, "_websock_connection", None)
    buffer = conn.get_message_buffer() if conn is not None and hasattr(conn, "get_message_buffer") else None
    scope = getattr(buffer, "sanctioned_dead_writes", None)
    return scope() if scope is not None else contextlib.nullcontext()


class TabCameras:
    """The cameras of all open tabs. ``latest`` returns the newest snapshot (or None);
    ``guarded(action, needs_localizer)`` turns an action into a GUI callback that reports
    failures in the panel."""

    def __init__(
        self,
        server: viser.ViserServer,
        scene: SceneView,
        latest: Callable[[], Snapshot | None],
        guarded: Callable,
        folder_order: float,
    ):
        self.server = server
        self.scene = scene
        self._latest = latest
        self._guarded = guarded
        self._order = folder_order
        self._tabs: dict[int, CameraControls] = {}
        self._placed: dict[int, tuple[np.ndarray, float]] = {}  # per tab: camera − look-at placed, until when
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ tabs
    def connect(self, client: viser.ClientHandle) -> None:
        """A new tab: its camera folder, each control wired to its move.

        A tab closed at once (a reload, a test's page) may be gone before or while its folder is
        built: nothing is built for a tab already gone, and the folder's messages to a tab that
        closes meanwhile are dropped by viser like its removal messages, without the warning meant
        for writes through forgotten handles."""
        with tab_may_close(client):
            if client.client_id not in self.server.get_clients():
                return
            tab = add_camera_folder(client.gui, self._order)
            tab.follow.on_update(self._guarded(lambda: self._follow_toggled(client, tab), needs_localizer=False))
            tab.top_down.on_click(self._guarded(lambda: self.top_down(client), needs_localizer=False))
            tab.fit.on_click(self._guarded(lambda: self.whole_map(client), needs_localizer=False))
        with self._lock:
            self._tabs[client.client_id] = tab
        if client.client_id not in self.server.get_clients():
            self.disconnect(client)  # it closed while its folder was built, before or after its own disconnect

    def disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self._tabs.pop(client.client_id, None)
            self._placed.pop(client.client_id, None)

    def _follow_toggled(self, client, tab: CameraControls) -> None:
        """Following starts behind the vehicle, looking along its heading."""
        if not tab.follow.value:
            return
        T = _vehicle(self._latest())
        if T is None:
            return
        p = T[:3, 3]
        yaw = float(np.arctan2(T[1, 0], T[0, 0]))
        back = np.array([-math.cos(yaw), -math.sin(yaw), 0.0])
        self._place(client, p + 35.0 * back + np.array([0, 0, 25.0]), p)

    def top_down(self, client) -> None:
        """Look straight down: on the vehicle if following it, else on the whole map."""
        with self._lock:
            tab = self._tabs.get(client.client_id)
        following = tab is not None and tab.follow.value
        T = _vehicle(self._latest())
        p = None if T is None else T[:3, 3]
        if following and p is not None:
            self._look_down(client, p, 120.0)
        else:
            self.whole_map(client)

    def whole_map(self, client) -> None:
        fov = client.camera.fov if client.camera.fov else 1.3
        h = 0.55 * self.scene.map_extent / math.tan(fov / 2.0)
        self._look_down(client, self.scene.map_center, h)

    def _look_down(self, client, target, height: float) -> None:
        target = np.asarray(target, float)
        # a hair off vertical keeps the orbit controls' up vector defined; +y stays up on screen
        self._place(client, target + np.array([0.0, -1e-3 * height, height]), target)

    def _place(self, client, position, look_at) -> None:
        """Move one tab's camera. Until the tab reports the camera there, the vehicle's moves
        leave it alone: a report the tab sent before this move arrives after it, and a follow
        step from that stale camera would put the old view back."""
        position, look_at = np.asarray(position, float), np.asarray(look_at, float)
        with self._lock:
            self._placed[client.client_id] = (position - look_at, time.monotonic() + PLACED_WAIT_S)
        with tab_may_close(client), client.atomic():
            client.camera.position = position
            client.camera.look_at = look_at

    def _settled(self, cid: int, position: np.ndarray, look_at: np.ndarray) -> bool:
        """Whether tab ``cid`` reports the view the server last placed it at (the camera where it
        was put relative to what it looks at: following moves both), or the wait is over."""
        with self._lock:
            placed = self._placed.get(cid)
            if placed is None:
                return True
            offset, until = placed
            if np.linalg.norm(position - look_at - offset) < PLACED_TOLERANCE_M or time.monotonic() > until:
                del self._placed[cid]
                return True
            return False

    # ------------------------------------------------------------------ all tabs
    def overview(self) -> None:
        """An oblique view of the whole map, for new tabs and for those already open. A map wider
        than LARGE_MAP_M moves the browser's far clipping plane (1 km by default) out so that the
        whole map stays in view, and the near one with it (the same depth precision)."""
        center, ext = self.scene.map_center, self.scene.map_extent
        position, look_at = center + np.array([0.0, -0.42 * ext, 0.6 * ext]), center
        far = max(DEFAULT_FAR, VIEW_DISTANCE_EXTENTS * ext) if ext > LARGE_MAP_M else DEFAULT_FAR
        near = DEFAULT_NEAR * far / DEFAULT_FAR
        initial = self.server.initial_camera
        initial.look_at = tuple(look_at)
        initial.position = tuple(position)
        initial.up = (0.0, 0.0, 1.0)
        if initial.far != far:
            initial.far, initial.near = far, near
        # tabs opened while the map was being built still look at the default origin
        for client in self.server.get_clients().values():
            with tab_may_close(client), client.atomic():
                client.camera.position = position
                client.camera.look_at = look_at
                if far != DEFAULT_FAR:
                    client.camera.far, client.camera.near = far, near

    def near(self, pose: np.ndarray, back: float = 45.0, up: float = 35.0) -> None:
        """New tabs, and those open now, look at the vehicle at ``pose`` (4×4) from behind and
        above: the run plays there, and a whole-map view of a town left the vehicle a few pixels
        wide."""
        T = np.asarray(pose, float)
        target = T[:3, 3]
        if not np.isfinite(T).all():
            return
        yaw = math.atan2(T[1, 0], T[0, 0])
        position = target + np.array([-back * math.cos(yaw), -back * math.sin(yaw), up])
        self.server.initial_camera.look_at = tuple(target)
        self.server.initial_camera.position = tuple(position)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        for client in self.server.get_clients().values():
            with tab_may_close(client), client.atomic():
                client.camera.position = position
                client.camera.look_at = target

    def follow(self, snap: Snapshot) -> None:
        """Move the cameras of the tabs that follow the vehicle onto it (see :func:`_vehicle`)."""
        T = _vehicle(snap)
        if T is None:
            return
        p = T[:3, 3]
        with self._lock:
            following = [cid for cid, tab in self._tabs.items() if tab.follow is not None and tab.follow.value]
        if not following:
            return
        clients = self.server.get_clients()
        for cid in following:
            client = clients.get(cid)
            if client is None:
                continue
            try:
                cam = client.camera
                if not self._settled(cid, np.asarray(cam.position, float), np.asarray(cam.look_at, float)):
                    continue
                shift = p - np.asarray(cam.look_at)
                if np.linalg.norm(shift) > 1e-3:
                    with tab_may_close(client):
                        cam.position = np.asarray(cam.position) + shift  # moves look_at along
            except (AssertionError, ValueError):  # camera state not reported yet
                continue


def start_pose(localizer) -> np.ndarray | None:
    """Where the vehicle starts, as far as the viewer knows before the first scan: the truth of
    the next scan (None without truth: the camera keeps the whole map in view)."""
    seq = localizer.seq
    try:
        return np.asarray(seq.pose(localizer.k), float) if seq.has_poses else None
    except Exception:  # a source that cannot say: the whole map stays in view
        return None
