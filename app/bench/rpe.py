"""``lidarloc bench rpe``: KISS-ICP's registration time and accuracy under several convergence
settings.

Each setting registers the first ``scans`` scans of a sequence in-process (one thread, as the
localizer runs it) and is compared with the sequence's ground truth:

* ``ms_median``, ``ms_max`` (at scan ``ms_max_scan``): one ``register_frame`` call (crop,
  voxelisation, ICP, local-map update);
* ``step_error_cm``: translation error of each scan-to-scan relative pose (median, p95);
* ``drift_10_pct``: median translation error over 10-scan windows, relative to their length;
* ``end_drift_pct``: end-point error relative to the distance driven.
"""

from __future__ import annotations

import time

import numpy as np

from ...core.config import Config
from ...core.errors import LidarlocError
from ...core.geometry import inv_pose
from ...core.odometry.kiss import KISS_CONVERGENCE, kiss_config
from ...core.sequences.factory import SourceSpec
from .common import open_source, pose_error

DEFAULT_SCANS = 300  # registered when the source options do not say --scans
MIN_SCANS = 11  # the 10-scan drift windows need at least one window


def measure(scans: list[np.ndarray], G: np.ndarray, convergence: float) -> dict:
    from kiss_icp.kiss_icp import KissICP

    icp = KissICP(kiss_config(100.0, 2.5, None, convergence))
    ms, poses = [], []
    for scan in scans:
        t0 = time.perf_counter()
        icp.register_frame(scan, np.zeros(0))
        ms.append((time.perf_counter() - t0) * 1e3)
        poses.append(icp.last_pose.copy())
    n = len(scans)

    def rel_error(i: int, j: int) -> tuple[float, float]:
        """Translation error of the relative pose from scan i to j, and the true distance."""
        truth = inv_pose(G[i]) @ G[j]
        return pose_error(inv_pose(poses[i]) @ poses[j], truth)[0], float(np.linalg.norm(truth[:3, 3]))

    step = [rel_error(i, i + 1)[0] for i in range(n - 1)]
    windows = [rel_error(i, i + 10) for i in range(n - 10)]
    path = float(sum(np.linalg.norm(G[i + 1][:3, 3] - G[i][:3, 3]) for i in range(n - 1)))
    end_err, _ = rel_error(0, n - 1)
    return {
        "convergence": convergence,
        "ms_median": float(np.median(ms)),
        "ms_max": float(np.max(ms)),
        "ms_max_scan": int(np.argmax(ms)),
        "step_error_cm_median": 100 * float(np.median(step)),
        "step_error_cm_p95": 100 * float(np.percentile(step, 95)),
        "drift_10_pct": 100 * float(np.median([e / max(d, 1e-6) for e, d in windows])) if windows else None,
        "end_drift_pct": 100 * end_err / max(path, 1e-9),
        "path_m": path,
    }


def run(spec: SourceSpec, cfg: Config, convergences: tuple[float, ...] = (1e-4, KISS_CONVERGENCE)) -> dict:
    """Register the first ``spec.scans`` scans (``DEFAULT_SCANS`` if not given) once per
    convergence setting."""
    if spec.scans is not None and spec.scans < MIN_SCANS:
        raise LidarlocError(f"bench rpe needs --scans ≥ {MIN_SCANS} (its drift is measured over 10-scan windows)")
    seq = open_source(spec, cfg, "rpe", need_poses=True)
    n = min(spec.scans or DEFAULT_SCANS, len(seq))
    points = [np.asarray(seq.scan(k)[:, :3], dtype=np.float64) for k in range(n)]
    return {
        "source": seq.name,
        "scans": n,
        "localizer_convergence": KISS_CONVERGENCE,
        "settings": [measure(points, seq.poses[:n], float(c)) for c in convergences],
    }
