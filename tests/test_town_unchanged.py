"""The default town stays the same: the same poses, the same triangles, the same scans and the
same prior map for ``--town-seed 0`` and the default configuration, whatever else the town package
learns (the city's districts, tiles and survey map never touch the town's path).

The drive and the triangles are plain numpy and must stay bit-identical (their digests were
computed from the town's code before the city existed). The scans and the map come from open3d's
ray casting (Embree), which picks its code for the CPU it runs on: on another CPU a few rays of a
scan land a last bit apart, and the voxel map built from the mapping drive may hold a point more
or less (seen: 1 521 628 map points against 1 521 629, the drive and triangles identical). So
scans and maps are compared by what they hold per 4 m cell of the ground plane — how many points,
the sum of their heights and of their intensities — with tolerances a last-bit difference stays
far below and a real change in the town exceeds (``test_the_cell_summary_sees_a_two_centimetre_shift``
checks that). The reference, ``data/town_reference.npz``, was written from the same code; a
library upgrade that changes the numbers more than that shows up here first (re-derive it, with
``python tests/test_town_unchanged.py``, only after checking that the town itself did not change)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from lidarloc.core.config import Config, TownConfig
from lidarloc.core.sim.town import TownSequence


def _digest(array) -> str:
    return hashlib.sha1(np.ascontiguousarray(array).tobytes()).hexdigest()[:16]


CELL_M = 4.0
REFERENCE = Path(__file__).parent / "data" / "town_reference.npz"
# A last-bit difference moves a point across a cell border with a chance of ~1e-6 m / 4 m, and
# turns a grazing ray from a hit into a miss now and then: a few points of a scan at most.
COUNT_SHARE = 5e-4  # of the points, at least MIN_COUNT, that may sit in another cell or be missing
MIN_COUNT = 4
SUM_SHARE = 5e-4  # of Σ|height| and Σ|intensity| that may differ, summed over the cells


def summary(points) -> tuple[np.ndarray, np.ndarray]:
    """Per occupied 4 m cell of the ground plane: its (ix, iy) and (count, Σ of every column from
    the third on: height, intensity), sorted by cell."""
    p = np.asarray(points, np.float64)
    cells = np.floor(p[:, :2] / CELL_M).astype(np.int64)
    keys, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    stats = np.zeros((len(keys), 1 + max(p.shape[1] - 2, 0)))
    np.add.at(stats[:, 0], inverse, 1.0)
    for c in range(2, p.shape[1]):
        np.add.at(stats[:, c - 1], inverse, p[:, c])
    return keys, stats


def differences(reference: tuple[np.ndarray, np.ndarray], points) -> list[str]:
    """What sets ``points`` apart from a reference summary beyond the tolerances (empty: the same)."""
    ref_cells, ref_stats = reference
    cells, stats = summary(points)
    if ref_stats.shape[1] != stats.shape[1]:
        return [f"columns {ref_stats.shape[1] + 1} != {stats.shape[1] + 1}"]
    # both summaries laid on the union of their cells (a cell one of them lacks holds zeros)
    union, row = np.unique(np.concatenate([ref_cells, cells]), axis=0, return_inverse=True)
    row = row.ravel()
    a = np.zeros((len(union), ref_stats.shape[1]))
    b = np.zeros_like(a)
    a[row[: len(ref_cells)]] = ref_stats
    b[row[len(ref_cells) :]] = stats
    n = a[:, 0].sum()
    out = []
    moved = np.abs(a[:, 0] - b[:, 0]).sum()
    if moved > max(MIN_COUNT, COUNT_SHARE * n):
        out.append(f"{moved:.0f} points in other cells or missing (of {n:.0f})")
    for c in range(1, a.shape[1]):
        diff, scale = np.abs(a[:, c] - b[:, c]).sum(), np.abs(a[:, c]).sum()
        if diff > SUM_SHARE * scale + 1e-9:
            out.append(f"column {c + 2}: cell sums differ by {diff:.4g} (of {scale:.4g})")
    return out


@pytest.fixture(scope="module")
def reference() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    with np.load(REFERENCE) as z:
        names = {k.split("/")[0] for k in z.files}
        return {n: (z[f"{n}/cells"], z[f"{n}/stats"]) for n in names}


POSES = "6522ecc6333b5c65"
POSES_TOWN = "689643a606221d38"
TIMES = "d10e215363082fa0"
SCANS = (0, 1, 600, 1199)
PARTS = {  # material: (triangles, vertices digest, triangles digest, reflectivity digest)
    "road": (23344, "6f5c2c03ac2650f6", "f65253f317cc8055", "e9b51d655b2965b2"),
    "sidewalk_lot": (97144, "fbd3d0560424c2bd", "e7a585feaaa9d6f7", "8c9033e4fc37e78f"),
    "curb": (25728, "726821b2981bbbea", "a1aef8ab9b7016c3", "9818da075427c945"),
    "building": (2400, "0c01ee3b717b47f1", "ca814bec7321ca25", "b49277b3c52d9225"),
    "roof": (240, "33e2971e11cc3286", "e94e0ab83e2f152d", "1d7dd20a185dcea4"),
    "wall": (390, "2c83389bacee64e4", "9a541de3a29c5bbb", "3bc5959c7111b67c"),
    "fence": (2650, "79c5d148b64001ef", "c5c950a8132be34a", "404a0c896b190bd2"),
    "hedge": (2788, "5ac9c5732e113e78", "c8507171e5fa207d", "23f02f5af112219c"),
    "trunk": (11682, "3591fed406249030", "e5c2322956870ec2", "2e23c8f527c2233e"),
    "crown": (89253, "4bc8a746d60f0821", "6308715575c582c3", "48ba5d4f4473d7fc"),
    "bush": (7616, "293fb1e5538de156", "f5c6a2b7509575be", "279b0f3a9cd99653"),
    "pole": (3112, "4aa1956141e5abaa", "efe6c54c23eb10c5", "7501382aabfe4e0f"),
    "sign": (20, "258b2abfc1db5cd8", "e2f66d9b0a6f013b", "ff4bfd8278168848"),
    "car": (2630, "a1df1879d3a1894c", "6313ea04e79d583a", "596a57388746d90b"),
    "glass": (2360, "efcd6a6de86ae330", "ed660e961aa97a8b", "2f505169836e8626"),
    "wheel": (10520, "5ae06062955ad60b", "7ea7ac0f4329252a", "39bc426cb71b36e6"),
    "marking": (602, "0b021316f2e900e2", "d0fe1c49b16f951d", "24445167b4615dde"),
}
COUNTS = dict(
    stops=3,
    walls=39,
    buildings=153,
    hedges=12,
    trees=531,
    poles=81,
    fences=31,
    parked_cars=263,
    bushes=141,
    triangles=282479,
    streets=11,
)
ROUTE_2_POSES = "b8afe06c47dee76c"


@pytest.fixture(scope="module")
def town(default_town) -> TownSequence:
    return default_town  # TownSequence.from_config(TownConfig(), seed=0), made once per session


def test_default_town_drive_and_triangles_are_unchanged(town):
    assert _digest(town.poses) == POSES
    assert _digest(town.poses_town) == POSES_TOWN
    assert _digest(town.timestamps) == TIMES
    parts = {
        p.name: (p.n_triangles, _digest(p.vertices), _digest(p.triangles), _digest(p.reflectivity))
        for p in town.lidar.parts
    }
    assert parts == PARTS
    assert {k: town.stats[k] for k in COUNTS} == COUNTS


def test_default_town_scans_are_unchanged(town, reference):
    assert {i: differences(reference[f"scan{i}"], town.scan(i)) for i in SCANS} == {i: [] for i in SCANS}


def test_the_cell_summary_sees_a_two_centimetre_shift(town, reference):
    """The tolerances are not so loose that a small real change passes: scan 0 moved by 2 cm, or
    with 1 % of its points dropped, is told apart from the reference."""
    scan = town.scan(0)
    assert differences(reference["scan0"], scan) == []
    shifted = scan.copy()
    shifted[:, 0] += 0.02
    assert differences(reference["scan0"], shifted)
    assert differences(reference["scan0"], scan[np.arange(len(scan)) % 100 != 0])


def test_default_town_world_options_are_unchanged(town, reference):
    second = town.with_world(route=2)
    assert _digest(second.poses) == ROUTE_2_POSES
    assert differences(reference["route2_scan5"], second.scan(5)) == []
    lived_in = town.with_world(changes=0.3, traffic=True, skew=True, sensor="vlp16")  # and the VLP-16
    assert differences(reference["lived_in_scan50"], lived_in.scan(50)) == []


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_default_town_map_is_unchanged(town, reference, default_town_cache):
    from lidarloc.core.maps.mapping import load_or_build_map

    # built by this session's code into its cache (once, shared with the benchmarks' tests)
    prior = load_or_build_map(town.map_source, Config().map, default_town_cache).value
    assert differences(reference["map"], prior.points) == []
    assert differences(reference["map_road_removed"], prior.points_bev) == []


def write_reference(path: Path = REFERENCE) -> None:
    """Writes the reference summaries from this machine: the scans and the map the tests read."""
    import tempfile

    from lidarloc.core.maps.mapping import load_or_build_map

    town = TownSequence.from_config(TownConfig(), seed=0)
    clouds = {f"scan{i}": town.scan(i) for i in SCANS}
    clouds["route2_scan5"] = town.with_world(route=2).scan(5)
    clouds["lived_in_scan50"] = town.with_world(changes=0.3, traffic=True, skew=True, sensor="vlp16").scan(50)
    with tempfile.TemporaryDirectory() as cache:
        prior = load_or_build_map(town.map_source, Config().map, Path(cache)).value
        clouds["map"], clouds["map_road_removed"] = prior.points, prior.points_bev
    arrays = {}
    for name, points in clouds.items():
        arrays[f"{name}/cells"], arrays[f"{name}/stats"] = summary(points)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)


if __name__ == "__main__":
    write_reference()
