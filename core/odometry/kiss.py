"""KISS-ICP's configuration for the RPE block, one place for the in-process odometry
(:mod:`lidarloc.core.odometry.rpe`), its child process (:mod:`lidarloc.core.odometry.worker`) and the RPE
benchmark."""

from __future__ import annotations

# KISS-ICP stops iterating when its Gauss-Newton step is shorter than this (metres and radians in
# one 6-vector norm). Its default, 1e-4, keeps refining 0.1 mm steps. Measured with
# ``lidarloc bench rpe`` (BENCHMARKS.md, "RPE"): 3e-3 cuts the registration to about half its
# time (45 % on the real drive, 51 % on the town) with the same per-scan and 10-scan errors. The
# time it frees is what lets the real-time clock keep up with 10 Hz on two cores.
KISS_CONVERGENCE = 3e-3


def kiss_config(max_range: float, min_range: float, voxel_size: float | None, convergence: float = KISS_CONVERGENCE):
    """A ``kiss_icp.config.KISSConfig`` for scans without per-point times (no deskew), on one
    thread. ``voxel_size=None``: KISS-ICP's own rule, max_range / 100."""
    from kiss_icp.config import KISSConfig

    config = KISSConfig()
    config.data.deskew = False
    config.data.max_range = float(max_range)
    config.data.min_range = float(min_range)
    # KISS-ICP's own rule when no voxel size is given: max_range / 100 (1 m for 100 m)
    config.mapping.voxel_size = float(voxel_size if voxel_size is not None else max_range / 100.0)
    config.registration.max_num_threads = 1  # the localizer's other threads need the second core
    config.registration.convergence_criterion = float(convergence)
    return config
