"""What the scene draws with: the map thinned for display, particle ranks by log-weight, a
vehicle's outline, rotations as viser wants them, and trajectories sent in chunks."""

from __future__ import annotations

import math

import numpy as np
import viser

from ...core.maps.voxel_grid import VoxelAccumulator
from ...core.snapshot import Snapshot
from .style import DISPLAY_MAX_POINTS, DISPLAY_VOXEL, TRAJ_CHUNK, VEHICLE_LENGTH, VEHICLE_WIDTH


def downsample_for_display(
    points: np.ndarray, voxel: float = DISPLAY_VOXEL, max_points: int = DISPLAY_MAX_POINTS
) -> tuple[np.ndarray, float]:
    """One centroid per voxel, the voxel grown by 1.5× until at most ``max_points`` remain.
    Returns (points float32, voxel used)."""
    if len(points) == 0:
        return np.zeros((0, 3), np.float32), voxel
    while True:
        acc = VoxelAccumulator(voxel, capacity=1 << max(10, int(np.ceil(np.log2(2 * len(points) + 1)))))
        acc.add(points)
        out = acc.points()
        if len(out) <= max_points:
            return out, voxel
        voxel *= 1.5


def quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    return viser.transforms.SO3.from_matrix(np.asarray(R, float)).wxyz


def log_weight_rank(log_w: np.ndarray) -> np.ndarray:
    """Each particle's rank by log-weight scaled to 0 (lowest) … 1 (highest); equal log-weights
    share their mean rank. With the paper's likelihood one particle holds nearly all the weight, but
    the others' log-weights still order them: colouring by rank keeps the cloud's structure visible
    where colouring by weight would paint all but one particle the same."""
    lw = np.asarray(log_w, np.float64)
    n = len(lw)
    if n < 2:
        return np.ones(n)
    lw = np.where(np.isfinite(lw), lw, -np.inf)
    order = np.argsort(lw, kind="stable")
    sorted_lw = lw[order]
    # mean rank of each run of equal values
    starts = np.r_[0, np.flatnonzero(sorted_lw[1:] != sorted_lw[:-1]) + 1]
    ends = np.r_[starts[1:], n]
    mean_rank = (starts + ends - 1) / 2.0
    ranks = np.empty(n)
    ranks[order] = np.repeat(mean_rank, ends - starts)
    return ranks / (n - 1)


def snapshot_log_weights(snap: Snapshot) -> np.ndarray:
    """The particles' log-weights: the snapshot's own where it has them (they keep the order of
    particles whose weight underflows to 0), else the log of the weights."""
    lw = snap.log_weights
    if lw is not None and len(lw) == len(snap.weights):
        return np.asarray(lw, np.float64)
    with np.errstate(divide="ignore"):
        return np.log(np.asarray(snap.weights, np.float64))


def vehicle_outline(T: np.ndarray) -> np.ndarray:
    """Line segments (S, 2, 3) of a vehicle's footprint at pose ``T`` (the LiDAR's position and
    heading): a rectangle with a nose pointing along the heading."""
    L, W = VEHICLE_LENGTH / 2.0, VEHICLE_WIDTH / 2.0
    pts = np.array([[-L, -W], [L - 1.0, -W], [L, 0.0], [L - 1.0, W], [-L, W]], np.float64)
    yaw = math.atan2(T[1, 0], T[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    xy = pts @ np.array([[c, s], [-s, c]]) + T[:2, 3]
    ring = np.c_[xy, np.full(len(xy), T[2, 3])]
    axle = np.array([[-L, 0.0], [L, 0.0]]) @ np.array([[c, s], [-s, c]]) + T[:2, 3]
    segs = np.stack([ring, np.roll(ring, -1, axis=0)], axis=1)
    return np.concatenate([segs, np.c_[axle, np.full(2, T[2, 3])][None]]).astype(np.float32)


class ChunkedPolyline:
    """A growing polyline sent in chunks: a finished chunk is sent once and left alone, only the
    last one is updated, so the per-scan cost does not grow with the length of the drive."""

    def __init__(self, scene, name: str, color, thickness: float = 2.0):
        self.scene, self.name, self.color, self.thickness = scene, name, color, thickness
        self.epoch = None
        self.handles: list = []
        self.visible = True

    def _clear(self) -> None:
        for h in self.handles:
            h.remove()
        self.handles = []

    def set_visible(self, visible: bool) -> None:
        self.visible = visible
        for h in self.handles:
            h.visible = visible

    def sync(self, epoch: int, pts: np.ndarray, connected: np.ndarray) -> None:
        """``pts`` (n, 3) so far; ``connected[i]`` says whether point i joins point i − 1.
        Chunk c holds the segments between points c·C … (c+1)·C (consecutive chunks share a point).
        Fewer points than last time (the timeline cut the line at its cursor): the chunks past
        the end go and the last one is rewritten; the points before are the same as sent."""
        if epoch != self.epoch:
            self._clear()
            self.epoch = epoch
        n = len(pts)
        if n < 2:
            self._clear()
            return
        last = (n - 2) // TRAJ_CHUNK  # chunk of the newest segment
        while len(self.handles) > last + 1:
            self.handles.pop().remove()
        first = max(len(self.handles) - 1, 0)  # the open chunk: finished ones stay as sent
        for c in range(first, last + 1):
            lo, hi = c * TRAJ_CHUNK, min((c + 1) * TRAJ_CHUNK, n - 1)
            segs = self._segments(pts, connected, lo, hi)
            if segs is None:  # nothing connected here (e.g. no ground truth): a zero-length stand-in
                segs = np.repeat(np.nan_to_num(pts[lo : lo + 1]).astype(np.float32)[:, None], 2, axis=1)
            if c < len(self.handles):
                self.handles[c].points = segs
            else:
                self.handles.append(
                    self.scene.add_line_segments(
                        f"{self.name}/c{c}",
                        segs,
                        self.color,
                        thickness=self.thickness,
                        thickness_units="screen",
                        visible=self.visible,
                    )
                )

    @staticmethod
    def _segments(pts, connected, lo, hi):
        """Segments between points lo…hi (inclusive) that are connected and finite, or None."""
        if hi <= lo:
            return None
        a, b = pts[lo:hi], pts[lo + 1 : hi + 1]
        keep = connected[lo + 1 : hi + 1] & np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
        if not keep.any():
            return None
        return np.stack([a[keep], b[keep]], axis=1).astype(np.float32)
