"""A run's trajectory errors as evo computes them: APE and RPE of ``trajectory_tum.txt`` against
``groundtruth_tum.txt``, through evo's own functions, so that the figures in ``summary.json`` are
the ones ``evo_ape tum groundtruth_tum.txt trajectory_tum.txt`` and ``evo_rpe tum …`` print.

The settings are evo's command-line defaults, chosen on purpose: a user who checks the summary
with evo gets the same numbers without options.

- Association by time (``evo.core.sync.associate_trajectories``, nearest stamp within 10 ms).
- No alignment: both files are in the map's frame, and an alignment would hide exactly the
  error a localizer must not have (a wrong place in the map).
- The translation part of the pose error; RPE between consecutive poses (delta 1 frame).

Both are over every scan of the file, the ones before the filter first localized included (a
global start is hundreds of metres off until then); the summary's ``rmse_after_localized_m`` and
the paper's metrics A–E stand beside them for the part after localization.
"""

from __future__ import annotations

import logging
from pathlib import Path

#: evo's ``--t_max_diff`` default (s): a pose of one file and of the other belong together when
#: their stamps are this close
MAX_DIFF_S = 0.01


def trajectory_errors(trajectory_tum: Path, groundtruth_tum: Path) -> dict:
    """``{"ape_rmse_m", "rpe_rmse_m"}`` of the estimate against the truth (metres), each None where
    evo cannot compute it (fewer than two associated poses, an empty or unreadable file)."""
    from evo.core import metrics, sync
    from evo.main_ape import ape
    from evo.main_rpe import rpe
    from evo.tools import file_interface

    logging.getLogger("evo").setLevel(logging.WARNING)  # evo logs its result tables at INFO
    out: dict = {"ape_rmse_m": None, "rpe_rmse_m": None}
    try:
        ref = file_interface.read_tum_trajectory_file(str(groundtruth_tum))
        est = file_interface.read_tum_trajectory_file(str(trajectory_tum))
        ref, est = sync.associate_trajectories(ref, est, max_diff=MAX_DIFF_S)
    except Exception:  # noqa: BLE001 - evo raises its own error types for empty or foreign files
        return out
    relation = metrics.PoseRelation.translation_part
    if ref.num_poses >= 1:
        out["ape_rmse_m"] = float(ape(ref, est, relation).stats["rmse"])
    if ref.num_poses >= 2:
        out["rpe_rmse_m"] = float(rpe(ref, est, relation, delta=1, delta_unit=metrics.Unit.frames).stats["rmse"])
    return out
