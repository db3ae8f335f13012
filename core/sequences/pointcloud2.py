"""sensor_msgs/PointCloud2 → numpy, with no ROS installation and no per-point Python.

A PointCloud2 is a byte buffer of ``height × width`` points, each ``point_step`` bytes, rows
``row_step`` bytes apart, with named fields at byte offsets. :func:`cloud_dtype` turns
``msg.fields`` into a numpy structured dtype whose ``itemsize`` is ``point_step`` (so padding,
e.g. Ouster's 48-byte points, and fields this module does not use, e.g. ``ring`` or ``t``, are
simply skipped), with the message's byte order; :func:`to_xyzi` views ``msg.data`` through it
with the row stride and copies out x, y, z and the intensity.

Works on any object with the message's attributes (rosbags' deserialized messages, or a plain
namespace in tests). Returns that lack a measurement are dropped: organised clouds (``height >
1``, one cell per beam and firing) mark them with NaN coordinates (Velodyne, Hesai drivers) or
with x = y = z = 0 (Ouster); the order of the remaining points is kept.
"""

from __future__ import annotations

import numpy as np

from ..errors import DataError

#: sensor_msgs/PointField datatype codes → numpy scalar type
POINTFIELD_TYPES = {
    1: np.int8,
    2: np.uint8,
    3: np.int16,
    4: np.uint16,
    5: np.int32,
    6: np.uint32,
    7: np.float32,
    8: np.float64,
}

#: the field read as intensity, first found wins (else the intensity is 0): drivers name the
#: return strength differently (Velodyne/Hesai "intensity", Livox/PCL "i", Ouster also
#: "reflectivity")
INTENSITY_NAMES = ("intensity", "i", "reflectivity")


def cloud_dtype(msg, where: str = "PointCloud2") -> np.dtype:
    """The structured dtype of one point of ``msg`` (``itemsize = point_step``). A field with
    ``count > 1`` becomes a sub-array; a repeated name keeps its first occurrence; a field of an
    unknown datatype is left out (an error only for x, y or z)."""
    order = ">" if msg.is_bigendian else "<"
    step = int(msg.point_step)
    names, formats, offsets = [], [], []
    for f in msg.fields:
        code = int(f.datatype)
        if code not in POINTFIELD_TYPES:
            if f.name in ("x", "y", "z"):
                raise DataError(f"{where}: field {f.name!r} has unknown PointField datatype {code} (expected 1–8)")
            continue  # a vendor's field this reader does not use
        if f.name in names:
            continue
        scalar = np.dtype(POINTFIELD_TYPES[code]).newbyteorder(order)
        count = max(int(f.count), 1)
        if int(f.offset) < 0 or int(f.offset) + scalar.itemsize * count > step:
            raise DataError(
                f"{where}: field {f.name!r} (offset {f.offset}, {count}×{scalar.itemsize} bytes) "
                f"does not fit in point_step {step}"
            )
        names.append(f.name)
        formats.append(scalar if count == 1 else (scalar, (count,)))
        offsets.append(int(f.offset))
    if step <= 0:
        raise DataError(f"{where}: point_step is {step}")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})


def check_xyz(msg, where: str = "PointCloud2") -> None:
    """Raise a one-line DataError unless the cloud has x, y and z fields."""
    names = [f.name for f in msg.fields]
    if not {"x", "y", "z"} <= set(names):
        have = ", ".join(names) if names else "none"
        raise DataError(f"{where}: PointCloud2 has no x/y/z fields (its fields: {have})")


def structured_points(msg, where: str = "PointCloud2") -> np.ndarray:
    """The cloud's points as a (height, width) structured array viewing ``msg.data`` (no copy)."""
    dtype = cloud_dtype(msg, where)
    height, width, row_step = int(msg.height), int(msg.width), int(msg.row_step)
    if height == 0 or width == 0:
        return np.zeros((0, 0), dtype=dtype)
    if row_step < width * dtype.itemsize:
        raise DataError(f"{where}: row_step {row_step} is smaller than width {width} × point_step {dtype.itemsize}")
    data = msg.data
    buf = data if isinstance(data, (bytes, bytearray, memoryview)) else np.asarray(data).reshape(-1)
    size = len(buf) if not isinstance(buf, np.ndarray) else buf.nbytes
    needed = (height - 1) * row_step + width * dtype.itemsize
    if size < needed:
        raise DataError(
            f"{where}: data holds {size} bytes, {height}×{width} points of {dtype.itemsize} bytes "
            f"with row_step {row_step} need {needed} (truncated message)"
        )
    return np.ndarray(shape=(height, width), dtype=dtype, buffer=buf, offset=0, strides=(row_step, dtype.itemsize))


def to_xyzi(msg, where: str = "PointCloud2") -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity (0 when the cloud has none) of a PointCloud2, in its
    frame; returns with a NaN or infinite coordinate, and x = y = z = 0 returns, are dropped."""
    check_xyz(msg, where)
    pts = structured_points(msg, where)  # (height, width), rows possibly padded: no copy
    names = pts.dtype.names or ()
    inten = next((n for n in INTENSITY_NAMES if n in names), None)
    # one contiguous float32 copy per field, then 1-D tests: ~20× faster on a 120 k-point scan
    # than testing rows of an (N, 3) block (np.isfinite(...).all(axis=1) reduces over 3 elements)
    with np.errstate(invalid="ignore", over="ignore"):  # garbage values are dropped, not warned about
        x, y, z = (_field(pts, c) for c in ("x", "y", "z"))
        keep = np.isfinite(x + y + z)  # a NaN or ±inf coordinate makes the sum non-finite
        i = None if inten is None else _field(pts, inten)
    returned = x != 0
    returned |= y != 0
    returned |= z != 0
    keep &= returned
    out = np.empty((len(x), 4), dtype=np.float32)
    out[:, 0], out[:, 1], out[:, 2] = x, y, z
    if i is None:
        out[:, 3] = 0.0
    else:
        i[~np.isfinite(i)] = 0.0
        out[:, 3] = i
    return out if keep.all() else out[keep]


def _field(pts: np.ndarray, name: str) -> np.ndarray:
    """One field of every point as contiguous float32 (N,), in row order (the first element of a
    ``count > 1`` field)."""
    column = pts[name]
    if column.ndim == pts.ndim + 1:
        column = column[..., 0]
    return column.astype(np.float32).reshape(-1)
