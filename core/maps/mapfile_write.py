"""Writing a point-cloud map file: binary little-endian .pcd or .ply (what CloudCompare, PCL,
Open3D and RViz read), in one go or in chunks, with the map's float64 origin added back."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..cache import atomic_write_file
from ..errors import DataError

#: Formats read by :func:`read_map` and written by :func:`write_map`.
from .mapfile import CHUNK_POINTS, WRITE_SUFFIXES, _unsupported


def write_map(path, points: np.ndarray, origin=None) -> None:
    """Write ``points`` (N, 3) as a binary .pcd or .ply (x, y, z only), in the frame
    ``points + origin``. With an origin the coordinates are written as float64 (UTM-sized
    coordinates keep full precision); without, in the points' own precision (float32 stays
    float32). The file appears whole or not at all (written aside, then renamed).

    PCL, CloudCompare and lidarloc read float64 PCD fields; open3d (0.19–0.20) reads them as
    zeros, so for open3d-based tools write a georeferenced map as .ply."""
    path = Path(path)
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"{path}: expected (N, ≥3) points to write, got shape {points.shape}")
    if origin is not None:
        origin = np.asarray(origin, np.float64).reshape(3)
    dtype = np.float32 if origin is None and points.dtype == np.float32 else np.float64

    def chunks():
        for i in range(0, len(points), CHUNK_POINTS):
            c = np.asarray(points[i : i + CHUNK_POINTS, :3], dtype=np.float64 if origin is not None else dtype)
            yield c + origin if origin is not None else c

    write_map_chunks(path, len(points), chunks(), dtype)


def write_map_chunks(path, n_points: int, chunks: Iterable[np.ndarray], dtype=np.float32) -> None:
    """Write a map of ``n_points`` given as chunks of (m, 3) xyz, never holding more than one
    chunk: binary .pcd or .ply with x, y, z of ``dtype`` (float32 or float64). Atomic like
    :func:`write_map`; the chunks must add up to ``n_points``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_SUFFIXES:
        raise _unsupported(path, "write", WRITE_SUFFIXES)
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"map coordinates are written as float32 or float64, not {dtype}")
    header = _pcd_header(n_points, dtype) if suffix == ".pcd" else _ply_header(n_points, dtype)

    def write(tmp: Path):
        written = 0
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            for chunk in chunks:
                chunk = np.ascontiguousarray(np.asarray(chunk)[:, :3], dtype=dtype.newbyteorder("<"))
                f.write(chunk.tobytes())
                written += len(chunk)
        if written != n_points:
            raise ValueError(f"{path}: {written} points written, {n_points} announced")

    try:
        atomic_write_file(path, write)
    except OSError as exc:
        raise DataError(f"{path}: cannot write the map ({exc.strerror or exc})") from None


def _pcd_header(n: int, dtype: np.dtype) -> str:
    size = dtype.itemsize
    return (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
        f"SIZE {size} {size} {size}\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )


def _ply_header(n: int, dtype: np.dtype) -> str:
    kind = "float" if dtype == np.float32 else "double"
    return (
        f"ply\nformat binary_little_endian 1.0\ncomment lidarloc map\nelement vertex {n}\n"
        f"property {kind} x\nproperty {kind} y\nproperty {kind} z\nend_header\n"
    )
