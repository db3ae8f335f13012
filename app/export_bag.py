"""A recorded run as a ROS 2 bag in MCAP storage, with standard messages only, written with
``rosbags`` (no ROS installation): ``lidarloc export RUN --bag OUT.mcap`` and ``lidarloc run …
--write-bag OUT.mcap``. It plays in RViz2 (``ros2 bag play``) and opens in Foxglove as it is.

``OUT.mcap`` is one self-describing file (message definitions inside); a name without a suffix
is a bag folder (``OUT/OUT.mcap`` and ``metadata.yaml``), what ``ros2 bag play`` of older ROS 2
releases asks for. Stamps and frames: :mod:`.run_steps`.

========================  ============================================  ==========================================
topic                     type                                          what
========================  ============================================  ==========================================
/lidarloc/pose            geometry_msgs/msg/PoseWithCovarianceStamped   the estimate; covariance of the particles
/tf                       tf2_msgs/msg/TFMessage                        map → lidar (estimate), map → lidar_truth
/tf_static                tf2_msgs/msg/TFMessage                        map → map_local (only a map with an origin)
/lidarloc/particles       geometry_msgs/msg/PoseArray                   every particle's pose
/lidarloc/particle_cloud  sensor_msgs/msg/PointCloud2                   the particles as points: x, y, z, weight
/lidarloc/truth           geometry_msgs/msg/PoseStamped                 the ground truth (sources that have it)
/lidarloc/scan            sensor_msgs/msg/PointCloud2                   the scan as the filter weighed it (lidar)
/lidarloc/map             sensor_msgs/msg/PointCloud2                   the prior map, once, latched
/rosout                   rcl_interfaces/msg/Log                        events: localized, loss, S2M results, …
/diagnostics              diagnostic_msgs/msg/DiagnosticArray           per scan: std, N_eff, error, latencies
========================  ============================================  ==========================================

``/lidarloc/map`` and ``/tf_static`` are offered with transient-local durability (latched), so a
late subscriber of ``ros2 bag play`` still gets them. With ``with_input`` (a run on a bag) every
topic of the input bag within the run's time span is copied in too, under its own name; the
input's ``/tf``, ``/tf_static`` and ``/rosout`` become ``/input/tf``, … so that its frames do not
clash with ``map → lidar``. The input must be a ROS 2 bag (a ROS 1 bag: convert it first).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from scipy.spatial.transform import Rotation

from ..core.errors import LidarlocError
from ..core.geometry import rotation_zyx
from .run_steps import LIDAR_FRAME, LOCAL_FRAME, MAP_FRAME, TRUTH_FRAME, RunSteps, Step, event_level

POSE = "/lidarloc/pose"
TF = "/tf"
TF_STATIC = "/tf_static"
PARTICLES = "/lidarloc/particles"
PARTICLE_CLOUD = "/lidarloc/particle_cloud"
TRUTH = "/lidarloc/truth"
SCAN = "/lidarloc/scan"
MAP = "/lidarloc/map"
ROSOUT = "/rosout"
DIAGNOSTICS = "/diagnostics"
#: (topic, type) of everything lidarloc writes
TOPICS = {
    POSE: "geometry_msgs/msg/PoseWithCovarianceStamped",
    TF: "tf2_msgs/msg/TFMessage",
    TF_STATIC: "tf2_msgs/msg/TFMessage",
    PARTICLES: "geometry_msgs/msg/PoseArray",
    PARTICLE_CLOUD: "sensor_msgs/msg/PointCloud2",
    TRUTH: "geometry_msgs/msg/PoseStamped",
    SCAN: "sensor_msgs/msg/PointCloud2",
    MAP: "sensor_msgs/msg/PointCloud2",
    ROSOUT: "rcl_interfaces/msg/Log",
    DIAGNOSTICS: "diagnostic_msgs/msg/DiagnosticArray",
}
LATCHED = (MAP, TF_STATIC)
#: the input bag's topics that would clash with lidarloc's frames or logs are copied under this prefix
INPUT_PREFIX = "/input"
#: rcl_interfaces/msg/Log levels
LOG_LEVELS = {"info": 20, "warning": 30, "error": 40}
FLOAT32 = 7  # sensor_msgs/PointField datatype


def bag_target(out) -> tuple[Path, Path | None]:
    """(the folder rosbags writes, the single .mcap file it becomes or None) for ``out``; one-line
    errors for a name that is not .mcap or a folder, an existing target or an unwritable place."""
    out = Path(out).expanduser()
    suffix = out.suffix.lower()
    if suffix and suffix != ".mcap":
        raise LidarlocError(f"{out}: a bag is written as MCAP: name it NAME.mcap (one file) or NAME (a bag folder)")
    if out.exists():
        raise LidarlocError(f"{out}: already exists; choose another name or remove it")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LidarlocError(f"{out.parent}: cannot create the folder ({exc.strerror})") from None
    if suffix == ".mcap":
        folder = out.with_name(f".{out.stem}.writing")
        if folder.exists():
            shutil.rmtree(folder)  # a write cut short before
        return folder, out
    return out, None


# -------------------------------------------------------------------------------- messages
class _Messages:
    """ROS 2 messages of the steps, built from the Humble type store of rosbags."""

    def __init__(self):
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.t = self.ts.types

    def serialize(self, msg, topic: str) -> bytes:
        return self.ts.serialize_cdr(msg, TOPICS[topic])

    def header(self, stamp_ns: int, frame: str):
        t = self.t
        return t["std_msgs/msg/Header"](stamp=self.time(stamp_ns), frame_id=frame)

    def time(self, stamp_ns: int):
        return self.t["builtin_interfaces/msg/Time"](
            sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
        )

    def pose(self, T: np.ndarray):
        t = self.t
        q = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_quat()
        x, y, z = (float(v) for v in np.asarray(T)[:3, 3])
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
            orientation=t["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )

    def transform(self, stamp_ns: int, parent: str, child: str, T: np.ndarray):
        t = self.t
        p = self.pose(T)
        return t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=p.position.x, y=p.position.y, z=p.position.z),
                rotation=p.orientation,
            ),
        )

    def tf(self, transforms: list):
        return self.t["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def cloud(self, stamp_ns: int, frame: str, columns: dict[str, np.ndarray]):
        """A PointCloud2 of float32 ``columns`` (name → (N,)), packed in that order."""
        t = self.t
        names = list(columns)
        n = len(next(iter(columns.values()))) if columns else 0
        data = np.empty((n, len(names)), np.float32)
        for j, name in enumerate(names):
            data[:, j] = columns[name]
        fields = [
            t["sensor_msgs/msg/PointField"](name=name, offset=4 * j, datatype=FLOAT32, count=1)
            for j, name in enumerate(names)
        ]
        step = 4 * len(names)
        return t["sensor_msgs/msg/PointCloud2"](
            header=self.header(stamp_ns, frame),
            height=1,
            width=n,
            fields=fields,
            is_bigendian=False,
            point_step=step,
            row_step=step * n,
            data=np.frombuffer(data.tobytes(), np.uint8),
            is_dense=True,
        )

    def xyz_cloud(self, stamp_ns: int, frame: str, points: np.ndarray):
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        return self.cloud(stamp_ns, frame, {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]})


def particle_poses(particles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(positions (N, 3), quaternions x, y, z, w (N, 4)) of particles (N, ≥6: x, y, z, yaw, pitch, roll)."""
    R = rotation_zyx(particles[:, 3], particles[:, 4], particles[:, 5]).reshape(-1, 3, 3)
    return particles[:, :3], Rotation.from_matrix(R).as_quat()


def figures_text(figures: dict) -> list[tuple[str, str]]:
    """The per-scan figures as diagnostic key–value pairs (values as text: that is the message's
    type); unknown values are left out."""
    out = []
    for key, value in figures.items():
        if value is None:
            continue
        out.append((key, ("true" if value else "false") if isinstance(value, bool) else f"{value:.6g}"))
    return out


class BagWriter:
    """Writes the steps of a :class:`RunSteps` into a rosbags MCAP writer (see the module docstring)."""

    def __init__(self, writer, steps: RunSteps):
        from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

        self.m = _Messages()
        self.w = writer
        self.steps = steps
        zero = QosTime(0, 0)
        latched = Qos(
            QosHistory.KEEP_LAST,
            1,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
            zero,
            zero,
            QosLiveliness.AUTOMATIC,
            zero,
            False,
        )
        self.conn = {}
        for topic, msgtype in TOPICS.items():
            if topic == TF_STATIC and steps.local_frame == MAP_FRAME:
                continue
            if topic == TRUTH and not steps.seq.has_poses:
                continue
            self.conn[topic] = writer.add_connection(
                topic, msgtype, typestore=self.m.ts, offered_qos_profiles=[latched] if topic in LATCHED else []
            )
        self.counts = {topic: 0 for topic in self.conn}

    def _write(self, topic: str, stamp_ns: int, msg) -> None:
        self.w.write(self.conn[topic], int(stamp_ns), self.m.serialize(msg, topic))
        self.counts[topic] += 1

    def write_map(self, stamp_ns: int, max_points: int) -> int:
        points, _ = self.steps.map_points(max_points)
        if TF_STATIC in self.conn:
            T = np.eye(4)
            T[:3, 3] = self.steps.origin
            self._write(TF_STATIC, stamp_ns, self.m.tf([self.m.transform(stamp_ns, MAP_FRAME, LOCAL_FRAME, T)]))
        self._write(MAP, stamp_ns, self.m.xyz_cloud(stamp_ns, self.steps.local_frame, points))
        return len(points)

    def write_step(self, s: Step, scan: np.ndarray | None) -> None:
        m, t = self.m, self.m.t
        stamp = s.stamp_ns
        cov = np.asarray(s.covariance, np.float64).reshape(36)
        self._write(
            POSE,
            stamp,
            t["geometry_msgs/msg/PoseWithCovarianceStamped"](
                header=m.header(stamp, MAP_FRAME),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=m.pose(s.pose), covariance=cov),
            ),
        )
        transforms = [m.transform(stamp, MAP_FRAME, LIDAR_FRAME, s.pose)]
        if s.truth is not None:
            transforms.append(m.transform(stamp, MAP_FRAME, TRUTH_FRAME, s.truth))
            if TRUTH in self.conn:
                self._write(
                    TRUTH,
                    stamp,
                    t["geometry_msgs/msg/PoseStamped"](header=m.header(stamp, MAP_FRAME), pose=m.pose(s.truth)),
                )
        self._write(TF, stamp, m.tf(transforms))
        pos, quat = particle_poses(s.particles)
        P, Q, Pose = t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"], t["geometry_msgs/msg/Pose"]
        poses = [
            Pose(
                position=P(x=float(a), y=float(b), z=float(c)),
                orientation=Q(x=float(qx), y=float(qy), z=float(qz), w=float(qw)),
            )
            for (a, b, c), (qx, qy, qz, qw) in zip(pos.tolist(), quat.tolist())
        ]
        self._write(PARTICLES, stamp, t["geometry_msgs/msg/PoseArray"](header=m.header(stamp, MAP_FRAME), poses=poses))
        local = pos - self.steps.origin
        self._write(
            PARTICLE_CLOUD,
            stamp,
            m.cloud(
                stamp,
                self.steps.local_frame,
                {"x": local[:, 0], "y": local[:, 1], "z": local[:, 2], "weight": s.weights},
            ),
        )
        if scan is not None:
            self._write(SCAN, stamp, m.xyz_cloud(stamp, LIDAR_FRAME, scan))
        for ev in s.events:
            self._write(
                ROSOUT,
                stamp,
                t["rcl_interfaces/msg/Log"](
                    stamp=m.time(stamp),
                    level=LOG_LEVELS[event_level(ev.kind)],
                    name="lidarloc",
                    msg=f"scan {ev.scan}: {ev.kind}" + (f": {ev.detail}" if ev.detail else ""),
                    file="",
                    function=ev.kind,
                    line=0,
                ),
            )
        KV, Status = t["diagnostic_msgs/msg/KeyValue"], t["diagnostic_msgs/msg/DiagnosticStatus"]
        localized = bool(s.figures.get("localized"))
        status = Status(
            level=0 if localized else 1,
            name="lidarloc: localizer",
            message="localized" if localized else "not localized",
            hardware_id=self.steps.name,
            values=[KV(key=k, value=v) for k, v in figures_text(s.figures)],
        )
        self._write(
            DIAGNOSTICS,
            stamp,
            t["diagnostic_msgs/msg/DiagnosticArray"](header=m.header(stamp, MAP_FRAME), status=[status]),
        )


# -------------------------------------------------------------------------------- the input
def check_input(bag) -> None:
    """Before a run with ``--write-bag --with-input``: one line unless the source is a ROS 2 bag."""
    if bag is None:
        raise LidarlocError("--with-input copies the input bag of a run on a bag; give the source as --bag")
    if Path(bag).suffix.lower() == ".bag":
        raise LidarlocError(
            f"{bag}: --with-input copies the topics of a ROS 2 bag; convert this ROS 1 bag first "
            "(rosbags-convert --src drive.bag --dst drive2) and run on that"
        )


def copy_input(writer, steps: RunSteps, taken: set[str]) -> dict[str, int]:
    """Copy the run's input bag (ROS 2) into ``writer``: every topic, messages recorded within the
    run's span (±1 s; /tf_static whole), under its own name or ``/input/NAME`` where lidarloc
    writes NAME. Returns messages copied per (output) topic."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from ..core.sequences.rosbag import bag_errors, resolve_bag_path

    bag_path = getattr(steps.seq, "path", None) if hasattr(steps.seq, "stamps_ns") else None
    if bag_path is None:
        raise LidarlocError(
            f"{steps.rec.run_dir}: --with-input copies the input bag of a run on a bag (--bag); "
            f"this run's source is {steps.name}"
        )
    lo, hi = int(steps.stamps_ns.min()) - 1_000_000_000, int(steps.stamps_ns.max()) + 1_000_000_000
    with bag_errors(Path(bag_path), "opening"):
        # the Humble definitions for an old sqlite3 bag without its own, as the bag reader does
        reader = AnyReader([resolve_bag_path(bag_path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    if not reader.is2:
        reader.close()
        # a ROS 1 message is not a ROS 2 message re-encoded (std_msgs/Header lost its seq):
        # converting it is rosbags-convert's job, done once for the whole bag
        raise LidarlocError(
            f"{bag_path}: --with-input copies the topics of a ROS 2 bag; convert this ROS 1 bag "
            "first (rosbags-convert --src drive.bag --dst drive2) and run on that"
        )
    counts: dict[str, int] = {}
    try:
        with bag_errors(Path(bag_path), "copying the input"):
            out_conn = {}
            for c in reader.connections:
                name = c.topic if c.topic not in taken else INPUT_PREFIX + c.topic
                key = (name, c.msgtype)
                if key not in out_conn:
                    qos = getattr(getattr(c, "ext", None), "offered_qos_profiles", ()) or ()
                    out_conn[key] = writer.add_connection(
                        name,
                        c.msgtype,
                        typestore=reader.typestore,
                        offered_qos_profiles=qos if not isinstance(qos, str) else (),
                    )
            for c, t, raw in reader.messages():
                if not (lo <= t <= hi) and c.topic.lstrip("/") != "tf_static":
                    continue
                name = c.topic if c.topic not in taken else INPUT_PREFIX + c.topic
                writer.write(out_conn[(name, c.msgtype)], t, raw)
                counts[name] = counts.get(name, 0) + 1
    finally:
        reader.close()
    return counts


# -------------------------------------------------------------------------------- export
def export_bag(
    run_dir,
    out,
    console: Console | None = None,
    cache_root: Path | None = None,
    with_input: bool = False,
    scans: bool = True,
    max_map_points: int = 400_000,
) -> dict:
    """Write the recorded run ``run_dir`` as a ROS 2 MCAP bag at ``out`` (see the module
    docstring); returns what was written: path, bytes, messages per topic, steps, seconds."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

    from .console import progress_bar

    console = console or Console(stderr=True)
    t0 = time.perf_counter()
    folder, single = bag_target(out)  # before the map is loaded: a bad name fails at once
    steps = RunSteps(run_dir, cache_root, console)
    writer = Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP)
    # zstd per chunk: the particles and scans are most of the bytes and compress ~2×
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    try:
        writer.open()
    except OSError as exc:
        raise LidarlocError(f"{folder}: cannot write the bag ({exc.strerror})") from None
    try:
        bag = BagWriter(writer, steps)
        map_points = bag.write_map(int(steps.stamps_ns[0]), max_map_points)
        with progress_bar() as bar:
            task = bar.add_task("writing the bag", total=steps.n)
            for i in range(steps.n):
                bag.write_step(steps.step(i), steps.scan(i) if scans else None)
                bar.update(task, completed=i + 1)
        counts = dict(bag.counts)
        if with_input:
            counts.update(copy_input(writer, steps, set(TOPICS)))
    except BaseException:
        try:
            writer.close()
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    writer.close()
    path = folder
    if single is not None:
        (folder / f"{folder.name}.mcap").replace(single)
        shutil.rmtree(folder, ignore_errors=True)
        path = single
    size = path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    result = {
        "bag": str(path),
        "bytes": size,
        "steps": steps.n,
        "messages": counts,
        "map_points": map_points,
        "seconds": time.perf_counter() - t0,
    }
    console.print(
        f"wrote {steps.n} steps of {steps.rec.run_dir} to {path} ({size / 1e6:.1f} MB, ROS 2 MCAP): "
        f"ros2 bag play {path}, or open it in Foxglove",
        highlight=False,
        soft_wrap=True,
    )
    return result
