"""A recording's PointCloud2 topic as a Sequence: ROS 1 ``.bag``, ROS 2 bag folders (sqlite3 or
MCAP storage), or a lone ``.db3`` / ``.mcap`` file; read with ``rosbags`` (no ROS installation).

**Which bag.** A folder must be a ROS 2 bag (it holds ``metadata.yaml``). A ``.db3`` or ``.mcap``
file is read through its folder when ``metadata.yaml`` is beside it (a split bag's parts are read
together), else on its own (the file carries its topics and, for MCAP and recent sqlite3 bags, the
message definitions; older sqlite3 files fall back to ROS 2 Humble's definitions).

**Which topic.** ``topic`` names a ``sensor_msgs/PointCloud2`` topic (the leading slash may be
left out); by default the bag's only one. Anything else is a one-line error listing the topics.

**Times and order.** A scan's time is its ``header.stamp`` (the sensor's clock), not the time
the recorder wrote it; scans are ordered by it, and :attr:`timestamps` counts from the first.
:attr:`stamps_ns` keeps the absolute stamps. A topic whose stamps are all the same (a driver that
never sets them) falls back to the recorder's times, with a note.

**Frames.** Scans are returned as the sensor gave them, in the cloud's ``frame_id`` (the LiDAR
frame): the localizer works in that frame with world ← LiDAR poses. Ground truth (``gt``, TUM or
KITTI, see :mod:`lidarloc.core.sequences.groundtruth`) is usually of the vehicle's base or IMU, so it is
moved to the LiDAR with base ← LiDAR (:mod:`lidarloc.core.sequences.extrinsic`: ``extrinsic`` if given,
else the bag's ``/tf_static`` chain from the root of the cloud frame's tree, else the identity).
Scans outside the truth's time span are left out (see :attr:`notes`). :attr:`poses` are re-based
so that the world is the first LiDAR pose, like every Sequence's; :attr:`truth_origin` is that
first pose in the truth's own frame, for a prior map given in that frame
(``truth_origin @ poses[i]`` is scan i's pose in it).

**Cost.** Opening reads the topic's messages once, in order, to index them (each message's
recorded time and header stamp; deserializing a PointCloud2 is zero-copy, so this costs one
sequential read of the topic's bytes — see BENCHMARKS.md for the measured rate) and keeps
nothing but that index in memory. A scan is then read on demand: consecutive scans continue one
stream through the bag (one read and one decode per scan), a jump (a kidnap, a seek in the
viewer) starts a new stream at the scan's recorded time — through the chunk index for ROS 1 and
MCAP (a ROS 1 jump walks the in-memory index from the start: milliseconds per 10⁴ messages), an
indexed query for sqlite3. A damaged bag found at opening or later is a one-line DataError naming
the file.

The sequence is thread-safe (one lock around the reader) and can be pickled: a copy in another
process opens the bag again on its first read, without indexing it again.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..cache import array_digest, file_identity
from ..errors import DataError
from .base import RecordedSequence
from .extrinsic import from_tf_static, resolve_extrinsic, transform_from_ros
from .groundtruth import MATCH_TOL_S, truth_of_recording
from .pointcloud2 import check_xyz, to_xyzi

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
BAG_KINDS = "a ROS 1 .bag, a ROS 2 bag folder (with metadata.yaml), a .db3 or an .mcap file"


def resolve_bag_path(path: str | os.PathLike) -> Path:
    """What to give rosbags for ``path`` (see the module docstring), or a one-line DataError."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: bag not found")
    if p.is_dir():
        if not (p / "metadata.yaml").is_file():
            inside = sorted(x.name for x in p.iterdir() if x.suffix in (".mcap", ".db3"))
            hint = f"; give the storage file itself ({inside[0]})" if inside else ""
            raise DataError(f"{p}: not a ROS 2 bag folder (no metadata.yaml){hint}; expected {BAG_KINDS}")
        return p
    suffix = p.suffix.lower()
    if suffix == ".bag":
        return p
    if suffix in (".mcap", ".db3"):
        return p.parent if (p.parent / "metadata.yaml").is_file() else p
    raise DataError(f"{p}: not a bag; expected {BAG_KINDS}")


@contextlib.contextmanager
def bag_errors(path: Path, doing: str = "reading"):
    """Whatever rosbags, sqlite or the file system raise while ``doing`` becomes one line naming
    the bag: a damaged bag shows up as any of a dozen exception types, none of them the user's to
    debug."""
    try:
        yield
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001 (see docstring)
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise DataError(f"{path}: truncated or corrupt bag ({doing}: {detail})") from None


def choose_topic(where: Path, topics: dict[str, str | None], topic: str | None) -> str:
    """The PointCloud2 topic to read: ``topic``, else the only one (one-line errors otherwise)."""
    clouds = sorted(n for n, t in topics.items() if t == POINTCLOUD2)
    listing = ", ".join(f"{n} ({t})" for n, t in sorted(topics.items())) or "none"
    if topic is not None:
        same = [c for c in clouds if c.lstrip("/") == topic.lstrip("/")]
        if same:
            return same[0]
        other = next((t for n, t in topics.items() if n.lstrip("/") == topic.lstrip("/")), None)
        what = f"topic {topic} is a {other}, not a sensor_msgs/PointCloud2" if other else f"no topic {topic}"
        choices = (
            f"PointCloud2 topics: {', '.join(clouds)}" if clouds else f"no PointCloud2 topic at all (topics: {listing})"
        )
        raise DataError(f"{where}: {what}; {choices}")
    if len(clouds) == 1:
        return clouds[0]
    if not clouds:
        raise DataError(f"{where}: no sensor_msgs/PointCloud2 topic (topics: {listing})")
    raise DataError(f"{where}: {len(clouds)} PointCloud2 topics, choose one with --topic: {', '.join(clouds)}")


def _open_reader(bag: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with bag_errors(bag, "opening"):
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    return reader


def _stamp_ns(msg) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class BagSequence(RecordedSequence):
    """See the module docstring. ``gt``: a TUM or KITTI poses file (or a loaded
    :class:`~lidarloc.core.sequences.groundtruth.Truth`), ``gt_times`` the times file of a KITTI one;
    ``extrinsic``: base ← LiDAR as a 4×4 array, a text file or "identity"; ``progress(i, n)`` is
    called while the topic is indexed (a long bag takes seconds: worth a progress bar)."""

    def __init__(
        self,
        path: str | os.PathLike,
        topic: str | None = None,
        gt=None,
        extrinsic=None,
        gt_times: str | os.PathLike | None = None,
        match_tol: float = MATCH_TOL_S,
        progress: Callable[[int, int], None] | None = None,
    ):
        self.path = Path(path)
        self._bag = resolve_bag_path(self.path)
        self.notes: list[str] = []
        self._lock = threading.Lock()
        self._reader = None
        self._pid = None
        self._cursor = None  # (generator, next log position) of the stream being read
        reader = self._ensure_open()
        try:
            self._set_up(reader, topic, gt, extrinsic, gt_times, match_tol, progress)
        except BaseException:
            self.close()  # a refused bag leaves no open file behind
            raise

    def _set_up(self, reader, topic, gt, extrinsic, gt_times, match_tol, progress) -> None:
        with bag_errors(self.path, "listing topics"):
            topics = {name: info.msgtype for name, info in reader.topics.items()}
        self.topic = choose_topic(self.path, topics, topic)
        self.name = f"bag {self.path.name} {self.topic}"
        log_ns, stamp_ns, self.frame_id = self._index(reader, progress)

        # scans in header-stamp order; positions refer to the topic's messages in recorded order
        self._log_ns = log_ns  # by recorded position
        self._header_ns = stamp_ns  # by recorded position: checks each read
        times_ns = stamp_ns
        if len(stamp_ns) > 1 and (stamp_ns == stamp_ns[0]).all():
            times_ns = log_ns  # a driver that never sets the stamp
            self.notes.append(
                f"{self.path}: every {self.topic} header has the stamp {stamp_ns[0] / 1e9:.9f} s; "
                "the recorder's times are used instead"
            )
        order = np.argsort(times_ns, kind="stable")
        self._positions = order  # scan → recorded position
        stamps = times_ns[order]
        repeated = int((np.diff(stamps) == 0).sum())
        if repeated:
            self.notes.append(f"{self.path}: {repeated} {self.topic} message(s) repeat the previous one's time")

        edges = self._tf_static(reader, topics)
        T = resolve_extrinsic(extrinsic)
        if T is None and edges:
            found = from_tf_static(edges, self.frame_id)
            if found is not None:
                root, T = found
                self.notes.append(f"{self.path}: LiDAR extrinsic {root} ← {self.frame_id} from /tf_static")
        self.T_base_lidar = T

        self._poses = None
        self.truth_origin = None
        self._gt_identity = ""
        if gt is not None:
            matched = truth_of_recording(gt, gt_times, stamps / 1e9, T, match_tol)
            self.notes += matched.notes
            self._positions = self._positions[matched.keep]
            stamps = stamps[matched.keep]
            self.truth_origin = matched.origin
            self._poses = matched.rebased
            self._gt_identity = matched.identity
        self.stamps_ns = stamps
        self._times = (stamps - stamps[0]).astype(np.float64) / 1e9

    # ------------------------------------------------------------------ opening and indexing
    def _ensure_open(self):
        if self._reader is None or self._pid != os.getpid():
            self._reader = _open_reader(self._bag)
            self._pid = os.getpid()
            self._cursor = None
        return self._reader

    def _connections(self, reader):
        return [c for c in reader.connections if c.topic == self.topic]

    def _index(self, reader, progress=None) -> tuple[np.ndarray, np.ndarray, str]:
        log, stamps, frame = [], [], ""
        conns = self._connections(reader)
        expected = sum(int(c.msgcount) for c in conns)
        with bag_errors(self.path, f"indexing {self.topic}"):
            for conn, t, raw in reader.messages(connections=conns):
                if progress is not None and len(log) % 50 == 0:
                    progress(len(log), expected)
                msg = reader.deserialize(raw, conn.msgtype)
                if not log:
                    check_xyz(msg, f"{self.path} {self.topic}")
                    frame = str(msg.header.frame_id)
                log.append(t)
                stamps.append(_stamp_ns(msg))
        if not log:
            raise DataError(f"{self.path}: topic {self.topic} has no messages")
        if progress is not None:
            progress(len(log), len(log))
        return np.asarray(log, dtype=np.int64), np.asarray(stamps, dtype=np.int64), frame

    def _tf_static(self, reader, topics) -> dict:
        names = [n for n, t in topics.items() if n.lstrip("/") == "tf_static" and t == TFMESSAGE]
        edges: dict[str, tuple[str, np.ndarray]] = {}
        if not names:
            return edges
        with bag_errors(self.path, "reading /tf_static"):
            conns = [c for c in reader.connections if c.topic in names]
            for conn, _, raw in reader.messages(connections=conns):
                for tf in reader.deserialize(raw, conn.msgtype).transforms:
                    T = transform_from_ros(tf.transform.translation, tf.transform.rotation)
                    edges[str(tf.child_frame_id).lstrip("/")] = (str(tf.header.frame_id).lstrip("/"), T)
        return edges

    # ------------------------------------------------------------------ the Sequence interface
    def __len__(self) -> int:
        return len(self._positions)

    def describe_scan(self, i: int) -> str:
        return f"{self.path} {self.topic} message {int(self._positions[i])} (stamp {self.stamps_ns[i] / 1e9:.6f} s)"

    def _read_scan(self, i: int) -> np.ndarray:
        with self._lock:
            reader = self._ensure_open()
            with bag_errors(self.path, f"reading {self.topic} message {int(self._positions[i])}"):
                pos = int(self._positions[i])
                msg = self._message(reader, pos, int(self._header_ns[pos]))
            return to_xyzi(msg, self.describe_scan(i))

    def _message(self, reader, pos: int, stamp: int):
        if self._cursor is None or self._cursor[1] != pos:
            log_t = int(self._log_ns[pos])
            stream = reader.messages(connections=self._connections(reader), start=log_t)
            # messages recorded at the same instant come in recorded order: skip the earlier ones
            skip = pos - int(np.searchsorted(self._log_ns, log_t, side="left"))
            self._cursor = (stream, pos - skip)
            for _ in range(skip):
                self._next_raw(pos)
        conn, raw = self._next_raw(pos)
        msg = reader.deserialize(raw, conn.msgtype)
        if _stamp_ns(msg) != stamp:
            self._cursor = None
            msg = self._message_by_stamp(reader, pos, stamp)
        return msg

    def _next_raw(self, pos: int):
        stream, at = self._cursor
        try:
            conn, _, raw = next(stream)
        except StopIteration:
            self._cursor = None
            raise self._missing(pos) from None
        self._cursor = (stream, at + 1)
        return conn, raw

    def _message_by_stamp(self, reader, pos: int, stamp: int):
        """The message recorded at ``pos``'s time whose header has ``stamp`` (when a storage does
        not return messages recorded at the same instant in the order they were indexed)."""
        log_t = int(self._log_ns[pos])
        for conn, _, raw in reader.messages(connections=self._connections(reader), start=log_t, stop=log_t + 1):
            msg = reader.deserialize(raw, conn.msgtype)
            if _stamp_ns(msg) == stamp:
                return msg
        raise self._missing(pos)

    def _missing(self, pos: int) -> DataError:
        return DataError(
            f"{self.path}: message {pos} of {self.topic} is missing (the bag changed since it was opened?)"
        )

    # ------------------------------------------------------------------ identity, life cycle
    def identity(self) -> str:
        return (
            f"bag|{file_identity(self._bag)}|{self.topic}|gt={self._gt_identity}|ext={array_digest(self.T_base_lidar)}"
        )

    def close(self) -> None:
        with self._lock:
            reader, self._reader, self._cursor = self._reader, None, None
            if reader is not None and self._pid == os.getpid():
                with contextlib.suppress(Exception):
                    reader.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self):
        state = self.__dict__.copy()
        state.update(_lock=None, _reader=None, _pid=None, _cursor=None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()
