"""The configuration's schema: one typed dataclass per section with the paper's defaults, and
the rules every configuration must follow (:meth:`Config.validate`).

Units inside the code are metres, seconds and radians. The paper quotes angles in degrees; those
entries are converted here once, and the edges (CLI, GUI, reports) convert back for display.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields

from ..errors import LidarlocError

DEG = math.pi / 180.0

# Paper, Simulation section: Q = diag[0.5², 0.5², 0.1², (5°)², (2°)², (0.1°)², 0.1²,
# (0.05°)², (0.05°)², (0.02°)², 0.001²] for [x, y, z, yaw, pitch, roll, v, yaw_rate,
# pitch_rate, roll_rate, a]. Stored as standard deviations (square roots of the diagonal), SI units.
PAPER_Q_STD = (
    0.5,
    0.5,
    0.1,
    5.0 * DEG,
    2.0 * DEG,
    0.1 * DEG,
    0.1,
    0.05 * DEG,
    0.05 * DEG,
    0.02 * DEG,
    0.001,
)
STATE_NAMES = ("x", "y", "z", "yaw", "pitch", "roll", "v", "yaw_rate", "pitch_rate", "roll_rate", "a")
# Which entries of the state are angles (or angular rates): the GUI and reports show them in degrees.
ANGULAR_STATE = (False, False, False, True, True, True, False, True, True, True, False)


@dataclass
class MapConfig:
    """Prior-map building (paper: the map is assembled from the drive's own scans and poses)."""

    voxel_size: float = 0.2  # m, voxel grid of the global 3D map
    road_normal_z: float = 0.75  # |n_z| above this = flat surface, removed for the BEV map
    normal_radius: float = 0.6  # m, neighbourhood radius for normal estimation
    normal_max_nn: int = 30  # at most this many neighbours for a normal
    scan_max_range: float = 80.0  # m, map points farther from the sensor are noisier; dropped
    scan_min_range: float = 2.5  # m, the car's own body


@dataclass
class PFConfig:
    """Particle filter (paper: Particle filtering, Dynamic model, Sensor model, Simulation)."""

    n_particles: int = 1000  # particles (with KLD-sampling: the most it keeps)
    scan_voxel: float = 0.5  # m, random-point-per-voxel down-sampling of each scan
    d_max: float = 5.0  # m, distance cap of the likelihood
    sigma: float = 0.5  # m, likelihood scale
    lookup_resolution: float = 0.25  # m, δ of the nearest-distance lookup table
    # m, side of the lookup table's tiles; 0 = one table over the whole map. A city's map: tiles
    # (rounded to whole 48 m build tiles at δ = 0.25 m) mapped in around the particles only
    lookup_tile_m: float = 0.0
    q_std: tuple = PAPER_Q_STD  # process-noise standard deviations, SI units, see PAPER_Q_STD
    dt: float = 0.1  # s, used when a sequence has no timestamps
    v_max: float = 15.0  # m/s, initial speeds are uniform in [0, v_max]
    init_yaw: float = math.pi  # rad, initial yaw uniform in ±init_yaw
    init_pitch: float = 30.0 * DEG  # rad
    init_roll: float = 10.0 * DEG  # rad
    init_rate_std: float = 0.1  # rad/s, initial angular rates ~ N(0, 0.1²)
    # "uniform_box": the paper's init, positions uniform in the map's 3D bounding box.
    # "map_support": x, y only where the map has points, z = local ground + sensor height.
    init_mode: str = "uniform_box"
    sensor_height: float = 1.73  # m, KITTI's Velodyne above the road
    resample_threshold: float = 0.5  # resample when N_eff < threshold · N
    # Likelihood shape and cost. The paper's log-likelihood is −Σ min(d², d_max²)/σ² over the
    # scan's points: summed over 12–15k points it separates particles by hundreds of nats, so the
    # weights collapse to one particle (N_eff ≈ 1), the std is ≈ 0 from the first scans, the 2σ
    # ellipse never holds the truth and the localization rule fires at its earliest scan whatever
    # the filter does; a point the map cannot explain (traffic, a moved car, a beam above what
    # the map's sensor saw) costs up to d_max²/σ² = 100 nats and outvotes the rest.
    # The defaults below were chosen by measurement (BENCHMARKS.md, "Making the filter cope"),
    # each against the paper's (--preset paper restores it): on the real drive and in the lived-in
    # town (changes 0.3, traffic, skew) an unexplained share of 0.1 with T = 1000 is more accurate
    # than the paper's likelihood (RMSE after localization: real drive 0.20 m against 0.23; town
    # HDL-64E 0.19 m against 0.29, OS1-128 0.17 against 1.54, VLP-16 0.40 against 1.71), and its
    # 2σ ellipse holds the truth in ~100 % of localized scans instead of ~0 %. Tempered, every
    # particle's sum runs to the end (none falls below the weight floor); max_points pays that
    # back.
    # the log-likelihood is divided by T (tempering); 1 = paper; 0 = T is the number of points
    # weighed (a per-point mean)
    temperature: float = 1000.0
    # per-point mixture with an "unexplained point" term, as the beam model's z_rand: p =
    # (1−z)·exp(−min(d²,d_max²)/σ²) + z; 0 = paper
    unexplained_share: float = 0.1
    # Weigh at most this many points of each prepared scan: an evenly spread subset (every
    # ~M/N-th point in a golden-ratio order) whose sum is scaled by M/N, so the log-likelihood
    # keeps the whole scan's scale (an unbiased estimate of it; all particles share the subset).
    # Tempered, the likelihood counts only a few points' worth of evidence, which a thousand
    # points estimate about as well as 15k (real drive, 5 runs: 0.22 m with 1000 points, 0.22 m
    # with all) at a fraction of the cost. 500 rather than 1000 pays for keeping 1000 particles
    # once converged (kld_min below): the PF's CPU per scan stays where it was. 0 = every point
    # (the paper).
    max_points: int = 500
    # Leave out scan points seen above this elevation angle from the sensor, before the
    # down-sampling. A map can only explain what its own sensor saw: the town's map (and a map
    # made with an HDL-64E, whose top beam is +2°) holds nothing higher than ~3 m above the
    # sensor near walls, so a VLP-16's or OS1-128's upper beams, unexplained, pull the estimate
    # ~1.4 m down the walls with the paper's likelihood (measured; BENCHMARKS.md). A cap at the
    # map's sensor's top beam (--set pf.max_elevation=0.035 for an HDL-64E's +2°) removes that
    # pull for the tempered likelihood without an unexplained share; the default likelihood's
    # unexplained share removes it already, and adding the cap to it did not help (one lived-in
    # VLP-16 run: 1.09 m with it, 0.40 m without). π/2 = every point (the paper).
    max_elevation: float = math.pi / 2  # rad
    # Dynamic points: scan points that stay farther than dynamic_distance from the map, at the
    # estimate, over dynamic_scans consecutive scans are left out of the likelihood.
    dynamic_rejection: bool = False
    dynamic_distance: float = 1.0  # m
    dynamic_scans: int = 2  # scans in a row a point must stay far to be left out
    # Adaptive particle count by KLD-sampling (Fox 2003): after each resampling, as many particles
    # as the KLD bound asks for the occupied (x, y, yaw) bins, within [kld_min, n_particles]: all
    # of them while spread, ~200 once converged, never fewer than kld_min. Converged, the
    # likelihood keeps only a few particles (N_eff ≈ 4) and the estimate is their mean, so its
    # error is how near the nearest particles happen to lie to the truth: more particles, a
    # smaller error. kld_min = the paper's 1000 particles with 500 points weighed, against 400
    # particles with 1000 points, at the same PF CPU per scan (BENCHMARKS.md, "Making the filter
    # cope"): RMSE after localization 0.164 m against 0.184 (lived-in town, 10 runs), 0.184
    # against 0.196 (real drive, 20 runs), 0.096 against 0.166 (the town as mapped), the same
    # A–E; only with a VLP-16, whose sparser scans 500 points cover less of, 4 % worse (0.43 m
    # against 0.41). KLD-sampling then trims only a larger set (n_particles raised).
    kld: bool = True
    kld_epsilon: float = 0.05  # KL-divergence bound ε
    kld_z: float = 2.326  # upper (1 − δ) quantile of N(0, 1); 2.326 = δ 0.01
    kld_bin_xy: float = 1.0  # m, bin size in x and y
    kld_bin_yaw: float = 10.0 * DEG  # rad, bin size in yaw
    kld_min: int = 1000  # fewest particles KLD-sampling keeps


@dataclass
class S2MConfig:
    """Scan-to-map matching (M3RSM on the bird's-eye view, then GICP in 3D)."""

    enabled: bool = True  # scan-to-map matching on or off
    match_resolution: float = 1.0  # m, d_m: cell size of pyramid level L0
    angle_step: float = 2.5 * DEG  # rad, d_θ
    region_x: float = 25.0  # m, L_x: local search half-width in x
    region_y: float = 25.0  # m, L_y: local search half-width in y
    yaw_window: float = math.pi  # rad, local search yaw half-window (π = full circle)
    binary_cells: bool = False  # L0 holds point counts (False) or occupancy (True)
    gicp_max_corr: float = 2.0  # m, GICP correspondence distance
    gicp_voxel: float = 0.5  # m
    n_s2m: int = 2  # scans between S2M start and landing in replay clock
    # Until the localization rule is met, search the whole map instead of ± (L_x, L_y) around the
    # best particle (the paper's "full map" mode of its S2M section; M3RSM's branch and bound
    # makes it ~0.2 s here). After localization the paper's local region applies. False = the
    # paper's experiments (local region from the first scan). See README "Method choices".
    global_until_localized: bool = True
    # Acceptance of a landed match. The paper rejects a match "as the corresponding likelihood
    # will significantly lower the weight of the particle": reject_if_weight_drops re-weights the
    # particle at the carried-forward pose and keeps its old state if the log-likelihood fell.
    reject_if_weight_drops: bool = False
    # A start already within the BnB lattice of the truth is refined by GICP and accepted if it
    # then beats its own score (not in the paper: there an unbeaten start is simply rejected).
    refine_unbeaten_start: bool = True
    # Real-time clock only: once localized, start an S2M match at most every this many scans
    # (10 ≈ 1 Hz), leaving the CPU to the PF and the RPE, which must keep the LiDAR rate. 0 = back
    # to back, as before localization and always in replay.
    realtime_interval_localized: int = 10
    # Replay clock only: nice value of the S2M child process (localize.s2m_process). In replay
    # the step waits for each match at k + n_s2m, so the priority never changes a result; it
    # keeps S2M work (in ``bench localize`` also the other runs' S2M processes) from pre-empting
    # the PF, whose per-scan latency is then the PF's own. The real-time clock always runs S2M
    # at nice 0: there it must make progress while the PF and the RPE keep the cores busy
    # (measured on the real drive at nice 10: no match landed, the filter never localized).
    replay_process_nice: int = 10
    # Hold S2M back until this scan (0 = from the first scan): what a cold viewer start, a busy
    # machine or a restarting S2M process does to a run, made repeatable in the replay clock.
    join_at_scan: int = 0
    # The second opinion, once localized: every this many scans (and at once when the confidence
    # falls: the scan fits the map poorly, or local matches are rejected in a row) the next match
    # searches the whole map instead of the local region. It confirms the estimate, or finds a
    # clearly better pose far from it and re-localizes there (see core/rules/integrity.py). 0 = never.
    global_check_interval: int = 50
    # A whole-map match far from the estimate moves the filter only if its BEV score is at least
    # this many times the estimate's own (a look-alike street scores about as well as the truth).
    relocalize_score_ratio: float = 1.25
    # How a whole-map match (until localized, the second opinion, a relocalization) is found.
    # "candidates": the place index built from the map names global_candidates places, the exact
    # M3RSM search verifies each in ± candidate_window and GICP the best (about a second on a
    # 16 km² city); the exact whole-map search only when none verifies. "exact": the whole-map
    # branch and bound every time (its cost grows with the map: ~3.7 CPU-s per km²). "auto":
    # candidates on maps of 0.25 km² and more (at d_m = 1 m), exact below, where it is fast and
    # certain. Also written s2m.global. See docs/global-localization.md.
    global_search: str = "auto"
    # places the look-up hands to the exact search (~7 ms each): on the 16 km² city, where
    # suburbs repeat, the true place ranked beyond the 8th for some scans
    global_candidates: int = 16
    candidate_window: float = 4.0  # m, half-width of the exact search around each place
    # Two distinct places (farther apart than localize.confirm_distance) that both pass GICP, the
    # second scoring at least this share of the best: the answer is "ambiguous", and the filter
    # is not moved. 1 = never ambiguous.
    ambiguity_ratio: float = 0.85


@dataclass
class LocalizeConfig:
    """Localization / false-positive / loss rules (paper: Simulation)."""

    std_threshold: float = 10.0  # m, per-axis position std below this counts as converged
    min_consecutive: int = 10  # scans the std must stay below the threshold
    min_moved: float = 10.0  # m moved (from RPE) over that window …
    min_turned: float = 30.0 * DEG  # … or rad turned
    loss_std: float = 50.0  # m, after localization a larger std is a loss
    clock: str = "replay"  # "replay" (deterministic) or "realtime"
    rpe_process: bool = True  # run KISS-ICP in a child process (it holds the GIL)
    s2m_process: bool = True  # run RS + S2M (M3RSM, GICP) in a child process (GICP holds the GIL)
    # Replay only: read the RPE's KISS-ICP poses from a per-sequence cache computed once (the same
    # numbers bit for bit: the odometry does not depend on the seed). ``bench localize`` uses it
    # so that 50 runs do not repeat the same odometry 50 times.
    recorded_odometry: bool = False
    # Tracking mode (optional): once localized, fewer particles and a smaller S2M region; a
    # false positive, a loss or a reset goes back to the full filter.
    tracking: bool = False  # tracking mode once localized (see below)
    tracking_particles: int = 300  # particles in tracking mode
    tracking_region: float = 10.0  # m, S2M search half-width in x and y while tracking
    # Confidence ("is it lost?"): an event when, while localized, the share of scan points within
    # d_max of the map at the estimate falls below this.
    min_inlier_share: float = 0.5
    # No localization without the matcher's word: the rule above fires only once an S2M match
    # (after GICP) agreed with the estimate during the rule's window, within confirm_distance and
    # confirm_yaw. While S2M is not available (its tables still being built, held back, switched
    # off) the filter may converge, but it says "PF only, unconfirmed", never "localized". False =
    # the paper's rule (the PF alone can fire it).
    require_s2m_confirmation: bool = True
    confirm_distance: float = 5.0  # m, the metrics' own "within 5 m"
    confirm_yaw: float = 15.0 * DEG  # rad
    # S2M's word goes stale: the rule fires only on an agreement at most this many scans old, and
    # "localized" is withdrawn once no S2M match has agreed with the estimate for this many scans
    # (S2M busy with a long search, its landings waiting for a lagging odometry, switched off).
    # Localized, a match lands about every 10 scans. 0 = an agreement never goes stale.
    confirm_within: int = 50
    # Loss detection beyond the paper's std rule: while localized, a scan fitting the map poorly
    # (inlier share below min_inlier_share) for this many scans in a row, with no whole-map match
    # agreeing with the estimate meanwhile, is a loss (re-initialise). 0 = only the std rule.
    lost_after_scans: int = 30
    # De-skew each scan before the filter with the constant-velocity motion from the odometry
    # (per-point times from the azimuth, a spinning LiDAR's sweep of 1/rate seconds).
    deskew: bool = False


@dataclass
class TownConfig:
    """The built-in generated town and its simulated drive.

    The prior map is always made from the mapping drive: the whole route, the town as it was
    (no changes, no traffic), scanned by an HDL-64E at 1.73 m without motion skew. The options
    below change only the world and the sensor of the drive being localized."""

    seed: int = 0
    extent_m: float = 400.0  # m, side of the square town (a city of districts from 1000 m)
    n_scans: int = 1200  # scans in the default drive (10 Hz)
    rate_hz: float = 10.0
    # share of movable objects (parked cars, bins, signs) moved, removed or added, and of
    # vegetation grown or cut, since mapping
    changes: float = 0.0
    traffic: bool = False  # moving cars, cyclists and pedestrians (never in the map)
    sensor: str = "hdl64e"  # hdl64e | vlp16 | vlp32c | os1-128
    mount_height: float = 1.73  # m, sensor above the road
    skew: bool = False  # each scan swept over 1/rate_hz while moving (not de-skewed)
    route: int = 1  # 1 = the mapping drive's route; 2 = another drive, same streets
    # which traffic (with traffic): 0 = the town's own, the same cars at the same moments in every
    # drive of the town; another number = another day's traffic on the same streets
    traffic_seed: int = 0


TOWN_SENSORS = ("hdl64e", "vlp16", "vlp32c", "os1-128")
#: m, the largest town.extent_m: a city's generation needs memory in proportion to its area (~10 GB at 4 km)
TOWN_MAX_EXTENT = 6000.0


@dataclass
class Config:
    map: MapConfig = field(default_factory=MapConfig)
    pf: PFConfig = field(default_factory=PFConfig)
    s2m: S2MConfig = field(default_factory=S2MConfig)
    localize: LocalizeConfig = field(default_factory=LocalizeConfig)
    town: TownConfig = field(default_factory=TownConfig)
    seed: int = 0

    def validate(self) -> Config:
        """Raise LidarlocError on an impossible parameter; returns self for chaining."""
        checks = [
            (self.pf.n_particles >= 1, "pf.n_particles must be ≥ 1"),
            (self.pf.scan_voxel > 0, "pf.scan_voxel must be > 0"),
            (self.pf.d_max > 0, "pf.d_max must be > 0"),
            (self.pf.sigma > 0, "pf.sigma must be > 0"),
            (self.pf.lookup_resolution > 0, "pf.lookup_resolution must be > 0"),
            (self.pf.lookup_tile_m >= 0, "pf.lookup_tile_m must be ≥ 0 (0 = one table)"),
            (len(self.pf.q_std) == 11, "pf.q_std must have 11 entries"),
            (all(q >= 0 and math.isfinite(q) for q in self.pf.q_std), "pf.q_std entries must be finite and ≥ 0"),
            (0 < self.pf.resample_threshold <= 1, "pf.resample_threshold must be in (0, 1]"),
            (
                self.pf.temperature == 0 or self.pf.temperature >= 1,
                "pf.temperature must be ≥ 1 (1 = the paper's likelihood) or 0 (per-point mean)",
            ),
            (0 <= self.pf.unexplained_share < 1, "pf.unexplained_share must be in [0, 1)"),
            (self.pf.max_points >= 0, "pf.max_points must be ≥ 0 (0 = every point)"),
            (self.pf.max_elevation > -math.pi / 2, "pf.max_elevation must be > −π/2 rad (π/2 = every point)"),
            (self.pf.dynamic_distance > 0, "pf.dynamic_distance must be > 0"),
            (self.pf.dynamic_scans >= 1, "pf.dynamic_scans must be ≥ 1"),
            (0 < self.pf.kld_epsilon < 1, "pf.kld_epsilon must be in (0, 1)"),
            (self.pf.kld_z > 0, "pf.kld_z must be > 0"),
            (self.pf.kld_bin_xy > 0 and self.pf.kld_bin_yaw > 0, "pf.kld_bin_xy/kld_bin_yaw must be > 0"),
            (1 <= self.pf.kld_min, "pf.kld_min must be ≥ 1"),
            (0 <= self.localize.min_inlier_share <= 1, "localize.min_inlier_share must be in [0, 1]"),
            (0 <= self.town.changes <= 1, "town.changes must be in [0, 1]"),
            (self.town.sensor in TOWN_SENSORS, f"town.sensor must be one of {'|'.join(TOWN_SENSORS)}"),
            (0.3 <= self.town.mount_height <= 5, "town.mount_height must be in 0.3..5 m"),
            (self.town.route in (1, 2), "town.route must be 1 or 2"),
            (self.pf.init_mode in ("uniform_box", "map_support"), "pf.init_mode must be uniform_box or map_support"),
            (self.map.voxel_size > 0, "map.voxel_size must be > 0"),
            (0 < self.map.road_normal_z <= 1, "map.road_normal_z must be in (0, 1]"),
            (self.s2m.match_resolution > 0, "s2m.match_resolution must be > 0"),
            (0 < self.s2m.angle_step <= math.pi, "s2m.angle_step must be in (0, π]"),
            (self.s2m.region_x > 0 and self.s2m.region_y > 0, "s2m.region_x/region_y must be > 0"),
            (self.s2m.realtime_interval_localized >= 0, "s2m.realtime_interval_localized must be ≥ 0"),
            (0 <= self.s2m.replay_process_nice <= 19, "s2m.replay_process_nice must be in 0..19"),
            (self.s2m.join_at_scan >= 0, "s2m.join_at_scan must be ≥ 0"),
            (self.s2m.global_check_interval >= 0, "s2m.global_check_interval must be ≥ 0 (0 = never)"),
            (self.s2m.relocalize_score_ratio >= 1, "s2m.relocalize_score_ratio must be ≥ 1"),
            (
                self.s2m.global_search in ("auto", "candidates", "exact"),
                "s2m.global_search must be auto, candidates or exact",
            ),
            (1 <= self.s2m.global_candidates <= 64, "s2m.global_candidates must be in 1..64"),
            (self.s2m.candidate_window > 0, "s2m.candidate_window must be > 0"),
            (0 < self.s2m.ambiguity_ratio <= 1, "s2m.ambiguity_ratio must be in (0, 1]"),
            (self.localize.confirm_distance > 0, "localize.confirm_distance must be > 0"),
            (0 < self.localize.confirm_yaw <= math.pi, "localize.confirm_yaw must be in (0, π]"),
            (self.localize.lost_after_scans >= 0, "localize.lost_after_scans must be ≥ 0 (0 = off)"),
            (self.localize.confirm_within >= 0, "localize.confirm_within must be ≥ 0 (0 = never stale)"),
            (1 <= self.s2m.n_s2m <= 50, "s2m.n_s2m must be in 1..50 (the odometry keeps 100 scans)"),
            (self.seed >= 0 and self.town.seed >= 0, "seeds must be ≥ 0"),
            (self.localize.std_threshold > 0, "localize.std_threshold must be > 0"),
            (self.localize.min_consecutive >= 1, "localize.min_consecutive must be ≥ 1"),
            (self.localize.clock in ("replay", "realtime"), "localize.clock must be replay or realtime"),
            (self.localize.tracking_particles >= 1, "localize.tracking_particles must be ≥ 1"),
            (
                not (self.localize.recorded_odometry and self.localize.clock == "realtime"),
                "localize.recorded_odometry needs the replay clock (real time must pay for its odometry)",
            ),
            (self.localize.tracking_region > 0, "localize.tracking_region must be > 0"),
            (self.town.n_scans >= 1, "town.n_scans must be ≥ 1"),
            (100 <= self.town.extent_m <= TOWN_MAX_EXTENT, f"town.extent_m must be in 100..{TOWN_MAX_EXTENT:g} m"),
        ]
        for ok, message in checks:
            if not ok:
                raise LidarlocError(f"invalid configuration: {message}")
        for section in (self.map, self.pf, self.s2m, self.localize, self.town):
            for f in fields(section):
                value = getattr(section, f.name)
                if isinstance(value, float) and not math.isfinite(value):
                    raise LidarlocError(f"invalid configuration: {f.name} is not finite")
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
