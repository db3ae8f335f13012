"""The built-in generated town (the default source): ``--town-seed``, or laid along a KITTI
trajectory with ``--trajectory`` and ``--calib``."""

from __future__ import annotations

from pathlib import Path

from ...errors import DataError
from ..registry import Option, Source, as_path


def _open(spec, cfg, progress=None):
    if (spec.trajectory is None) != (spec.calib is None):
        raise DataError("--trajectory and --calib go together (the calib's Tr converts cam0 poses to LiDAR)")
    from ...sim.town import TownSequence

    return TownSequence.from_config(
        cfg.town, seed=spec.town_seed, trajectory=as_path(spec.trajectory), calib=as_path(spec.calib)
    )


def _describe(spec) -> str:
    along = f" along {spec.trajectory}" if spec.trajectory else ""
    return f"built-in town (seed {spec.town_seed}){along}"


SOURCE = Source(
    name="town",
    title="the built-in generated town, its drive simulated scan by scan",
    options=(
        Option("town_seed", int, "Seed of the built-in generated town.", default=0, min=0),
        Option("trajectory", Path, "Lay the town along this KITTI poses file (cam0 poses)."),
        Option("calib", Path, "KITTI calib file with the Tr line for --trajectory."),
    ),
    open=_open,
    describe=_describe,
    default=True,
)
