"""The KITTI readers (core/sequences/kitti_odometry.py, kitti_raw.py): poses converted from cam0
to the LiDAR frame, real consecutive scans that agree under their poses, scan index errors."""

import numpy as np
import pytest
from helpers import Tr_KITTI, make_odometry
from lidarloc.core.errors import DataError
from lidarloc.core.geometry import pose_matrix
from lidarloc.core.sequences.base import validate_scan
from lidarloc.core.sequences.kitti_odometry import KittiOdometry
from scipy.spatial import cKDTree


def test_kitti_odometry_reader_converts_cam0_to_lidar(tmp_path):
    make_odometry(tmp_path, n_scans=3)
    seq = KittiOdometry(tmp_path, "00")
    assert len(seq) == 3 and seq.scan(1).dtype == np.float32 and seq.scan(1).shape == (500, 4)
    assert np.allclose(seq.poses[0], np.eye(4))
    cam = [pose_matrix(i * 1.0, 0.1 * i, 0, 0.01 * i, 0, 0) for i in range(3)]
    lidar = [np.linalg.inv(Tr_KITTI) @ c @ Tr_KITTI for c in cam]
    expected = np.linalg.inv(lidar[0]) @ lidar[2]
    assert np.allclose(seq.poses[2], expected, atol=1e-9)
    assert np.allclose(seq.timestamps, [0, 0.1, 0.2])


def test_kitti_raw_consecutive_scans_agree(kitti_raw_seq):
    """Consecutive real scans aligned with the OXTS poses agree on non-ground points."""
    seq = kitti_raw_seq
    medians = []
    for i in (0, 30, 60, 90):
        a, b = seq.scan(i)[:, :3].astype(float), seq.scan(i + 1)[:, :3].astype(float)
        a = a[(a[:, 2] > -1.2) & (np.linalg.norm(a, axis=1) < 40)]  # non-ground, near
        b = b[(b[:, 2] > -1.2) & (np.linalg.norm(b, axis=1) < 40)]
        rel = np.linalg.inv(seq.poses[i]) @ seq.poses[i + 1]
        b_in_a = b @ rel[:3, :3].T + rel[:3, 3]
        d, _ = cKDTree(a).query(b_in_a)
        medians.append(np.median(d))
    assert max(medians) < 0.3, medians


def test_scan_index_errors(kitti_raw_seq):
    with pytest.raises(IndexError):
        kitti_raw_seq.scan(100)
    with pytest.raises(DataError):
        validate_scan(np.zeros((0, 4), np.float32), "x.bin")
