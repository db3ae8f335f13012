"""``lidarloc export RUN --foxglove OUT.mcap``: a recorded run in Foxglove's own schemas (written
with ``foxglove-sdk``, protobuf-encoded, each schema inside the file), and beside it
``OUT.layout.json``, the layout that opens it ready to read (:mod:`.foxglove_layout`). Stamps
and frames as in the ROS 2 bag (:mod:`.run_steps`); each message's log time is its scan's stamp.

=========================  ==========================  ===================================================
topic                      schema                      what
=========================  ==========================  ===================================================
/lidarloc/pose             foxglove.PoseInFrame        the estimate (map)
/lidarloc/truth            foxglove.PoseInFrame        the ground truth (sources that have it)
/tf                        foxglove.FrameTransforms    map → lidar, map → lidar_truth (map → map_local)
/lidarloc/particles        foxglove.PosesInFrame       every particle's pose
/lidarloc/particle_cloud   foxglove.PointCloud         the particles as points: x, y, z, weight
/lidarloc/scan             foxglove.PointCloud         the scan as the filter weighed it (lidar)
/lidarloc/map              foxglove.PointCloud         the prior map, once, at the first stamp
/lidarloc/scene            foxglove.SceneUpdate        the 2σ ellipse; the last S2M match: its search box,
                                                       the matched pose, accepted or why not
/lidarloc/log              foxglove.Log                events: localized, loss, S2M results, …
/lidarloc/figures          JSON (schema inside)        per scan: std, N_eff share, error, latencies, …
=========================  ==========================  ===================================================
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from scipy.spatial.transform import Rotation

from ..core.errors import LidarlocError
from .foxglove_channels import FIGURES, LOG, MAP, PARTICLE_CLOUD, PARTICLES, POSE, SCAN, SCENE, TF, TRUTH
from .run_steps import LIDAR_FRAME, LOCAL_FRAME, MAP_FRAME, TRUTH_FRAME, RunSteps, Step, event_level

LAYOUT_SUFFIX = ".layout.json"

#: the figures channel's JSON schema: numbers a plot reads (a figure unknown at a scan is left out)
FIGURES_SCHEMA = {
    "title": "lidarloc.Figures",
    "type": "object",
    "properties": {
        "scan": {"type": "integer", "description": "source scan index"},
        "std_m": {"type": "number", "description": "position std, the larger of x and y (m)"},
        "std_x_m": {"type": "number"},
        "std_y_m": {"type": "number"},
        "std_z_m": {"type": "number"},
        "n_eff": {"type": "number", "description": "effective sample size"},
        "n_eff_share": {"type": "number", "description": "N_eff / particles"},
        "particles": {"type": "integer"},
        "localized": {"type": "boolean", "description": "the localization rule holds"},
        "error_m": {"type": "number", "description": "3D distance of the estimate to the truth (m)"},
        "pf_ms": {"type": "number"},
        "rpe_ms": {"type": "number"},
        "s2m_ms": {"type": "number"},
    },
}
ORANGE = (1.0, 0.62, 0.1, 1.0)
GREEN = (0.3, 0.85, 0.4, 1.0)
RED = (0.95, 0.3, 0.3, 1.0)


def foxglove_target(out) -> tuple[Path, Path]:
    """(the .mcap file, its layout file) for ``out``; one-line errors for another suffix or an
    unwritable place. An existing file is replaced (the export is a copy of the recording)."""
    out = Path(out).expanduser()
    if out.suffix.lower() != ".mcap":
        raise LidarlocError(f"{out}: the Foxglove export is an MCAP file: name it NAME.mcap")
    if out.is_dir():
        raise LidarlocError(f"{out}: is a folder; name the MCAP file to write")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LidarlocError(f"{out.parent}: cannot create the folder ({exc.strerror})") from None
    return out, out.with_name(out.stem + LAYOUT_SUFFIX)


class FoxgloveWriter:
    """Logs the steps of a :class:`RunSteps` to Foxglove channels of one SDK context (an MCAP
    file's, or a live server's)."""

    def __init__(self, context, steps: RunSteps):
        import foxglove
        import foxglove.messages as messages
        from foxglove import channels as ch

        self.M = messages
        self.steps = steps
        c = {"context": context}
        self.ch = {
            POSE: ch.PoseInFrameChannel(POSE, **c),
            TF: ch.FrameTransformsChannel(TF, **c),
            PARTICLES: ch.PosesInFrameChannel(PARTICLES, **c),
            PARTICLE_CLOUD: ch.PointCloudChannel(PARTICLE_CLOUD, **c),
            SCAN: ch.PointCloudChannel(SCAN, **c),
            MAP: ch.PointCloudChannel(MAP, **c),
            SCENE: ch.SceneUpdateChannel(SCENE, **c),
            LOG: ch.LogChannel(LOG, **c),
            FIGURES: foxglove.Channel(FIGURES, schema=FIGURES_SCHEMA, message_encoding="json", **c),
        }
        if steps.seq.has_poses:
            self.ch[TRUTH] = ch.PoseInFrameChannel(TRUTH, **c)
        self.counts = {topic: 0 for topic in self.ch}

    def _log(self, topic: str, msg, stamp_ns: int) -> None:
        self.ch[topic].log(msg, log_time=int(stamp_ns))
        self.counts[topic] += 1

    # ---------------------------------------------------------------- message parts
    def ts(self, stamp_ns: int):
        return self.M.Timestamp(sec=int(stamp_ns // 1_000_000_000), nsec=int(stamp_ns % 1_000_000_000))

    def _parts(self, T: np.ndarray):
        """(Vector3, Quaternion) of a 4×4 pose (the SDK's messages are built whole, not read back)."""
        M = self.M
        q = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_quat()
        x, y, z = (float(v) for v in np.asarray(T)[:3, 3])
        return M.Vector3(x=x, y=y, z=z), M.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))

    def pose(self, T: np.ndarray):
        position, orientation = self._parts(T)
        return self.M.Pose(position=position, orientation=orientation)

    def transform(self, stamp_ns: int, parent: str, child: str, T: np.ndarray):
        translation, rotation = self._parts(T)
        return self.M.FrameTransform(
            timestamp=self.ts(stamp_ns),
            parent_frame_id=parent,
            child_frame_id=child,
            translation=translation,
            rotation=rotation,
        )

    def cloud(self, stamp_ns: int, frame: str, columns: dict[str, np.ndarray]):
        M = self.M
        names = list(columns)
        n = len(next(iter(columns.values())))
        data = np.empty((n, len(names)), np.float32)
        for j, name in enumerate(names):
            data[:, j] = columns[name]
        fields = [
            M.PackedElementField(name=name, offset=4 * j, type=M.PackedElementFieldNumericType.Float32)
            for j, name in enumerate(names)
        ]
        return M.PointCloud(
            timestamp=self.ts(stamp_ns),
            frame_id=frame,
            pose=self.pose(np.eye(4)),
            point_stride=4 * len(names),
            fields=fields,
            data=data.tobytes(),
        )

    def color(self, rgba):
        r, g, b, a = rgba
        return self.M.Color(r=r, g=g, b=b, a=a)

    def loop(self, points_xyz: np.ndarray, rgba, thickness: float = 0.15):
        M = self.M
        return M.LinePrimitive(
            type=M.LinePrimitiveLineType.LineLoop,
            pose=self.pose(np.eye(4)),
            thickness=thickness,
            points=[M.Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in points_xyz],
            color=self.color(rgba),
        )

    # ---------------------------------------------------------------- what is logged
    def write_map(self, stamp_ns: int, max_points: int) -> int:
        points, _ = self.steps.map_points(max_points)
        self._log(
            MAP,
            self.cloud(stamp_ns, self.steps.local_frame, {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}),
            stamp_ns,
        )
        return len(points)

    def write_step(self, s: Step, scan: np.ndarray | None) -> None:
        M, stamp = self.M, s.stamp_ns
        self._log(POSE, M.PoseInFrame(timestamp=self.ts(stamp), frame_id=MAP_FRAME, pose=self.pose(s.pose)), stamp)
        transforms = [self.transform(stamp, MAP_FRAME, LIDAR_FRAME, s.pose)]
        if s.truth is not None:
            transforms.append(self.transform(stamp, MAP_FRAME, TRUTH_FRAME, s.truth))
            if TRUTH in self.ch:
                self._log(
                    TRUTH, M.PoseInFrame(timestamp=self.ts(stamp), frame_id=MAP_FRAME, pose=self.pose(s.truth)), stamp
                )
        if self.steps.local_frame != MAP_FRAME:
            T = np.eye(4)
            T[:3, 3] = self.steps.origin
            transforms.append(self.transform(stamp, MAP_FRAME, LOCAL_FRAME, T))
        self._log(TF, M.FrameTransforms(transforms=transforms), stamp)
        from .export_bag import particle_poses

        pos, quat = particle_poses(s.particles)
        poses = [
            M.Pose(position=M.Vector3(x=a, y=b, z=c), orientation=M.Quaternion(x=qx, y=qy, z=qz, w=qw))
            for (a, b, c), (qx, qy, qz, qw) in zip(pos.tolist(), quat.tolist())
        ]
        self._log(PARTICLES, M.PosesInFrame(timestamp=self.ts(stamp), frame_id=MAP_FRAME, poses=poses), stamp)
        local = pos - self.steps.origin
        self._log(
            PARTICLE_CLOUD,
            self.cloud(
                stamp,
                self.steps.local_frame,
                {"x": local[:, 0], "y": local[:, 1], "z": local[:, 2], "weight": s.weights},
            ),
            stamp,
        )
        if scan is not None:
            self._log(SCAN, self.cloud(stamp, LIDAR_FRAME, {"x": scan[:, 0], "y": scan[:, 1], "z": scan[:, 2]}), stamp)
        self._log(SCENE, M.SceneUpdate(entities=self.entities(s)), stamp)
        levels = {"info": M.LogLevel.Info, "warning": M.LogLevel.Warning, "error": M.LogLevel.Error}
        for ev in s.events:
            self._log(
                LOG,
                M.Log(
                    timestamp=self.ts(stamp),
                    level=levels[event_level(ev.kind)],
                    name="lidarloc",
                    message=f"scan {ev.scan}: {ev.kind}" + (f": {ev.detail}" if ev.detail else ""),
                    file=ev.kind,
                ),
                stamp,
            )
        figures = {"scan": s.scan, **{k: v for k, v in s.figures.items() if v is not None}}
        self._log(FIGURES, figures, stamp)

    def entities(self, s: Step) -> list:
        """The step's scene: the 2σ x-y ellipse at the estimate and, when a match landed at this
        step, the S2M search box and its matched pose (kept until the next match replaces them)."""
        M, stamp = self.M, s.stamp_ns
        a, b, angle = s.ellipse_xy
        out = []
        if all(math.isfinite(v) for v in (a, b, angle)):
            t = np.linspace(0, 2 * np.pi, 48, endpoint=False)
            c, sn = math.cos(angle), math.sin(angle)
            ex, ey = a * np.cos(t), b * np.sin(t)
            pts = np.c_[s.pose[0, 3] + c * ex - sn * ey, s.pose[1, 3] + sn * ex + c * ey, np.full(len(t), s.pose[2, 3])]
            out.append(
                M.SceneEntity(
                    timestamp=self.ts(stamp), frame_id=MAP_FRAME, id="ellipse_2sigma", lines=[self.loop(pts, ORANGE)]
                )
            )
        v = s.s2m
        if v is not None:
            o = self.steps.origin
            x0, y0, x1, y1 = (float(q) for q in v.region)
            z = float(v.pose[2, 3] + o[2])
            box = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]) + [o[0], o[1], 0.0]
            colour = GREEN if v.accepted else RED
            matched = self.steps.in_map(v.pose)
            verdict = "accepted" if v.accepted else f"rejected: {v.reason}"
            text_pose = matched.copy()
            text_pose[2, 3] += 4.0
            out.append(
                M.SceneEntity(
                    timestamp=self.ts(stamp),
                    frame_id=MAP_FRAME,
                    id="s2m",
                    lines=[self.loop(box, colour, 0.3)],
                    arrows=[
                        M.ArrowPrimitive(
                            pose=self.pose(matched),
                            shaft_length=4.0,
                            shaft_diameter=0.4,
                            head_length=1.5,
                            head_diameter=1.0,
                            color=self.color(colour),
                        )
                    ],
                    texts=[
                        M.TextPrimitive(
                            pose=self.pose(text_pose),
                            billboard=True,
                            font_size=14,
                            scale_invariant=True,
                            color=self.color(colour),
                            text=f"S2M {v.mode or 'match'} of scan {v.started_at}: {verdict}",
                        )
                    ],
                )
            )
        return out


def export_foxglove(
    run_dir,
    out,
    console: Console | None = None,
    cache_root: Path | None = None,
    scans: bool = True,
    max_map_points: int = 400_000,
) -> dict:
    """Write the recorded run ``run_dir`` as a Foxglove MCAP file and its layout (see the module
    docstring); returns what was written."""
    import foxglove

    from .console import progress_bar
    from .foxglove_layout import layout_json

    console = console or Console(stderr=True)
    t0 = time.perf_counter()
    path, layout_path = foxglove_target(out)
    steps = RunSteps(run_dir, cache_root, console)
    context = foxglove.Context()
    tmp = path.with_name(f".{path.name}.writing")
    try:
        mcap = foxglove.open_mcap(tmp, allow_overwrite=True, context=context)
    except Exception as exc:  # noqa: BLE001 - the SDK reports I/O failures as its own error type
        raise LidarlocError(f"{path}: cannot write ({exc})") from None
    try:
        fw = FoxgloveWriter(context, steps)
        map_points = fw.write_map(int(steps.stamps_ns[0]), max_map_points)
        with progress_bar() as bar:
            task = bar.add_task("writing the Foxglove file", total=steps.n)
            for i in range(steps.n):
                fw.write_step(steps.step(i), steps.scan(i) if scans else None)
                bar.update(task, completed=i + 1)
        mcap.close()
        tmp.replace(path)
        layout_path.write_text(layout_json(), encoding="utf-8")
    except OSError as exc:
        raise LidarlocError(f"{path}: cannot write ({exc.strerror or exc})") from None
    finally:
        tmp.unlink(missing_ok=True)
    result = {
        "mcap": str(path),
        "layout": str(layout_path),
        "bytes": path.stat().st_size,
        "steps": steps.n,
        "messages": dict(fw.counts),
        "map_points": map_points,
        "seconds": time.perf_counter() - t0,
    }
    console.print(
        f"wrote {steps.n} steps of {steps.rec.run_dir} to {path} ({result['bytes'] / 1e6:.1f} MB) and "
        f"its layout {layout_path}: open the file in Foxglove, then Layouts → Import from file",
        highlight=False,
        soft_wrap=True,
    )
    return result
