"""PointCloud2 → numpy on every field layout the drivers publish (synthetic messages; the real
drive's scans through real bags are in test_rosbag.py)."""

from types import SimpleNamespace

import numpy as np
import pytest
from lidarloc.core.errors import DataError
from lidarloc.core.sequences.pointcloud2 import cloud_dtype, to_xyzi

CODES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def message(points: np.ndarray, height: int = 1, row_pad: int = 0, bigendian: bool = False, fields=None):
    """A PointCloud2-like message whose data are the structured ``points`` (height × width in row
    order), each row followed by ``row_pad`` garbage bytes."""
    dt = points.dtype
    width = len(points) // height
    rows = points.view(np.uint8).reshape(height, width * dt.itemsize)
    buf = np.full((height, width * dt.itemsize + row_pad), 0xCD, dtype=np.uint8)
    buf[:, : rows.shape[1]] = rows
    if fields is None:
        fields = [
            SimpleNamespace(
                name=n,
                offset=dt.fields[n][1],
                datatype=CODES[dt.fields[n][0].base.str[1:]],
                count=int(np.prod(dt.fields[n][0].shape)) or 1,
            )
            for n in dt.names
        ]
    return SimpleNamespace(
        height=height,
        width=width,
        fields=fields,
        is_bigendian=bigendian,
        point_step=dt.itemsize,
        row_step=width * dt.itemsize + row_pad,
        data=buf.reshape(-1),
        is_dense=False,
    )


def structured(spec, n, itemsize=None, order="<", rng=None):
    names = [s[0] for s in spec]
    formats = [order + s[1] if isinstance(s[1], str) else (order + s[1][0], s[1][1]) for s in spec]
    offsets = [s[2] for s in spec]
    dt = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, **({"itemsize": itemsize} if itemsize else {})}
    )
    arr = np.zeros(n, dtype=dt)
    rng = rng or np.random.default_rng(0)
    for name in names:
        if arr[name].dtype.kind == "f":
            arr[name] = rng.uniform(-50, 50, arr[name].shape)
        else:
            arr[name] = rng.integers(0, 100, arr[name].shape)
    return arr


def test_dense_float32_xyzi_is_read_exactly():
    arr = structured([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12)], 1000)
    out = to_xyzi(message(arr))
    assert out.dtype == np.float32 and out.shape == (1000, 4)
    for k, name in enumerate(("x", "y", "z", "intensity")):
        np.testing.assert_array_equal(out[:, k], arr[name])


def test_float64_xyz_and_extra_fields_in_any_order():
    # ring and t before the coordinates, a 3-element field, intensity as uint16
    spec = [
        ("ring", "u2", 0),
        ("t", "f8", 2),
        ("normal", ("f4", (3,)), 10),
        ("x", "f8", 22),
        ("y", "f8", 30),
        ("z", "f8", 38),
        ("intensity", "u2", 46),
    ]
    arr = structured(spec, 500)
    out = to_xyzi(message(arr))
    np.testing.assert_array_equal(out[:, 0], arr["x"].astype(np.float32))
    np.testing.assert_array_equal(out[:, 2], arr["z"].astype(np.float32))
    np.testing.assert_array_equal(out[:, 3], arr["intensity"].astype(np.float32))


def test_big_endian_cloud():
    arr = structured([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12)], 300, order=">")
    out = to_xyzi(message(arr, bigendian=True))
    np.testing.assert_array_equal(out[:, 1], arr["y"].astype("<f4"))
    np.testing.assert_array_equal(out[:, 3], arr["intensity"].astype("<f4"))
    # the same bytes read as little-endian are not the cloud: the byte order is honoured
    assert not np.array_equal(to_xyzi(message(arr, bigendian=False))[:, :3], out[:, :3])


def test_padded_organised_cloud_drops_missing_returns_and_keeps_order():
    """Ouster: 48-byte points, 16 rows, row padding; cells without a return are NaN or all-zero."""
    spec = [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("intensity", "f4", 16),
        ("t", "u4", 20),
        ("reflectivity", "u2", 24),
        ("ring", "u2", 26),
    ]
    arr = structured(spec, 16 * 64, itemsize=48)
    rng = np.random.default_rng(1)
    missing = rng.random(len(arr)) < 0.2
    nan = missing & (rng.random(len(arr)) < 0.5)
    for c in ("x", "y", "z"):
        arr[c][missing] = 0.0
        arr[c][nan] = np.nan
    out = to_xyzi(message(arr, height=16, row_pad=24))
    assert len(out) == int((~missing).sum())
    np.testing.assert_array_equal(out[:, 0], arr["x"][~missing])
    np.testing.assert_array_equal(out[:, 3], arr["intensity"][~missing])
    assert np.isfinite(out).all()


def test_intensity_alternatives_and_absence():
    arr = structured([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("reflectivity", "u2", 12)], 50, itemsize=16)
    np.testing.assert_array_equal(to_xyzi(message(arr))[:, 3], arr["reflectivity"])
    bare = structured([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8)], 50)
    assert (to_xyzi(message(bare))[:, 3] == 0).all()


def test_unknown_datatype_of_an_unused_field_is_skipped():
    arr = structured([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("vendor", "u4", 12)], 40)
    msg = message(arr)
    msg.fields[3].datatype = 42
    np.testing.assert_array_equal(to_xyzi(msg)[:, 2], arr["z"])


def test_dtype_itemsize_is_point_step():
    arr = structured([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8)], 10, itemsize=32)
    assert cloud_dtype(message(arr)).itemsize == 32


@pytest.mark.parametrize(
    "case, words",
    [
        ("no_xyz", ["no x/y/z fields", "rgb", "label"]),
        ("bad_datatype", ["unknown PointField datatype 9"]),
        ("field_outside_point", ["does not fit in point_step"]),
        ("truncated", ["truncated"]),
        ("short_row_step", ["row_step"]),
    ],
)
def test_bad_clouds_are_one_line_errors(case, words):
    arr = structured([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8)], 20)
    msg = message(arr)
    if case == "no_xyz":
        msg.fields = [
            SimpleNamespace(name="rgb", offset=0, datatype=7, count=1),
            SimpleNamespace(name="label", offset=4, datatype=6, count=1),
        ]
    elif case == "bad_datatype":
        msg.fields[1].datatype = 9
    elif case == "field_outside_point":
        msg.fields[2].offset = 10
    elif case == "truncated":
        msg.data = msg.data[:-5]
    else:
        msg.row_step = 8
    with pytest.raises(DataError) as exc:
        to_xyzi(msg, "drive.mcap /points")
    text = str(exc.value)
    assert "\n" not in text and text.startswith("drive.mcap /points")
    for w in words:
        assert w in text
