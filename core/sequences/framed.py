"""A sequence localized in a map file's frame (``--map FILE``).

The prior map then comes from the file, not from the drive's scans and truth, and lives in the
file's local frame (file frame − ``PriorMap.origin``, see :mod:`lidarloc.core.maps.mapfile`). Ground
truth given with a map file is taken to be in the map's frame:

- a bag or scan folder re-bases its truth to the first LiDAR pose and keeps that pose in the
  truth's frame as ``truth_origin``; the truth in the map's local frame is then
  ``truth_origin @ poses[i]`` with the origin taken off the translation;
- a source without ``truth_origin`` (KITTI, the town) is taken to be in the map's frame as it is
  (a map exported from that source, for instance).

The origin is known once the map is read: the localizer hands it over
(:meth:`MapFramed.use_map_origin`); a reader of :attr:`poses` before that (a benchmark without a
localizer) reads the file once for it.
"""

from __future__ import annotations

import numpy as np

from .base import Limited, Sequence


class MapFramed(Limited):
    """``inner``'s scans, with ``map_file`` (a :class:`~lidarloc.core.maps.map_source.MapFileSource`)
    as its map source and its truth in that map's local frame."""

    def __init__(self, inner: Sequence, map_file):
        super().__init__(inner, len(inner))
        self.map_file = map_file
        self._origin: np.ndarray | None = None
        self._poses: np.ndarray | None = None

    @property
    def map_source(self):
        return self.map_file

    @property
    def origin(self) -> np.ndarray:
        """The map's local frame's origin in the file's frame (float64 (3,))."""
        if self._origin is None:
            self._origin = np.asarray(self.map_file.read().origin, dtype=np.float64)
        return self._origin

    def use_map_origin(self, origin) -> None:
        """The origin of the map as read (by the localizer, which reads it anyway)."""
        origin = np.asarray(origin, dtype=np.float64).reshape(3)
        if self._origin is None or not np.array_equal(origin, self._origin):
            self._origin, self._poses = origin, None

    @property
    def poses(self) -> np.ndarray | None:
        inner = self.inner.poses
        if inner is None:
            return None
        if self._poses is None:
            to_map = np.eye(4)
            truth_origin = getattr(self.inner, "truth_origin", None)
            if truth_origin is not None:
                to_map = np.asarray(truth_origin, dtype=np.float64).copy()
            to_map[:3, 3] -= self.origin
            self._poses = to_map[None] @ inner
        return self._poses

    def identity(self) -> str:
        # the scans' identity: caches of the scans (odometry) do not depend on the map
        return self.inner.identity()
