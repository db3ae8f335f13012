"""Point-cloud map files: read a user's prior map (.pcd, .ply, .las/.laz, .npy/.npz) into a local
float32 frame with a float64 origin, and write maps as .pcd or .ply.

Georeferenced maps
    A surveyed or SLAM map may be in UTM (x ≈ 5·10⁵ m, y ≈ 4·10⁶ m). float32 keeps 24 bits of
    mantissa: 0.25–0.5 m steps at 4·10⁶ m, so such coordinates cannot be held as float32 as they
    are. Every map is read as ``points`` (float32) in a local frame plus a float64 ``origin``:
    world (the file's frame) = local + origin. The origin is chosen per axis: where the file's
    coordinates on that axis exceed ±10 km (float32 steps ≥ 1 mm), the bounding box's centre on
    that axis rounded to 1 km; else 0, so a map already in a local frame (a KITTI drive, a
    FAST-LIO map) keeps its coordinates and heights stay heights. Round kilometres make the
    origin easy to read and to add back by hand.

Memory
    A 50 M-point map is 600 MB as float32 xyz. Binary PCD and PLY files, .las/.laz and .npy are
    read in chunks of :data:`CHUNK_POINTS` points (one float64 chunk at a time, the file's own
    fields never all at once) straight into the one float32 output array, so the peak is about
    the output plus a chunk. A file whose header does not give the bounding box (PCD, PLY, .npy)
    is read twice: once for the bounds (to choose the origin before any coordinate is rounded
    to float32), once for the points. ASCII PCD/PLY is parsed chunk by chunk too; compressed PCD
    (and PLY with lists or other elements before its vertices) goes through open3d, which holds
    the whole cloud as float64;
    .npz members cannot be read in parts and are loaded whole.

Points that are not finite (NaN/inf: an organised cloud's missing returns) or lie beyond 10⁸ m
(no place on Earth; a damaged file's garbage) are dropped and counted; a map with no point left
is an error. A file numpy cannot parse is one line, whatever numpy raised. Only x, y, z are read; other fields
(intensity, rgb, normals, padding) are skipped.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError

#: Formats read by :func:`read_map` and written by :func:`write_map`.
READ_SUFFIXES = (".pcd", ".ply", ".las", ".laz", ".npy", ".npz")
WRITE_SUFFIXES = (".pcd", ".ply")
#: Points per chunk when reading or writing (2²¹: a 48 MB float64 chunk).
CHUNK_POINTS = 1 << 21
#: Beyond this (m) on an axis, float32 steps exceed 1 mm: the origin moves to the map (see above).
LARGE_COORDINATE = 10_000.0
ORIGIN_ROUNDING = 1_000.0

_MAX_HEADER = 1 << 16


@dataclass
class MapCloud:
    """A map file's finite points in the local frame: world = ``points`` + ``origin``."""

    points: np.ndarray  # (N, 3) float32, local frame
    origin: np.ndarray  # (3,) float64, the local frame's origin in the file's frame
    path: Path
    n_read: int  # points in the file
    n_dropped_nonfinite: int  # of which not finite or beyond MAX_COORD_M (dropped)

    def world_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Min and max per axis in the file's frame (float64)."""
        return (
            self.points.min(axis=0).astype(np.float64) + self.origin,
            self.points.max(axis=0).astype(np.float64) + self.origin,
        )


def choose_origin(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The local frame's origin for a map with bounds ``lo``..``hi`` (see the module docstring)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    large = np.maximum(np.abs(lo), np.abs(hi)) > LARGE_COORDINATE
    centre = np.round((lo + hi) / 2.0 / ORIGIN_ROUNDING) * ORIGIN_ROUNDING
    return np.where(large, centre, 0.0)


def _unsupported(path: Path, verb: str, suffixes) -> DataError:
    return DataError(
        f"{path}: cannot {verb} a map of this type ({path.suffix or 'no extension'}); supported: {', '.join(suffixes)}"
    )


# ------------------------------------------------------------------------------------ reading
class _Chunks:
    """A map file as chunks of float64 xyz: ``n`` points, optional header ``bounds``, and
    ``iterate()`` (callable more than once: a second pass reads the file again)."""

    def __init__(self, n: int, iterate: Callable[[], Iterator[np.ndarray]], bounds=None):
        self.n, self.iterate, self.bounds = n, iterate, bounds


def read_map(path, progress: Callable[[int, int], None] | None = None, chunk_points: int = CHUNK_POINTS) -> MapCloud:
    """The map in ``path`` (format from the extension, see :data:`READ_SUFFIXES`) as a
    :class:`MapCloud`. ``progress(done, total)`` is called after each chunk (in points, over
    every pass). Raises :class:`DataError` with one line naming the file on any bad input."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in READ_SUFFIXES:
        raise _unsupported(path, "read", READ_SUFFIXES)
    if not path.is_file():
        raise DataError(f"{path}: no such map file")
    try:
        if suffix == ".pcd":
            source = _pcd_chunks(path, chunk_points)
        elif suffix == ".ply":
            source = _ply_chunks(path, chunk_points)
        elif suffix in (".las", ".laz"):
            source = _las_chunks(path, chunk_points)
        else:
            source = _numpy_chunks(path, chunk_points)
        return _assemble(path, source, progress)
    except DataError:
        raise
    except MemoryError:
        raise
    except OSError as exc:
        raise DataError(f"{path}: cannot read the map ({exc.strerror or exc})") from None
    except Exception as exc:  # a parser's own error on a corrupt file: one line, not a traceback
        raise DataError(
            f"{path}: cannot read the map, corrupt or truncated ({type(exc).__name__}: {exc})".splitlines()[0]
        ) from None


#: Coordinates beyond this (metres) are no place on Earth in any map frame (UTM northings stay
#: below 10⁷ m, ECEF below 6.4·10⁶ m): such a point is dropped like a NaN one, instead of
#: overflowing the map's float32 local frame or stretching its extent over light-years.
MAX_COORD_M = 1.0e8
UNUSABLE = "NaN, infinite or beyond 10⁸ m"


def _usable(xyz: np.ndarray) -> np.ndarray:
    """Which rows of ``xyz`` are points a map can hold (finite, within ``MAX_COORD_M``)."""
    with np.errstate(invalid="ignore"):
        return (np.abs(xyz) <= MAX_COORD_M).all(axis=1)  # NaN compares False


def _assemble(path: Path, source: _Chunks, progress) -> MapCloud:
    if source.n == 0:
        raise DataError(f"{path}: the map holds no points")
    passes = 1 if source.bounds is not None else 2
    total, done = source.n * passes, 0
    bounds = source.bounds
    if bounds is None:
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for xyz in source.iterate():
            good = xyz[_usable(xyz)]
            if len(good):
                lo, hi = np.minimum(lo, good.min(axis=0)), np.maximum(hi, good.max(axis=0))
            done += len(xyz)
            if progress is not None:
                progress(done, total)
        if not np.isfinite(lo).all():
            raise DataError(f"{path}: the map has no finite point within 10⁸ m (all {source.n:,} are {UNUSABLE})")
        bounds = (lo, hi)
    origin = choose_origin(*bounds)
    out = np.empty((source.n, 3), dtype=np.float32)
    k = n_read = 0
    for xyz in source.iterate():
        n_read += len(xyz)
        if n_read > source.n:
            raise DataError(f"{path}: more points than its header says ({source.n:,})")
        good = xyz[_usable(xyz)]
        good -= origin
        out[k : k + len(good)] = good
        k += len(good)
        done += len(xyz)
        if progress is not None:
            progress(done, total)
    if n_read < source.n:
        raise DataError(f"{path}: truncated: {n_read:,} of the {source.n:,} points its header says")
    if k == 0:
        raise DataError(f"{path}: the map has no finite point within 10⁸ m (all {n_read:,} are {UNUSABLE})")
    if k < len(out):
        # shrinks the allocation in place (no second copy of a large map)
        out.resize((k, 3), refcheck=False)
    return MapCloud(points=out, origin=origin, path=path, n_read=n_read, n_dropped_nonfinite=n_read - k)


def _from_records(records: np.ndarray, names: tuple[str, str, str]) -> np.ndarray:
    xyz = np.empty((len(records), 3), dtype=np.float64)
    for j, name in enumerate(names):
        xyz[:, j] = records[name]
    return xyz


def _binary_chunks(path: Path, offset: int, n: int, dtype: np.dtype, names, chunk_points: int) -> _Chunks:
    """Fixed-size records from ``offset`` on: checked against the file's size, read chunk by chunk
    into one reused buffer. ``names``: the x, y, z fields of a structured ``dtype``, or None for
    rows of plain numbers whose first three are x, y, z."""
    need = offset + n * dtype.itemsize
    size = path.stat().st_size
    if size < need:
        raise DataError(
            f"{path}: truncated: the header says {n:,} points ({need:,} bytes), the file has {size:,} bytes"
        )

    def iterate():
        buf = np.empty(min(chunk_points, max(n, 1)), dtype=dtype)
        raw = buf.view(np.uint8)
        with open(path, "rb") as f:
            f.seek(offset)
            left = n
            while left > 0:
                m = min(left, len(buf))
                got = f.readinto(memoryview(raw)[: m * dtype.itemsize])
                if got != m * dtype.itemsize:
                    raise DataError(f"{path}: truncated while reading")
                yield _from_records(buf[:m], names) if names else np.asarray(buf[:m, :3], dtype=np.float64)
                left -= m

    return _Chunks(n, iterate)


def _read_header(path: Path, is_end: Callable[[str], bool], what: str) -> tuple[list[str], int]:
    """The header lines of a text-headed binary format, up to and including the one ``is_end``
    accepts, and the byte offset after it."""
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER)
    lines, pos = [], 0
    while True:
        nl = head.find(b"\n", pos)
        if nl < 0:
            raise DataError(f"{path}: not a {what} file (no complete header)")
        line = head[pos:nl].decode("ascii", errors="replace").strip()
        pos = nl + 1
        lines.append(line)
        if is_end(line):
            return lines, pos


_PCD_TYPES = {"F": "f", "I": "i", "U": "u"}


def _pcd_chunks(path: Path, chunk_points: int):
    lines, offset = _read_header(path, lambda s: s.upper().startswith("DATA"), "PCD")
    header = {}
    for line in lines:
        if line and not line.startswith("#"):
            key, _, value = line.partition(" ")
            header[key.upper()] = value.split()
    try:
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        n = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        data = header["DATA"][0].lower()
    except (KeyError, IndexError, ValueError):
        raise DataError(f"{path}: not a valid PCD file (header lacks FIELDS/SIZE/TYPE/POINTS/DATA)") from None
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise DataError(f"{path}: not a valid PCD file (FIELDS, SIZE, TYPE and COUNT differ in length)")
    lower = [f.lower() for f in fields]
    if not {"x", "y", "z"} <= set(lower):
        raise DataError(f"{path}: the PCD has no x/y/z fields (fields: {' '.join(fields)})")
    if n == 0:
        raise DataError(f"{path}: the map holds no points")
    if data == "ascii":
        starts = np.cumsum([0] + counts)
        return _ascii_chunks(path, offset, n, tuple(int(starts[lower.index(a)]) for a in "xyz"), chunk_points)
    if data != "binary":
        return _open3d_cloud(path, n)
    try:
        dtype = np.dtype(
            {
                "names": _unique(lower),
                "formats": [
                    (f"<{_PCD_TYPES[t.upper()]}{s}", (c,)) if c > 1 else f"<{_PCD_TYPES[t.upper()]}{s}"
                    for t, s, c in zip(types, sizes, counts)
                ],
            }
        )
    except (KeyError, TypeError):
        raise DataError(
            f"{path}: not a valid PCD file (field types {' '.join(types)}, sizes {' '.join(map(str, sizes))})"
        ) from None
    return _binary_chunks(path, offset, n, dtype, ("x", "y", "z"), chunk_points)


def _unique(names: list[str]) -> list[str]:
    """Field names made unique (PCL pads points with several fields named ``_``)."""
    seen, out = set(), []
    for i, name in enumerate(names):
        out.append(name if name not in seen else f"{name}__{i}")
        seen.add(name)
    return out


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def _ply_chunks(path: Path, chunk_points: int):
    with open(path, "rb") as f:
        if f.read(4) not in (b"ply\n", b"ply\r"):
            raise DataError(f"{path}: not a PLY file (it does not start with 'ply')")
    lines, offset = _read_header(path, lambda s: s == "end_header", "PLY")
    fmt, elements = None, []
    for line in lines:
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) > 1:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            elements[-1][2].append(words[1:])
    vertex = next((e for e in elements if e[0] == "vertex"), None)
    if vertex is None:
        raise DataError(f"{path}: the PLY has no vertex element")
    names = [p[-1].lower() for p in vertex[2]]
    if not {"x", "y", "z"} <= set(names):
        raise DataError(f"{path}: the PLY's vertices have no x/y/z properties ({' '.join(names) or 'none'})")
    n = vertex[1]
    if n == 0:
        raise DataError(f"{path}: the map holds no points")
    scalar = all(len(p) == 2 and p[0] in _PLY_TYPES for p in vertex[2])
    if fmt in ("binary_little_endian", "binary_big_endian") and elements[0] is vertex and scalar:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype({"names": _unique(names), "formats": [order + _PLY_TYPES[p[0]] for p in vertex[2]]})
        return _binary_chunks(path, offset, n, dtype, ("x", "y", "z"), chunk_points)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: not a valid PLY file (format {fmt!r})")
    if fmt == "ascii" and elements[0] is vertex and scalar:
        return _ascii_chunks(path, offset, n, tuple(names.index(a) for a in "xyz"), chunk_points)
    return _open3d_cloud(path, n)


def _ascii_chunks(path: Path, offset: int, n: int, columns: tuple[int, int, int], chunk_points: int) -> _Chunks:
    """Whitespace-separated rows after the header, one point each; x, y, z in ``columns``."""

    def iterate():
        with open(path, "rb") as raw:
            raw.seek(offset)
            lines = (line.decode("ascii", errors="replace") for line in raw)
            left = n
            while left > 0:
                m = min(left, chunk_points)
                try:
                    xyz = np.loadtxt(itertools.islice(lines, m), dtype=np.float64, usecols=columns, ndmin=2)
                except ValueError as exc:
                    raise DataError(f"{path}: a point row cannot be read ({exc})".splitlines()[0]) from None
                if len(xyz) < m:
                    raise DataError(f"{path}: truncated: {n - left + len(xyz):,} of the {n:,} points its header says")
                yield xyz
                left -= m

    return _Chunks(n, iterate)


def _open3d_cloud(path: Path, n_expected: int) -> _Chunks:
    """The layouts read by open3d (compressed PCD, PLY with lists or other elements before the
    vertices): the whole cloud at once, as float64."""
    from ..o3d import open3d

    o3d = open3d()
    # open3d reports a file it cannot parse as a warning and an empty cloud: check the count
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    pts = np.asarray(cloud.points)
    if len(pts) == 0:
        raise DataError(
            f"{path}: cannot read the map (corrupt, or a layout open3d does not read); "
            f"the header says {n_expected:,} points"
        )
    return _Chunks(len(pts), lambda: iter([pts]))


def _las_chunks(path: Path, chunk_points: int) -> _Chunks:
    import laspy

    try:
        with laspy.open(path) as reader:
            header = reader.header
            n = int(header.point_count)
            lo, hi = np.asarray(header.mins, np.float64), np.asarray(header.maxs, np.float64)
    except laspy.errors.LaspyException as exc:
        raise DataError(f"{path}: not a valid LAS/LAZ file ({exc})".splitlines()[0]) from None
    if n == 0:
        raise DataError(f"{path}: the LAS file holds no points")
    # the header's bounds choose the origin (one pass); a writer that left them unset costs a pass
    bounds = (
        (lo, hi) if np.isfinite(lo).all() and np.isfinite(hi).all() and (lo <= hi).all() and (hi > lo).any() else None
    )

    def iterate():
        with laspy.open(path) as reader:
            for points in reader.chunk_iterator(chunk_points):
                xyz = np.empty((len(points), 3), dtype=np.float64)
                xyz[:, 0], xyz[:, 1], xyz[:, 2] = points.x, points.y, points.z
                yield xyz

    return _Chunks(n, iterate, bounds)


def _not_valid(path: Path, kind: str, exc: Exception) -> str:
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return f"{path}: not a valid {kind} file ({detail[:200]})"


def _numpy_chunks(path: Path, chunk_points: int) -> _Chunks:
    if path.suffix.lower() == ".npy":
        with open(path, "rb") as f:
            try:
                version = np.lib.format.read_magic(f)
                read_header = {
                    (1, 0): np.lib.format.read_array_header_1_0,
                    (2, 0): np.lib.format.read_array_header_2_0,
                }.get(version)
                shape, fortran, dtype = read_header(f) if read_header else ((), True, np.dtype(object))
            except Exception as exc:  # numpy's header parser raises ValueError, SyntaxError, TokenError, …
                raise DataError(_not_valid(path, ".npy", exc)) from None
            offset = f.tell()
        if len(shape) == 2 and shape[1] >= 3 and not fortran and dtype.kind in "fiu" and not dtype.hasobject:
            # rows read straight from the file: a memory map would count the whole file as resident
            return _binary_chunks(path, offset, shape[0], np.dtype((dtype, (shape[1],))), None, chunk_points)
        try:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        except Exception as exc:  # cut short, a header numpy cannot parse
            raise DataError(_not_valid(path, ".npy", exc)) from None
    else:
        try:
            with np.load(path, allow_pickle=False) as npz:
                keys = list(npz.keys())
                if "points" in keys:
                    key = "points"
                elif len(keys) == 1:
                    key = keys[0]
                else:
                    raise DataError(
                        f"{path}: no array named 'points' and {len(keys)} arrays "
                        f"({', '.join(keys) or 'none'}): name the map's array 'points'"
                    )
                arr = npz[key]
        except DataError:
            raise
        except Exception as exc:  # a damaged zip or array inside: any of a dozen types
            raise DataError(_not_valid(path, ".npz", exc)) from None
    if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
        raise DataError(f"{path}: expected an (N, ≥3) numeric array of points, got shape {arr.shape} {arr.dtype}")

    def iterate():
        for i in range(0, len(arr), chunk_points):
            yield np.asarray(arr[i : i + chunk_points, :3], dtype=np.float64)

    return _Chunks(len(arr), iterate)
