"""Per-tile cache files of a tiled table (lookup table, BEV pyramid): one ``.npy`` file per tile
and layer, opened memory-mapped, and an index (``tiles.json``) naming the table's key and every
tile's arrays with their sizes and CRC-32.

Why per tile: a city's tables are larger than a run needs (a 4 × 4 km city's lookup table is
several GB); a run maps in the tiles its particles and its searches touch and drops the others,
and the operating system pages in only the parts of a mapped tile that are read.

Why a CRC per tile: a truncated file is caught by its size, but a tile copied from another cache
(another map, another resolution) has the right size. Each tile file's CRC is checked once per
process, when it is first opened, reading the file in chunks (not through the map, so the check
leaves nothing resident); a tile reopened later (a run coming back to it) is checked again only
if its file changed (size, modification time or inode). A tile that fails is rebuilt and
rewritten (temporary file, then rename).
"""

from __future__ import annotations

import json
import threading
import zlib
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from ..cache import atomic_write_file, cache_rebuilt
from ..errors import DataError

INDEX = "tiles.json"
T = TypeVar("T")
_CHUNK = 1 << 22

# files whose CRC matched, as (path, size, mtime_ns, inode, crc): a file changed since is checked again
_checked: set[tuple] = set()
_checked_lock = threading.Lock()


def tile_name(tx: int, ty: int) -> str:
    return f"t{tx}_{ty}"


def file_crc(path: Path) -> int:
    crc = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            crc = zlib.crc32(chunk, crc)
    return crc


def write_tile(directory: Path, name: str, arrays: dict[str, np.ndarray]) -> dict:
    """Write each array as ``<name>.<layer>.npy`` atomically; returns the index entry."""
    entry = {}
    for layer, array in arrays.items():
        path = Path(directory) / f"{name}.{layer}.npy"
        atomic_write_file(path, lambda tmp, a=array: np.save(tmp, a))
        entry[layer] = {"bytes": path.stat().st_size, "crc": file_crc(path), "shape": list(array.shape)}
    return entry


def open_tile(directory: Path, name: str, entry: dict) -> dict[str, np.ndarray]:
    """The tile's arrays, memory-mapped read-only, after checking size and CRC against the index
    entry; DataError names what is wrong (the caller rebuilds the tile)."""
    out = {}
    for layer, want in entry.items():
        path = Path(directory) / f"{name}.{layer}.npy"
        try:
            st = path.stat()
        except OSError:
            raise DataError(f"{path}: missing tile file") from None
        if st.st_size != want["bytes"]:
            raise DataError(f"{path}: truncated tile file ({st.st_size} of {want['bytes']} bytes)")
        seen = (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino, want["crc"])
        with _checked_lock:
            checked = seen in _checked
        if not checked:
            if file_crc(path) != want["crc"]:
                raise DataError(f"{path}: tile file of another table (checksum differs)")
            with _checked_lock:
                _checked.add(seen)
        try:
            array = np.load(path, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise DataError(f"{path}: unreadable tile file ({exc})") from None
        if list(array.shape) != want["shape"]:
            raise DataError(f"{path}: tile file of another shape {array.shape}")
        out[layer] = array
    return out


def open_or_rebuild(directory: Path, name: str, entry: dict, read: Callable[[dict], T], rebuild, hint: str) -> T:
    """Tile ``name``'s arrays as ``read`` takes them from :func:`open_tile`; a damaged tile is made
    again by ``rebuild()`` (the user told), or, where it cannot be (``rebuild`` None), a
    DataError naming the file and ending in ``hint`` (what the user can do)."""
    try:
        return read(open_tile(directory, name, entry))
    except DataError as exc:
        if rebuild is None:
            raise DataError(f"{exc}; {hint}") from None
        cache_rebuilt(Path(directory) / name, str(exc))
        return rebuild()


def remember(opened: OrderedDict, key, value, max_open: int):
    """``value`` as the most recently used of a reader's open tiles (``opened``, least recently
    used first); the least recently used beyond ``max_open`` are forgotten (unmapped once nothing
    else holds them). Returns ``value``."""
    opened[key] = value
    while len(opened) > max_open:
        opened.popitem(last=False)
    return value


def read_index(directory: Path, key: str) -> dict | None:
    """The index of a cached tiled table made for ``key``, or None (absent, unreadable, foreign)."""
    try:
        index = json.loads((Path(directory) / INDEX).read_text())
    except (OSError, ValueError):
        return None
    return index if isinstance(index, dict) and index.get("key") == key else None


def write_index(directory: Path, index: dict) -> None:
    atomic_write_file(Path(directory) / INDEX, lambda tmp: tmp.write_text(json.dumps(index, indent=1)))


def cache_bytes(directory: Path) -> int:
    return sum(p.stat().st_size for p in Path(directory).glob("*.npy")) + (Path(directory) / INDEX).stat().st_size
