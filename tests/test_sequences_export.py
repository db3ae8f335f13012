"""Export to a KITTI odometry tree (core/sequences/export.py): a round trip through the KITTI
reader gives the same scans, poses and timestamps, and an interrupted export leaves nothing."""

import numpy as np
import pytest
from lidarloc.core.errors import DataError
from lidarloc.core.sequences.base import Limited
from lidarloc.core.sequences.export import export_kitti_odometry
from lidarloc.core.sequences.kitti_odometry import KittiOdometry
from lidarloc.core.sim.town import TownSequence


@pytest.fixture(scope="module")
def small_town() -> TownSequence:
    return TownSequence(seed=3, extent_m=150.0, n_scans=40)


def test_export_round_trip_through_kitti_reader(small_town, tmp_path):
    seq = Limited(small_town, 5)
    calls = []
    out = export_kitti_odometry(seq, tmp_path, "00", progress=lambda i, n: calls.append((i, n)))
    assert out == tmp_path / "sequences" / "00"
    assert calls[-1] == (5, 5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses", "sequences"]  # no temp dir left
    back = KittiOdometry(tmp_path, "00")
    assert len(back) == 5
    for i in range(5):
        np.testing.assert_array_equal(back.scan(i), seq.scan(i))
    np.testing.assert_allclose(back.poses, seq.poses, atol=1e-6)
    np.testing.assert_allclose(back.timestamps, seq.timestamps, atol=1e-6)
    with pytest.raises(DataError, match="already exists"):
        export_kitti_odometry(seq, tmp_path, "00")


def test_interrupted_export_leaves_nothing(small_town, tmp_path):
    def interrupt(i, n):
        if i == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        export_kitti_odometry(Limited(small_town, 6), tmp_path, "01", progress=interrupt)
    assert list(tmp_path.iterdir()) == []
