"""``lidarloc bench peers``, global part: lidarloc's M3RSM (+ GICP) beside open3d's FPFH + RANSAC and
FGR global registration of a scan to the whole map (hdl_global_localization's alternative to BBS),
on the same scans, map and machine."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from ...core.cache import atomic_write_dir, cache_rebuilt, log
from ...core.config import Config
from ...core.maps.bev import load_or_build_pyramid
from ...core.maps.mapping import load_or_build_map, range_filter
from ...core.maps.voxel_grid import voxel_centroids
from ...core.sequences.factory import SourceSpec
from .common import median, open_source, pose_error

SUCCESS_M, SUCCESS_DEG = 2.0, 5.0
FEATURE_VOXEL = 1.0  # m, the peers' map and scan voxel
NORMAL_RADIUS_VOXELS, FPFH_RADIUS_VOXELS = 2, 5  # the normals' and the features' search radii, in voxels
FEATURES_RECORD = "features.json"  # a cached feature map's record: what it was computed with
FEATURES_VERSION = 1  # of the cached feature map's layout
RANSAC_N = 3  # correspondences a RANSAC hypothesis is drawn from


# ------------------------------------------------------------------------------ global localization
def features_dir(cache_dir: Path, voxel: float = FEATURE_VOXEL) -> Path:
    """Where the FPFH features of the map whose cache directory is ``cache_dir`` are kept."""
    return Path(cache_dir) / f"fpfh-{voxel:g}m"


class FeatureMap:
    """The map's down-sampled points and FPFH features, computed once (open3d). With
    ``cache_dir`` they are kept there (``fpfh-<voxel>m/``) and read back by a later run: on a
    16 km² city they take ~40 minutes to compute and 5.8 GB on disk (20 M points). ``build_s``
    is the time the features took to compute (read from the cache's record when they came from
    it), ``load_s`` the time this object took to have them."""

    def __init__(self, points: np.ndarray, voxel: float = FEATURE_VOXEL, cache_dir: Path | None = None):
        from ...core.o3d import open3d

        self.o3d = open3d()
        self.voxel = voxel
        self.directory = None if cache_dir is None else features_dir(cache_dir, voxel)
        self.cached = False
        t0 = time.perf_counter()
        if self.directory is not None and (self.directory / FEATURES_RECORD).is_file():
            try:
                self.cloud, self.fpfh, self.build_s = self._load(self.directory)
                self.cached = True
            except (OSError, ValueError, KeyError, TypeError) as exc:  # cut short or foreign: built again
                cache_rebuilt(self.directory, str(exc))
        if not self.cached:
            self.cloud, self.fpfh = self.features(points)
            self.build_s = time.perf_counter() - t0
            if self.directory is not None:
                try:
                    atomic_write_dir(self.directory, self._save)
                except OSError as exc:  # a full disk costs the next run the features, not this run
                    log.warning(
                        "lidarloc: warning: %s: cannot keep the FPFH features (%s)", self.directory, exc.strerror
                    )
        self.load_s = time.perf_counter() - t0
        self._index = None  # the map's features in a k-d tree, built when first asked for (index())
        self.index_s = 0.0

    def _record(self) -> dict:
        """What the cached features depend on besides the map (whose cache directory holds them)."""
        return {
            "version": FEATURES_VERSION,
            "voxel": self.voxel,
            "normal_radius": NORMAL_RADIUS_VOXELS * self.voxel,
            "fpfh_radius": FPFH_RADIUS_VOXELS * self.voxel,
            "open3d": self.o3d.__version__,
        }

    def _save(self, directory: Path) -> None:
        np.save(directory / "points.npy", np.asarray(self.cloud.points))
        np.save(directory / "fpfh.npy", np.asarray(self.fpfh.data))
        record = {**self._record(), "feature_points": len(self.cloud.points), "build_s": self.build_s}
        (directory / FEATURES_RECORD).write_text(json.dumps(record, indent=1))

    def _load(self, directory: Path):
        record = json.loads((directory / FEATURES_RECORD).read_text())
        theirs = {k: record.get(k) for k in self._record()}
        if theirs != self._record():
            raise ValueError(f"features of another voxel, radius or open3d ({theirs})")
        n = int(record["feature_points"])
        # copy-on-write maps: open3d copies them into its own arrays (and wants them writeable)
        points = np.load(directory / "points.npy", mmap_mode="c")  # a cut-short file raises here
        fpfh = np.load(directory / "fpfh.npy", mmap_mode="c")
        if points.shape != (n, 3) or fpfh.shape != (33, n) or points.dtype != np.float64 or fpfh.dtype != np.float64:
            raise ValueError(f"arrays of shape {points.shape} and {fpfh.shape}, not ({n}, 3) and (33, {n})")
        cloud = self.o3d.geometry.PointCloud(self.o3d.utility.Vector3dVector(points))
        feature = self.o3d.pipelines.registration.Feature()
        feature.data = fpfh  # copied into open3d's own matrix, exactly as computed
        return cloud, feature, float(record["build_s"])

    def features(self, points: np.ndarray):
        o3d, v = self.o3d, self.voxel
        # Down-sampled before open3d sees it, a chunk at a time: open3d's own voxel_down_sample
        # wants every point as float64 in its cloud first (a city map: tens of GB).
        centroids = voxel_centroids(points, v)
        assert centroids is not None  # no cap
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centroids.astype(np.float64)))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_VOXELS * v, max_nn=30))
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * v, max_nn=100)
        )
        return pcd, fpfh

    def index(self):
        """The map's features in open3d's k-d tree, built once (``index_s``): open3d's
        ``registration_ransac_based_on_feature_matching`` builds it again on every call (217 s of
        508 s on a city's scan). hdl_global_localization, whose alternative to BBS this
        stands for, builds it once when the map is loaded, as lidarloc builds its pyramid."""
        if self._index is None:
            t = time.perf_counter()
            self._index = self.o3d.geometry.KDTreeFlann(self.fpfh)
            self.index_s = time.perf_counter() - t
        return self._index

    def correspondences(self, src_features, ransac_n: int = RANSAC_N) -> np.ndarray:
        """The (scan point, map point) pairs open3d's ``registration_ransac_based_on_feature_matching``
        hands to its RANSAC with ``mutual_filter=True``, the same pairs in the same order: each scan
        point's nearest map feature, kept where that map point's nearest scan feature is the scan
        point again (all pairs when fewer than ``3 ransac_n`` survive). open3d asks the reverse
        question of every map point; only those some scan point chose can answer it, so only they
        are asked."""
        index, o3d = self.index(), self.o3d
        src = np.asarray(src_features.data)
        ahead = np.array([index.search_knn_vector_xd(src[:, i], 1)[1][0] for i in range(src.shape[1])], np.int64)
        back_index = o3d.geometry.KDTreeFlann(src_features)
        target = np.asarray(self.fpfh.data)
        back = {int(j): back_index.search_knn_vector_xd(target[:, j], 1)[1][0] for j in np.unique(ahead)}
        pairs = np.column_stack([np.arange(len(ahead)), ahead]).astype(np.int32)
        mutual = pairs[[back[int(j)] == i for i, j in pairs]] if len(pairs) else pairs
        return mutual if len(mutual) >= 3 * ransac_n else pairs

    def ransac(self, scan: np.ndarray, seed: int) -> np.ndarray:
        """open3d's FPFH + RANSAC global registration of ``scan`` to the map, with open3d's
        parameters as before; the feature correspondences from :meth:`correspondences` (the map's
        feature index built once), RANSAC by open3d's ``registration_ransac_based_on_correspondence``,
        which is what its feature-matching call runs on them."""
        reg = self.o3d.pipelines.registration
        src, src_f = self.features(scan)
        corres = self.o3d.utility.Vector2iVector(self.correspondences(src_f))
        self.o3d.utility.random.seed(seed)
        res = reg.registration_ransac_based_on_correspondence(src, self.cloud, corres, *self._ransac_parameters())
        return np.asarray(res.transformation)

    def ransac_open3d(self, scan: np.ndarray, seed: int) -> np.ndarray:
        """The same registration by open3d's one call (the map's feature index built inside it, every
        call): what :meth:`ransac` must equal."""
        reg = self.o3d.pipelines.registration
        self.o3d.utility.random.seed(seed)
        src, src_f = self.features(scan)
        res = reg.registration_ransac_based_on_feature_matching(
            src, self.cloud, src_f, self.fpfh, True, *self._ransac_parameters()
        )
        return np.asarray(res.transformation)

    def _ransac_parameters(self) -> tuple:
        """open3d's RANSAC parameters after the correspondences, the same for both ways of calling it:
        inlier distance, estimation, points a hypothesis, checkers, iterations and confidence."""
        reg, v = self.o3d.pipelines.registration, self.voxel
        return (
            1.5 * v,
            reg.TransformationEstimationPointToPoint(False),
            RANSAC_N,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * v)],
            reg.RANSACConvergenceCriteria(100000, 0.999),
        )

    def fgr(self, scan: np.ndarray) -> np.ndarray:
        reg, v = self.o3d.pipelines.registration, self.voxel
        src, src_f = self.features(scan)
        res = reg.registration_fgr_based_on_feature_matching(
            src, self.cloud, src_f, self.fpfh, reg.FastGlobalRegistrationOption(maximum_correspondence_distance=0.5 * v)
        )
        return np.asarray(res.transformation)


def _judge(T: np.ndarray, truth: np.ndarray) -> tuple[bool, float, float]:
    if not np.isfinite(T).all():
        return False, math.inf, math.inf
    m, deg = pose_error(T, truth)
    return m <= SUCCESS_M and deg <= SUCCESS_DEG, m, deg


def global_localization(
    spec: SourceSpec, cfg: Config, scans: int, cache_root: Path | None = None, progress=None, peers: bool = True
) -> dict:
    """M3RSM (+GICP) against FPFH + RANSAC and FGR (``peers``; else M3RSM alone) on ``scans``
    random scans of the source."""
    from ...core.matching import m3rsm
    from ...core.matching.s2m import ScanToMapMatcher

    seq = open_source(spec, cfg, "peers", need_poses=True)
    prior, map_dir, _ = load_or_build_map(seq.map_source, cfg.map, cache_root)
    t0 = time.perf_counter()
    pyramid = load_or_build_pyramid(prior, map_dir, cfg.s2m).value
    matcher = ScanToMapMatcher(prior, pyramid, cfg.s2m)
    lidarloc_build_s = time.perf_counter() - t0
    features = FeatureMap(prior.points) if peers else None
    if features is not None:
        features.index()  # built once, off the clock, as on a city
    names = ("m3rsm", "fpfh_ransac", "fgr") if peers else ("m3rsm",)
    rng = np.random.default_rng(cfg.seed)
    idx = [int(k) for k in rng.choice(len(seq), min(scans, len(seq)), replace=False)]
    warm = matcher.prepare(seq.scan(idx[0]))  # numba's kernels and the bound grids, off the clock
    m3rsm.match_global(pyramid, warm.road_removed[:, :2], cfg.s2m.angle_step)
    rows = []
    for j, k in enumerate(idx):
        truth, scan = seq.pose(k), seq.scan(k)
        row = {"scan": k}
        out = matcher.match_global(scan)
        row["m3rsm_ms"], row["m3rsm_accepted"] = out.ms, bool(out.accepted)
        row["m3rsm_success"], row["m3rsm_err_m"], row["m3rsm_err_deg"] = _judge(out.pose, truth)
        pts = range_filter(scan, cfg.map)[:, :3]
        peer_calls = (("fpfh_ransac", lambda: features.ransac(pts, cfg.seed + j)), ("fgr", lambda: features.fgr(pts)))
        for name, call in peer_calls if peers else ():
            t = time.perf_counter()
            T = call()
            row[f"{name}_ms"] = (time.perf_counter() - t) * 1e3
            row[f"{name}_success"], row[f"{name}_err_m"], row[f"{name}_err_deg"] = _judge(T, truth)
        rows.append(row)
        if progress is not None:
            progress(j + 1, len(idx))
    out = {
        "source": seq.name,
        "scans": len(rows),
        "map_points": int(len(prior.points)),
        "lidarloc_map_build_s": lidarloc_build_s,
        "rows": rows,
    }
    for name in names:
        out[f"{name}_success"] = float(np.mean([r[f"{name}_success"] for r in rows]))
        out[f"{name}_ms_median"] = median(r[f"{name}_ms"] for r in rows)
        out[f"{name}_err_m_median"] = median(r[f"{name}_err_m"] for r in rows)
    out["m3rsm_accepted"] = float(np.mean([r["m3rsm_accepted"] for r in rows]))
    if peers:
        best = max(("fpfh_ransac", "fgr"), key=lambda n: (out[f"{n}_success"], -out[f"{n}_ms_median"]))
        out.update(
            feature_map_points=int(len(features.cloud.points)),
            feature_map_build_s=features.build_s,
            best_peer=best,
            time_ratio_best_peer_over_m3rsm=out[f"{best}_ms_median"] / max(out["m3rsm_ms_median"], 1e-9),
        )
    return out


# ------------------------------------------------------------------------------------- tracking
