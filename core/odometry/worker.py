"""KISS-ICP in its own process.

KISS-ICP's Python binding holds the GIL while it registers a scan (~45 ms per KITTI scan on this
project's 2-core reference machine, ``lidarloc bench rpe``; measured: a Python thread beside it
ran at ~20 % of its normal rate).
In a thread it would stall the particle filter's Python code for that long every scan. Running it
in a child process (:mod:`lidarloc.core.worker_process`) makes the RPE block truly parallel; the
parent sends each scan (float32) and receives the 4×4 odometry pose.

:class:`KissICPProcess` mimics the two members of ``kiss_icp.kiss_icp.KissICP`` that
:class:`~lidarloc.core.odometry.rpe.RelativePoseEstimator` uses (``register_frame``, ``last_pose``) plus
``reset()`` (a fresh odometry, e.g. after a kidnap) and ``close()``.
"""

from __future__ import annotations

import numpy as np

from ..worker_process import WorkerProxy, serve
from .kiss import kiss_config


def _make_handler(config_args: tuple):
    from kiss_icp.kiss_icp import KissICP

    state = {"icp": KissICP(kiss_config(*config_args))}

    def handle(request):
        kind, payload = request
        if kind == "reset":
            state["icp"] = KissICP(kiss_config(*config_args))
            return np.eye(4)
        icp = state["icp"]
        icp.register_frame(np.asarray(payload, dtype=np.float64), np.zeros(0))
        return np.ascontiguousarray(icp.last_pose, dtype=np.float64)

    return handle


class KissICPProcess(WorkerProxy):
    def __init__(self, max_range: float = 100.0, min_range: float = 2.5, voxel_size: float | None = None):
        args = (float(max_range), float(min_range), None if voxel_size is None else float(voxel_size))
        super().__init__("lidarloc.core.odometry.worker", args, "KISS-ICP", block="RPE")
        self.last_pose = np.eye(4)

    def register_frame(self, points: np.ndarray, timestamps=None) -> None:
        pts = np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float32)
        self.last_pose = np.array(self._worker.call(("scan", pts)), dtype=np.float64)

    def reset(self) -> None:
        self.last_pose = np.array(self._worker.call(("reset", None)), dtype=np.float64)


if __name__ == "__main__":
    serve(_make_handler)
