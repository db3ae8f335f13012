"""Scan folders as sources: .pcd (the real drive, written at test time), .ply, .bin and .npy
scans, times from times.txt, ground truth from TUM; bad folders are one-line errors."""

import numpy as np
import pytest
from bagfixtures import N_SCANS
from lidarloc.core.errors import DataError
from lidarloc.core.sequences.scan_folder import ScanFolderSequence


def one_line(exc) -> str:
    text = str(exc.value)
    assert "\n" not in text, text
    return text


def test_pcd_folder_reads_the_kitti_readers_scans_times_and_poses(kitti_drive, kitti_recordings, kitti_raw_seq):
    scans, _, poses = kitti_drive
    seq = ScanFolderSequence(kitti_recordings["pcd"], gt=kitti_recordings["tum"])
    assert len(seq) == N_SCANS and seq.notes == []
    for i in (0, 13, N_SCANS - 1, 1):
        np.testing.assert_array_equal(seq.scan(i), scans[i])
    np.testing.assert_allclose(seq.timestamps, kitti_raw_seq.timestamps[:N_SCANS], rtol=0, atol=1e-9)
    np.testing.assert_allclose(seq.poses, poses, atol=1e-6)


def test_other_kinds_natural_order_and_default_times(kitti_drive, tmp_path):
    from lidarloc.core.o3d import open3d

    scans = kitti_drive[0][:3]
    o3d = open3d()
    names = ["scan_1", "scan_2", "scan_10"]  # scans 0, 1, 2; by plain string order 10 would come second
    for kind in (".bin", ".npy", ".ply"):
        d = tmp_path / kind[1:]
        d.mkdir()
        for k, name in enumerate(names):
            path = d / f"{name}{kind}"
            if kind == ".bin":
                scans[k].tofile(path)
            elif kind == ".npy":
                np.save(path, scans[k][:, :3].astype(np.float64))  # x, y, z only
            else:
                pc = o3d.t.geometry.PointCloud()
                pc.point.positions = o3d.core.Tensor(scans[k][:, :3])
                pc.point.intensity = o3d.core.Tensor(scans[k][:, 3:4])
                assert o3d.t.io.write_point_cloud(str(path), pc)
        seq = ScanFolderSequence(d)
        assert len(seq) == 3 and not seq.has_poses
        np.testing.assert_allclose(seq.timestamps, [0.0, 0.1, 0.2])
        assert len(seq.notes) == 1 and "no times.txt" in seq.notes[0]
        for i in range(3):
            got = seq.scan(i)
            np.testing.assert_array_equal(got[:, :3], scans[i][:, :3])
            if kind == ".npy":
                assert (got[:, 3] == 0).all()
            else:
                np.testing.assert_array_equal(got[:, 3], scans[i][:, 3])


def test_bad_folders_are_one_line_errors(kitti_drive, tmp_path):
    scan = kitti_drive[0][0]
    with pytest.raises(DataError) as exc:
        ScanFolderSequence(tmp_path / "missing")
    assert "not found" in one_line(exc)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError) as exc:
        ScanFolderSequence(empty)
    assert "no scans" in one_line(exc)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    scan.tofile(mixed / "0.bin")
    np.save(mixed / "1.npy", scan)
    with pytest.raises(DataError) as exc:
        ScanFolderSequence(mixed)
    assert ".bin, .npy" in one_line(exc)

    d = tmp_path / "bins"
    d.mkdir()
    for i in range(3):
        scan.tofile(d / f"{i:06d}.bin")
    (d / "times.txt").write_text("0\n0.1\n")
    with pytest.raises(DataError) as exc:
        ScanFolderSequence(d)
    assert "2 times for 3 scans" in one_line(exc)
    (d / "times.txt").write_text("0\n0.2\n0.1\n")
    with pytest.raises(DataError) as exc:
        ScanFolderSequence(d)
    assert "times must increase" in one_line(exc)
    (d / "times.txt").write_text("0\n0.1\n0.2\n")
    (d / "000001.bin").write_bytes(b"\0" * 10)
    seq = ScanFolderSequence(d)
    with pytest.raises(DataError) as exc:
        seq.scan(1)
    assert "000001.bin" in one_line(exc)

    pcd = tmp_path / "pcd"
    pcd.mkdir()
    (pcd / "0.pcd").write_text("not a point cloud\n")
    with pytest.raises(DataError) as exc:
        ScanFolderSequence(pcd).scan(0)
    assert "0.pcd" in one_line(exc) and "no points" in str(exc.value)


def test_truth_by_index_from_kitti_poses(kitti_drive, tmp_path):
    scans, _, poses = kitti_drive
    d = tmp_path / "bins"
    d.mkdir()
    for i in range(4):
        scans[i].tofile(d / f"{i:06d}.bin")
    gt = tmp_path / "poses.txt"
    gt.write_text("".join(" ".join(f"{v:.15e}" for v in T[:3].ravel()) + "\n" for T in poses[:4]))
    seq = ScanFolderSequence(d, gt=gt)
    np.testing.assert_allclose(seq.poses, poses[:4], atol=1e-6)
    gt.write_text("".join(" ".join(f"{v:.15e}" for v in T[:3].ravel()) + "\n" for T in poses[:3]))
    with pytest.raises(DataError) as exc:
        ScanFolderSequence(d, gt=gt)
    assert "3 poses for 4 scans" in one_line(exc)
