"""A prior map from a point-cloud file (``--map FILE``) instead of a mapping drive.

:func:`lidarloc.core.maps.mapping.load_or_build_map` takes a :class:`MapFileSource` where it takes a
sequence: the file's points are voxelized at ``map.voxel_size`` like a fused drive, the road is
removed as for any map, and the result is cached under a key of the file's absolute path, size,
modification time and the map configuration (an edited or replaced file builds a new entry).

Voxelizing a file's map
    Each occupied voxel keeps the centroid of the file's points in it, as a drive's map does.
    A map denser than the voxel (a SLAM map at a few centimetres) is thinned to one point per
    voxel; a sparser one (a map already down-sampled at 0.5 m, a sparse survey) keeps each of
    its points as it is (one per voxel) and stays sparse: holes are not filled, so the
    likelihood then sees more d_max misses than on a drive's map. No range filter applies (there
    is no sensor position in a map file).

The map then lives in the file's local frame (see :mod:`lidarloc.core.maps.mapfile`): ``PriorMap.
origin`` (float64) is what to add to a map-frame position to report it in the file's frame.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

from ..errors import DataError
from .mapfile import READ_SUFFIXES, MapCloud, read_map


class MapFileSource:
    """A point-cloud map file as the source of a prior map (what a sequence's ``map_source`` is
    for a drive)."""

    def __init__(self, path):
        self.path = Path(path).expanduser().resolve()
        if self.path.suffix.lower() not in READ_SUFFIXES:
            raise DataError(
                f"{path}: cannot read a map of this type ({self.path.suffix or 'no extension'}); "
                f"supported: {', '.join(READ_SUFFIXES)}"
            )
        if not self.path.is_file():
            raise DataError(f"{path}: no such map file")

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def map_source(self) -> MapFileSource:
        return self

    def identity(self) -> str:
        """The file as a cache key: its absolute path, size and modification time (ns)."""
        try:
            st = self.path.stat()
        except OSError as exc:
            raise DataError(f"{self.path}: cannot read the map file ({exc.strerror})") from None
        return f"mapfile:{self.path}|size={st.st_size}|mtime_ns={st.st_mtime_ns}"

    def cache_key(self) -> str:
        return hashlib.sha1(self.identity().encode()).hexdigest()[:16]

    def read(self, progress: Callable[[int, int], None] | None = None) -> MapCloud:
        """The file's finite points in its local frame (see :func:`~lidarloc.core.maps.mapfile.read_map`)."""
        return read_map(self.path, progress=progress)

    def __repr__(self) -> str:
        return f"MapFileSource({str(self.path)!r})"
