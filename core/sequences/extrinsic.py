"""The LiDAR's mounting: the rigid transform base ← LiDAR.

Convention: the localizer works in the LiDAR frame (scans as the sensor gave them, poses
world ← LiDAR). Ground truth is usually recorded for the vehicle's base or IMU frame, so a
recording's truth is moved to the LiDAR once, ``T_world_lidar = T_world_base · T_base_lidar``,
and nothing downstream needs to know about the base frame. Scans are never transformed.

Where the transform comes from, first found wins:

1. a text file (``--extrinsic FILE``): 16 numbers (4×4, row-major) or 12 (the top 3×4 rows),
   whitespace- or comma-separated, ``#`` comments allowed; or the word ``identity``;
2. a recording's ``/tf_static``: the chain of static transforms from the root of the tree that
   holds the cloud's ``frame_id`` (e.g. ``base_link``) down to that frame (:func:`from_tf_static`);
3. none: the identity (the truth is taken to be the LiDAR's own poses).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import DataError

#: how far R·Rᵀ may be from I (rounded numbers in a hand-written file pass; a scale does not)
ORTHONORMAL_TOL = 1e-3


def check_rigid(T: np.ndarray, where: str) -> np.ndarray:
    """A 4×4 rigid transform, or a one-line DataError naming ``where``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DataError(f"{where}: a transform must be 4×4; got shape {T.shape}")
    if not np.isfinite(T).all():
        raise DataError(f"{where}: transform contains NaN or infinite values")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise DataError(f"{where}: last row must be 0 0 0 1; got {' '.join(f'{v:g}' for v in T[3])}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > ORTHONORMAL_TOL or np.linalg.det(R) < 0:
        raise DataError(f"{where}: the 3×3 block is not a rotation (not orthonormal with determinant +1)")
    return T


def read_extrinsic(path: str | os.PathLike) -> np.ndarray:
    """base ← LiDAR from a text file (see the module docstring)."""
    path = Path(path)
    if str(path).strip().lower() == "identity":
        return np.eye(4)
    if not path.is_file():
        raise DataError(f"{path}: extrinsic file not found")
    text = "\n".join(line.split("#", 1)[0] for line in path.read_text(errors="replace").splitlines())
    try:
        values = np.array([float(v) for v in text.replace(",", " ").split()], dtype=np.float64)
    except ValueError:
        raise DataError(f"{path}: extrinsic must be 12 or 16 numbers (a 4×4 or 3×4 matrix)") from None
    if values.size == 12:
        values = np.r_[values, 0, 0, 0, 1]
    if values.size != 16:
        raise DataError(f"{path}: extrinsic must be 12 or 16 numbers (a 4×4 or 3×4 matrix); got {values.size}")
    return check_rigid(values.reshape(4, 4), str(path))


def resolve_extrinsic(extrinsic) -> np.ndarray | None:
    """``extrinsic`` as given to a sequence: None (look elsewhere), a 4×4 array, a path or "identity"."""
    if extrinsic is None:
        return None
    if isinstance(extrinsic, (str, os.PathLike)):
        return read_extrinsic(extrinsic)
    return check_rigid(extrinsic, "extrinsic")


def transform_from_ros(translation, rotation) -> np.ndarray:
    """4×4 from a geometry_msgs Transform's translation (x, y, z) and rotation (x, y, z, w)."""
    from scipy.spatial.transform import Rotation

    q = np.array([rotation.x, rotation.y, rotation.z, rotation.w], dtype=np.float64)
    if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-9:
        raise DataError("/tf_static: a transform has a zero or invalid quaternion")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    T[:3, 3] = [translation.x, translation.y, translation.z]
    return T


def from_tf_static(edges: dict[str, tuple[str, np.ndarray]], frame: str) -> tuple[str, np.ndarray] | None:
    """Chain static transforms up from ``frame`` to the root of its tree.

    ``edges`` maps a child frame to ``(parent frame, T_parent_child)``, as collected from
    ``/tf_static``. Returns ``(root frame, T_root_frame)``, or None when ``frame`` is not a child
    in the tree (no static transform mentions it). Frame names are compared without a leading
    slash (ROS 1 bags often write ``/base_link``)."""
    frame = frame.lstrip("/")
    if frame not in edges:
        return None
    T = np.eye(4)
    seen = {frame}
    while frame in edges:
        parent, T_pc = edges[frame]
        T = T_pc @ T
        frame = parent
        if frame in seen:
            raise DataError(f"/tf_static: the static transforms form a loop through {frame!r}")
        seen.add(frame)
    return frame, T
