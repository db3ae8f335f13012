"""Write any :class:`~.base.Sequence` in the KITTI odometry layout, so tools that read KITTI
(pykitti, KISS-ICP, this project's own reader) can use the simulated drives:

    out_dir/sequences/SS/velodyne/000000.bin …   float32 x, y, z, intensity records
    out_dir/sequences/SS/calib.txt               P0: P1: P2: P3: Tr: (pykitti needs all five)
    out_dir/sequences/SS/times.txt               seconds since the first scan
    out_dir/poses/SS.txt                         cam0 poses Tr · P_lidar · inv(Tr), if known

Everything is written into a hidden temporary directory inside ``out_dir`` and renamed into place
at the end, so an interrupted export leaves no half-written sequence behind.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import DataError, LidarlocError
from .base import Sequence
from .kitti_io import lidar_to_cam0_poses, read_tr, write_pose_lines, write_velodyne_bin

# KITTI odometry sequences 04–10 (recorded 2011-09-30) share this calibration; the simulated
# sensor has no cameras, but pykitti reads all four projections, and Tr (velodyne → rectified
# cam0) converts between the LiDAR poses and the cam0 poses KITTI's ground truth is given in.
KITTI_CALIB_LINES = (
    "P0: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 0.000000000000e+00 0.000000000000e+00 "
    "7.070912000000e+02 1.831104000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 0.000000000000e+00",
    "P1: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 -3.798145000000e+02 0.000000000000e+00 "
    "7.070912000000e+02 1.831104000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 0.000000000000e+00",
    "P2: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 4.688783000000e+01 0.000000000000e+00 "
    "7.070912000000e+02 1.831104000000e+02 1.178601000000e-01 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 6.203223000000e-03",
    "P3: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 -3.334597000000e+02 0.000000000000e+00 "
    "7.070912000000e+02 1.831104000000e+02 1.930130000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 3.318498000000e-03",
)
KITTI_TR_LINE = (
    "Tr: -1.857739385241e-03 -9.999659513510e-01 -8.039975204516e-03 -4.784029760483e-03 "
    "-6.481465826011e-03 8.051860151134e-03 -9.999466081774e-01 -7.337429464231e-02 "
    "9.999773098287e-01 -1.805528627661e-03 -6.496203536139e-03 -3.339968064433e-01"
)


def _tr_line(seq: Sequence) -> str:
    """The sequence's own Tr when it has one (a KITTI sequence being re-exported), else KITTI's."""
    Tr = getattr(seq, "Tr", None)
    if Tr is None:
        return KITTI_TR_LINE
    return "Tr: " + " ".join(f"{v:.12e}" for v in np.asarray(Tr, float)[:3, :4].reshape(-1))


def export_kitti_odometry(
    seq: Sequence,
    out_dir: str | os.PathLike,
    sequence: str = "00",
    progress: Callable[[int, int], None] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``seq`` as KITTI odometry sequence ``sequence`` under ``out_dir``; returns the
    sequence directory. ``progress(done, total)`` is called after each scan. An existing
    sequence of that id is replaced only with ``overwrite=True``."""
    out_dir = Path(out_dir)
    sequence = str(sequence)
    if not sequence or sequence in (".", "..") or "/" in sequence or os.sep in sequence:
        raise LidarlocError(f"invalid sequence id {sequence!r}: a single directory name like 00")
    final_seq = out_dir / "sequences" / sequence
    final_poses = out_dir / "poses" / f"{sequence}.txt"
    if not overwrite and (final_seq.exists() or final_poses.exists()):
        raise DataError(f"{final_seq}: sequence already exists (use --overwrite, or another --sequence-id)")
    n = len(seq)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".export-{sequence}-", dir=out_dir))
    except OSError as exc:
        raise LidarlocError(f"{out_dir}: cannot write there ({exc.strerror})") from None
    try:
        seq_dir = tmp / "sequences" / sequence
        velodyne = seq_dir / "velodyne"
        velodyne.mkdir(parents=True)
        tr_line = _tr_line(seq)
        (seq_dir / "calib.txt").write_text("\n".join(KITTI_CALIB_LINES + (tr_line,)) + "\n")
        # Convert poses with Tr exactly as a reader will parse it back from calib.txt.
        Tr = read_tr(seq_dir / "calib.txt")
        times = np.asarray(seq.timestamps, dtype=np.float64)
        np.savetxt(seq_dir / "times.txt", times, fmt="%.9e")
        for i in range(n):
            write_velodyne_bin(velodyne / f"{i:06d}.bin", seq.scan(i))
            if progress is not None:
                progress(i + 1, n)
        poses = seq.poses
        if poses is not None:
            (tmp / "poses").mkdir()
            write_pose_lines(tmp / "poses" / f"{sequence}.txt", lidar_to_cam0_poses(np.asarray(poses), Tr))

        (out_dir / "sequences").mkdir(exist_ok=True)
        if overwrite:
            shutil.rmtree(final_seq, ignore_errors=True)
            final_poses.unlink(missing_ok=True)
        os.replace(seq_dir, final_seq)
        if poses is not None:
            (out_dir / "poses").mkdir(exist_ok=True)
            os.replace(tmp / "poses" / f"{sequence}.txt", final_poses)
    except OSError as exc:
        raise LidarlocError(f"{out_dir}: export failed ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final_seq
