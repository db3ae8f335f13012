"""Ground-truth files (TUM, KITTI), matching them to scan times, and the LiDAR extrinsic."""

import numpy as np
import pytest
from bagfixtures import write_tum
from lidarloc.core.errors import DataError
from lidarloc.core.geometry import euler_zyx, pose_matrix
from lidarloc.core.sequences.extrinsic import from_tf_static, read_extrinsic
from lidarloc.core.sequences.groundtruth import Truth, load_truth, match, read_kitti, truth_for_scans

T0 = 1317042651.175862  # Unix seconds, as a recorder's clock gives them


def straight_drive(n=11, dt=0.1):
    """A car at 10 m/s turning at 0.5 rad/s, sampled every ``dt``."""
    times = T0 + dt * np.arange(n)
    poses = np.array([pose_matrix(10 * dt * k, 0.2 * k, 0.01 * k, 0.5 * dt * k, 0.01, -0.02) for k in range(n)])
    return times, poses


def one_line(exc) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_tum_round_trip_and_format_detection(tmp_path):
    times, poses = straight_drive()
    truth = load_truth(write_tum(tmp_path / "gt.txt", times, poses))
    assert truth.times is not None
    np.testing.assert_allclose(truth.times, times, rtol=0, atol=1e-6)
    np.testing.assert_allclose(truth.poses, poses, atol=1e-9)


def test_kitti_poses_with_and_without_times(tmp_path):
    _, poses = straight_drive(5)
    path = tmp_path / "poses.txt"
    path.write_text("".join(" ".join(f"{v:.12e}" for v in T[:3].ravel()) + "\n" for T in poses))
    (tmp_path / "times.txt").write_text("".join(f"{0.1 * k:.3f}\n" for k in range(5)))
    by_index = load_truth(path)
    assert by_index.times is None
    np.testing.assert_allclose(by_index.poses, poses, atol=1e-9)
    timed = load_truth(path, times=tmp_path / "times.txt")
    np.testing.assert_allclose(timed.times, 0.1 * np.arange(5))
    # one pose per scan, matched by index
    got, has = match(np.arange(5) * 0.1, by_index)
    assert has.all()
    np.testing.assert_allclose(got, poses, atol=1e-9)
    with pytest.raises(DataError) as exc:
        match(np.arange(7) * 0.1, by_index)
    assert "5 poses for 7 scans" in one_line(exc)
    (tmp_path / "short_times.txt").write_text("0\n0.1\n")
    with pytest.raises(DataError) as exc:
        read_kitti(path, tmp_path / "short_times.txt")
    assert "5 poses but 2 times" in one_line(exc)


def test_nearest_within_20ms_else_interpolated_else_none():
    times, poses = straight_drive()
    truth = Truth(poses=poses, times=times, source="gt.tum")
    scans = np.array(
        [
            times[2] + 0.015,  # within 20 ms of sample 2: taken as is
            times[4] + 0.05,  # halfway between 4 and 5: interpolated
            times[0] - 0.5,  # before the truth
            times[-1] + 0.5,
        ]
    )  # after it
    got, has = match(scans, truth)
    assert has.tolist() == [True, True, False, False]
    np.testing.assert_array_equal(got[0], poses[2])
    np.testing.assert_allclose(got[1][:3, 3], (poses[4][:3, 3] + poses[5][:3, 3]) / 2, atol=1e-12)
    yaw4, yaw5 = euler_zyx(poses[4][:3, :3])[0], euler_zyx(poses[5][:3, :3])[0]
    assert euler_zyx(got[1][:3, :3])[0] == pytest.approx((yaw4 + yaw5) / 2, abs=1e-9)
    np.testing.assert_allclose(got[1][:3, :3] @ got[1][:3, :3].T, np.eye(3), atol=1e-12)
    assert np.isnan(got[2]).all()


def test_truth_that_does_not_overlap_is_a_clear_error():
    times, poses = straight_drive()
    truth = Truth(poses=poses, times=times - T0, source="gt.tum")  # relative seconds
    with pytest.raises(DataError) as exc:
        match(times, truth)  # scans in Unix time
    text = one_line(exc)
    assert text.startswith("gt.tum") and "do not overlap" in text


def test_truth_moves_to_the_lidar_and_scans_outside_are_left_out():
    times, base = straight_drive()
    T_base_lidar = pose_matrix(1.2, 0.1, 1.73, 0.02, 0.0, 0.01)
    scans = np.r_[times[0] - 0.3, times[0] - 0.2, times, times[-1] + 0.4]
    m = truth_for_scans(scans, Truth(poses=base, times=times, source="gt.tum"), T_base_lidar)
    np.testing.assert_array_equal(m.keep, np.arange(2, 2 + len(times)))
    np.testing.assert_allclose(m.poses, base @ T_base_lidar, atol=1e-12)
    assert len(m.notes) == 1 and "3 of 14 scans" in m.notes[0] and "2 at the start, 1 at the end" in m.notes[0]


@pytest.mark.parametrize(
    "content, words",
    [
        ("1 2 3 4 5\n", ["5 numbers per line", "TUM", "KITTI"]),
        ("0 0 0 0 0 0 0 1\n1 2 x 4 5 6 7 8\n", [":2:", "not a line of numbers"]),
        ("0 0 0 0 0 0 0 1\n1 2 3 4 5 6 7\n", [":2:", "expected 8 numbers"]),
        ("0 1 2 3 0 0 0 0\n", ["quaternion is zero"]),
        ("# only a comment\n", ["no poses"]),
    ],
)
def test_bad_truth_files_are_one_line_errors(tmp_path, content, words):
    path = tmp_path / "gt.txt"
    path.write_text(content)
    with pytest.raises(DataError) as exc:
        load_truth(path)
    text = one_line(exc)
    assert text.startswith(str(path))
    for w in words:
        assert w in text


def test_missing_truth_file(tmp_path):
    with pytest.raises(DataError) as exc:
        load_truth(tmp_path / "nope.tum")
    assert "not found" in one_line(exc)


def test_tum_truth_of_the_real_drive_matches_its_poses(kitti_drive, tmp_path):
    """The KITTI drive's LiDAR poses written as TUM at the scans' times come back equal."""
    _, stamps_ns, poses = kitti_drive
    truth = load_truth(write_tum(tmp_path / "gt.tum", stamps_ns, poses))
    got, has = match(stamps_ns / 1e9, truth)
    assert has.all()
    np.testing.assert_allclose(got, poses, atol=1e-6)


# ------------------------------------------------------------------------------------- extrinsic
def test_extrinsic_files(tmp_path):
    T = pose_matrix(0.8, -0.1, 1.7, 0.03, -0.01, 0.02)
    full = tmp_path / "ext4.txt"
    full.write_text("# base_link <- velodyne\n" + "\n".join(" ".join(f"{v:.15g}" for v in row) for row in T) + "\n")
    np.testing.assert_allclose(read_extrinsic(full), T, atol=1e-14)
    top = tmp_path / "ext3.txt"
    top.write_text(",".join(f"{v:.15g}" for v in T[:3].ravel()))
    np.testing.assert_allclose(read_extrinsic(top), T, atol=1e-14)
    assert (read_extrinsic("identity") == np.eye(4)).all()
    scaled = tmp_path / "scaled.txt"
    scaled.write_text(" ".join(f"{v:g}" for v in (2 * np.eye(4)).ravel()))
    with pytest.raises(DataError) as exc:
        read_extrinsic(scaled)
    assert "not a rotation" in one_line(exc) or "last row" in str(exc.value)
    short = tmp_path / "short.txt"
    short.write_text("1 0 0 0 1 0")
    with pytest.raises(DataError) as exc:
        read_extrinsic(short)
    assert "12 or 16 numbers" in one_line(exc)


def test_tf_static_chain_goes_up_to_the_root():
    T_base_imu = pose_matrix(0.5, 0, 0.9, 0, 0, 0)
    T_imu_velo = pose_matrix(0.3, 0.1, 0.8, 0.05, 0, 0)
    edges = {
        "imu_link": ("base_link", T_base_imu),
        "velodyne": ("imu_link", T_imu_velo),
        "camera": ("base_link", np.eye(4)),
    }
    root, T = from_tf_static(edges, "/velodyne")
    assert root == "base_link"
    np.testing.assert_allclose(T, T_base_imu @ T_imu_velo, atol=1e-12)
    assert from_tf_static(edges, "os_sensor") is None
