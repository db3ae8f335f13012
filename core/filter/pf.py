"""The particle filter (paper: Particle filtering, Main approach → Particle filter).

Sequential importance sampling with the transition prior as proposal (motion.propagate), the
lookup-table likelihood (likelihood.py) as weight update, log-weights normalised with
log-sum-exp, and systematic (low-variance) resampling when N_eff < resample_threshold · N
(the paper: 50 %).

Initialisation (paper, Simulation): positions uniform in the map's 3D bounding box, yaw in
±180°, pitch ±30°, roll ±10°, angular rates N(0, 0.1²), speed uniform in [0, v_max], a = 0.
``init_mode = "map_support"`` instead draws x, y only over 2 m cells where the map has points
(a vehicle drives where the scans were taken, not inside the empty corners of the box), z = the
cell's ground height (a low percentile of the map's z there) + sensor height, and small
pitch/roll (N(0, 2°²)): far fewer particles are wasted in the air or underground.

Choices where the paper is silent, kept explicit:

- The S2M block protects one particle through resampling (``protect``): it keeps its slot index
  (the index the S2M job remembers), its state and the slot's copy is the protected particle
  itself, whatever systematic resampling drew for that slot. All weights are uniform after a
  resampling, the protected slot's included.
- ``reweight(j)`` replaces particle j's share of the current scan's likelihood:
  log w_j ← log w_j − ll_old_j + ll_new_j, i.e. its weight is rescaled by the likelihood ratio
  of its new and old pose (after a resampling too, where the uniform weights already include
  the old likelihood), then all weights are renormalised.
- Weights that are exactly 0.0 in float64 are floored in log space (likelihood.py,
  log_likelihood_floored), which makes the weight update several times faster; see there.
- Process noise Q is applied once per step as the paper states it (not scaled by dt).

Options beyond the paper (with all of them off, as ``--preset paper`` sets them, the filter is the
paper's, bit for bit; the defaults in core/config.py turn the likelihood options and KLD on):

- Likelihood shape, ``cfg.temperature`` and ``cfg.unexplained_share``: see likelihood.py. The
  temperature :data:`~lidarloc.core.filter.likelihood.PER_POINT` (0) divides by the number of points
  the scan is weighed with (after dynamic-point rejection). reweight() uses the same T as the
  update of the same scan, so a particle's ll_new − ll_old stays consistent.
- Point budget, ``cfg.max_points``: update() weighs an evenly spread subset of that many points
  (after dynamic-point rejection), each standing for M/max_points of the scan's M points, an
  unbiased estimate of the whole scan's log-likelihood (likelihood.subset_for); reweight()
  weighs the same subset.
- Dynamic-point rejection, ``cfg.dynamic_rejection``: update() leaves out the points
  :class:`~lidarloc.core.filter.dynamic.DynamicPointFilter` rejects at the prior estimate (the weighted
  mean of the predicted particles), but only while the particles' x/y std is below
  ``dynamic.MAX_SPREAD`` (a spread cloud's mean is no pose to judge the world by); otherwise
  the history is forgotten. reweight() with the same scan array weighs the same subset.
- KLD-sampling, ``cfg.kld``: each resampling draws ``n_max`` particles by systematic resampling
  in a random order and keeps the shortest prefix Fox's bound accepts (core/filter/kld.py), so the
  count falls to a few hundred once the cloud has converged and rises again when it spreads
  (up to ``n_max``: ``cfg.n_particles``, or the count set_n_particles() last set, e.g. tracking
  mode's). initialize() always starts from ``n_max``. The
  protected particle keeps its slot if the new count still has it, else it takes the last slot:
  ``protected_index`` says where it is. ``kld_bins`` is the bin count of the last KLD resampling.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..config import PFConfig
from ..errors import LidarlocError
from ..geometry import as_points, pose_to_xyz_ypr, wrap_angle
from ..maps.lookup import LookupTable
from .dynamic import MAX_SPREAD, DynamicPointFilter
from .estimate import Estimate, weighted_estimate
from .kld import bin_keys, kld_count
from .likelihood import (
    check_shape,
    effective_temperature,
    log_likelihood,
    log_likelihood_floored,
    scrambled_order,
    subset_for,
)
from .motion import N_STATE, propagate
from .support import SupportGrid, support_for

MAP_SUPPORT_PITCH_ROLL_STD = 2.0 * math.pi / 180.0
DEFAULT_POSE_STD = (1.0, 1.0, 0.2, 5.0 * math.pi / 180.0, 1.0 * math.pi / 180.0, 1.0 * math.pi / 180.0)


def systematic_resample(weights: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n_out`` draws by systematic (low-variance) resampling: one uniform offset,
    then evenly spaced positions through the cumulative weights."""
    w = np.asarray(weights, dtype=np.float64)
    cum = np.cumsum(w)
    cum /= cum[-1]
    positions = (rng.random() + np.arange(n_out)) / n_out
    return np.minimum(np.searchsorted(cum, positions, side="right"), len(w) - 1)


class ParticleFilter:
    """The paper's particle filter. ``states`` (N, 11) and ``log_weights`` (N,) are public;
    ``weights`` are the normalised exp(log_weights)."""

    def __init__(
        self,
        cfg: PFConfig,
        lookup: LookupTable,
        bounds_min,
        bounds_max,
        seed: int = 0,
        support: SupportGrid | None = None,
        map_points: np.ndarray | None = None,
    ):
        self.cfg = cfg
        self.lookup = lookup
        self.bounds_min = np.asarray(bounds_min, dtype=np.float64).reshape(3)
        self.bounds_max = np.asarray(bounds_max, dtype=np.float64).reshape(3)
        if np.any(self.bounds_max < self.bounds_min):
            raise LidarlocError("particle filter: bounds_max must be ≥ bounds_min")
        self.rng = np.random.default_rng(seed)
        self._support = support
        self._map_points = map_points  # turned into a SupportGrid on first map_support init
        self.set_d_max(cfg.d_max)
        self.set_sigma(cfg.sigma)
        self.set_q_std(cfg.q_std)
        self.n = int(cfg.n_particles)
        if self.n < 1:
            raise LidarlocError("particle filter: n_particles must be ≥ 1")
        self.n_max = self.n  # the count a fresh cloud gets, and KLD-sampling's ceiling
        self.states = np.zeros((self.n, N_STATE))
        self.log_weights = np.full(self.n, -math.log(self.n))
        self.log_likelihoods = np.zeros(self.n)  # of the last update, per particle
        self._scan: np.ndarray | None = None  # the points the last update weighed with
        self._scan_input = None  # the array update() was given (see reweight)
        self._temperature = 1.0  # effective T of the last update
        self._point_weight = 1.0  # scan points each weighed point stood for
        self.protected_index: int | None = None  # where the last resampling put the protected particle
        self.kld_bins: int | None = None  # occupied bins at the last KLD resampling
        check_shape(cfg.temperature, cfg.unexplained_share)
        self.dynamic = (
            DynamicPointFilter(lookup, cfg.dynamic_distance, cfg.dynamic_scans) if cfg.dynamic_rejection else None
        )
        self.initialize()

    # ------------------------------------------------------------------------ parameters
    @property
    def weighed_points(self) -> np.ndarray | None:
        """The points the last update weighed (after the point budget and dynamic rejection)."""
        return self._scan

    @property
    def d_max(self) -> float:
        return self._d_max

    @property
    def sigma(self) -> float:
        return self._sigma

    @property
    def q_std(self) -> np.ndarray:
        return self._q_std.copy()

    def set_d_max(self, d_max: float) -> None:
        """Likelihood distance cap from the next update on. Up to the lookup table's built d_max
        this needs no rebuild (reads are clamped); above it the cap stays at the built value,
        because the table holds nothing farther (``d_max`` tells the effective value; a larger
        one needs a table built for it, see set_lookup)."""
        d_max = float(d_max)
        if not (d_max > 0 and math.isfinite(d_max)):
            raise LidarlocError(f"d_max must be > 0, got {d_max}")
        self._d_max_requested = d_max
        self._d_max = self.lookup.capped(d_max)

    def set_sigma(self, sigma: float) -> None:
        sigma = float(sigma)
        if not (sigma > 0 and math.isfinite(sigma)):
            raise LidarlocError(f"sigma must be > 0, got {sigma}")
        self._sigma = sigma

    def set_q_std(self, q_std) -> None:
        q = np.asarray(q_std, dtype=np.float64)
        if q.shape != (N_STATE,) or not np.all(np.isfinite(q)) or np.any(q < 0):
            raise LidarlocError("q_std must be 11 finite values ≥ 0")
        self._q_std = q.copy()

    def set_lookup(self, lookup: LookupTable) -> None:
        """Use another lookup table (e.g. rebuilt for a larger d_max) from the next update on."""
        self.lookup = lookup
        self._d_max = lookup.capped(self._d_max_requested)
        if self.dynamic is not None:
            self.dynamic.set_lookup(lookup)

    # ------------------------------------------------------------------------ initialisation
    @property
    def support(self) -> SupportGrid:
        if self._support is None:
            if self._map_points is None:
                raise LidarlocError("init_mode map_support needs the map (pass support= or map_points=)")
            self._support = support_for(self._map_points)
        return self._support

    def initialize(
        self, region=None, pose: np.ndarray | None = None, pose_std=None, speed: float | None = None
    ) -> None:
        """(Re)draw all particles with uniform weights.

        - default: globally, per ``cfg.init_mode``;
        - ``region=(x0, y0, x1, y1)``: x, y inside that rectangle (same mode rules otherwise);
        - ``pose`` (4×4): Gaussian around it with ``pose_std`` = 6 stds for x, y, z, yaw,
          pitch, roll (or one number: the x, y std; default DEFAULT_POSE_STD).
        ``speed``: initial speed for every particle instead of uniform [0, v_max].
        With KLD-sampling the count goes back to ``n_max`` (a fresh cloud is spread).
        """
        cfg, rng = self.cfg, self.rng
        if cfg.kld:
            self.n = self.n_max
        n = self.n
        s = np.zeros((n, N_STATE))
        if pose is not None:
            mean = pose_to_xyz_ypr(np.asarray(pose, dtype=np.float64))
            if pose_std is None:
                std = np.asarray(DEFAULT_POSE_STD)
            elif np.ndim(pose_std) == 0:
                std = np.asarray(DEFAULT_POSE_STD)
                std[:2] = float(pose_std)
            else:
                std = np.asarray(pose_std, dtype=np.float64).reshape(6)
            s[:, :6] = mean + rng.standard_normal((n, 6)) * std
        else:
            if region is not None:
                x0, y0, x1, y1 = (float(v) for v in region)
                if not (x1 > x0 and y1 > y0):
                    raise LidarlocError("init region must have x1 > x0 and y1 > y0")
            drawn = None
            if cfg.init_mode == "map_support":
                drawn = self.support.sample(rng, n, region)
            if drawn is not None:
                s[:, 0], s[:, 1], ground = drawn
                s[:, 2] = ground + cfg.sensor_height
                s[:, 4] = rng.standard_normal(n) * MAP_SUPPORT_PITCH_ROLL_STD
                s[:, 5] = rng.standard_normal(n) * MAP_SUPPORT_PITCH_ROLL_STD
            else:
                # the paper's box init (or map_support with no map cell in the region)
                lo, hi = self.bounds_min.copy(), self.bounds_max.copy()
                if region is not None:
                    lo[:2], hi[:2] = (x0, y0), (x1, y1)
                s[:, :3] = lo + rng.random((n, 3)) * (hi - lo)
                s[:, 4] = rng.uniform(-cfg.init_pitch, cfg.init_pitch, n)
                s[:, 5] = rng.uniform(-cfg.init_roll, cfg.init_roll, n)
            s[:, 3] = rng.uniform(-cfg.init_yaw, cfg.init_yaw, n)
        s[:, 6] = rng.uniform(0.0, cfg.v_max, n) if speed is None else float(speed)
        s[:, 7:10] = rng.standard_normal((n, 3)) * cfg.init_rate_std
        s[:, 10] = 0.0
        s[:, 3:6] = wrap_angle(s[:, 3:6])
        self.states = s
        self.log_weights = np.full(n, -math.log(n))
        self.log_likelihoods = np.zeros(n)
        self.protected_index = None
        if self.dynamic is not None:
            self.dynamic.reset()  # the far cells were judged at an estimate now discarded

    # ------------------------------------------------------------------------ filtering
    def predict(self, dt: float) -> None:
        """Propagate every particle through the motion model (weights unchanged)."""
        self.states = propagate(self.states, dt, self._q_std, self.rng)

    def update(self, scan: np.ndarray) -> None:
        """Weight by the likelihood of a prepared (M, 3) scan; normalise in log space."""
        pts = as_points(scan)
        self._scan_input = scan
        self._scan = np.ascontiguousarray(pts[:, :3], dtype=np.float32)
        if self.dynamic is not None:
            self._scan = self._reject_dynamic(self._scan)
        cfg = self.cfg
        self._weigh(self._scan)
        ll = log_likelihood_floored(
            self.states,
            self._scan,
            self.lookup,
            self._d_max,
            self._sigma,
            self.log_weights,
            temperature=self._temperature,
            unexplained_share=cfg.unexplained_share,
            point_weight=self._point_weight,
        )
        self.log_likelihoods = ll
        self.log_weights = self.log_weights + ll
        self._normalise()

    def _weigh(self, pts: np.ndarray) -> None:
        """Set the points the likelihood weighs, its effective temperature (T, or the number of
        points for the per-point mean) and how many points each weighed one stands for: all of
        ``pts`` at weight 1, or ``cfg.max_points`` of them at M/max_points, which estimates the
        same log-likelihood."""
        m = len(pts)
        self._temperature = effective_temperature(self.cfg.temperature, m)
        pick = subset_for(m, int(self.cfg.max_points))
        self._scan = pts if pick is None else np.ascontiguousarray(pts[pick])
        self._point_weight = 1.0 if pick is None else m / len(pick)

    def _reject_dynamic(self, pts: np.ndarray) -> np.ndarray:
        """The points of the scan the dynamic-point filter keeps, judged at the prior estimate
        (every point while the cloud is too spread for its mean to be a pose)."""
        w = self.weights
        xy = self.states[:, :2]
        mean_xy = w @ xy
        spread = float(np.sqrt(np.max(w @ (xy - mean_xy) ** 2)))
        if not spread < MAX_SPREAD:
            self.dynamic.reset()
            return pts
        pose = np.empty(6)
        pose[:3] = w @ self.states[:, :3]
        angles = self.states[:, 3:6]
        pose[3:] = np.arctan2(w @ np.sin(angles), w @ np.cos(angles))
        keep = self.dynamic.keep_mask(pts, pose)
        return pts if keep.all() else np.ascontiguousarray(pts[keep])

    def _normalise(self) -> None:
        lw = self.log_weights
        m = float(np.max(lw))
        self.log_weights = lw - (m + math.log(float(np.sum(np.exp(lw - m)))))

    @property
    def weights(self) -> np.ndarray:
        w = np.exp(self.log_weights)
        return w / w.sum()

    def n_eff(self) -> float:
        w = self.weights
        return float(1.0 / np.dot(w, w))

    def resample_if_needed(self, protect: int | None = None) -> bool:
        """Systematic resampling when N_eff < resample_threshold · N. ``protect``: a particle
        index that survives unchanged; afterwards ``protected_index`` is where it is (its own
        index, except when KLD-sampling shrank the count below it: then the last slot).
        Returns whether it resampled."""
        if protect is not None:
            protect = int(protect)
            if not 0 <= protect < self.n:
                raise LidarlocError(f"protected particle {protect} out of range (N = {self.n})")
        self.protected_index = protect
        if self.n_eff() >= self.cfg.resample_threshold * self.n:
            return False
        cfg = self.cfg
        if cfg.kld:
            n_max = self.n_max
            # a random order makes every prefix of the systematic draw a fair sample (module docstring)
            idx = systematic_resample(self.weights, n_max, self.rng)[self.rng.permutation(n_max)]
            n_new, self.kld_bins = kld_count(
                bin_keys(self.states[idx], cfg.kld_bin_xy, cfg.kld_bin_yaw),
                cfg.kld_epsilon,
                cfg.kld_z,
                cfg.kld_min,
                n_max,
            )
            idx = idx[:n_new]
        else:
            idx = systematic_resample(self.weights, self.n, self.rng)
        if protect is not None:
            self.protected_index = protect if protect < len(idx) else len(idx) - 1
            idx[self.protected_index] = protect
        self.states = self.states[idx]
        self.log_likelihoods = self.log_likelihoods[idx]
        self.n = len(idx)
        self.log_weights = np.full(self.n, -math.log(self.n))
        return True

    def set_n_particles(self, n: int) -> None:
        """Resample (systematic, by the current weights) to ``n`` particles, uniform weights;
        ``n`` is also the count of a fresh cloud and KLD-sampling's ceiling from now on."""
        n = int(n)
        if n < 1:
            raise LidarlocError(f"n_particles must be ≥ 1, got {n}")
        idx = systematic_resample(self.weights, n, self.rng)
        self.states = self.states[idx]
        self.log_likelihoods = self.log_likelihoods[idx]
        self.n = self.n_max = n
        self.log_weights = np.full(n, -math.log(n))
        self.protected_index = None

    def set_particle(self, j: int, state) -> None:
        """Overwrite particle j's state (S2M sample update); call reweight(j) after."""
        st = np.asarray(state, dtype=np.float64).reshape(N_STATE).copy()
        st[3:6] = wrap_angle(st[3:6])
        self.states[int(j)] = st

    def reweight(self, j: int, scan: np.ndarray | None = None) -> float:
        """Recompute particle j's likelihood for the current scan (or ``scan``, which then
        becomes the current scan) and swap it into its log-weight; returns the new log-likelihood.

        ``scan`` being the very array the last update() weighed (the same object) keeps that
        update's points (after dynamic-point rejection) and temperature; another array is used
        whole, with the temperature recomputed for its point count."""
        if scan is not None and scan is not self._scan_input:
            self._scan_input = scan
            self._weigh(np.ascontiguousarray(np.asarray(scan)[:, :3], dtype=np.float32))
        if self._scan is None:
            raise LidarlocError("reweight needs a scan: call update() first or pass one")
        j = int(j)
        # same point order as update() sums in, so that ll_new − ll_old has no rounding offset
        pts = self._scan[scrambled_order(len(self._scan))]
        ll = float(
            log_likelihood(
                self.states[j : j + 1],
                pts,
                self.lookup,
                self._d_max,
                self._sigma,
                temperature=self._temperature,
                unexplained_share=self.cfg.unexplained_share,
                point_weight=self._point_weight,
            )[0]
        )
        self.log_weights[j] += ll - self.log_likelihoods[j]
        self.log_likelihoods[j] = ll
        self._normalise()
        return ll

    # ------------------------------------------------------------------------ output
    def estimate(self) -> Estimate:
        """The weighted summary of the particles as they are now (see :func:`.estimate.weighted_estimate`)."""
        return weighted_estimate(self.states, self.weights, self.log_weights)

    # ------------------------------------------------------------------------ resuming
    def checkpoint(self) -> dict[str, np.ndarray]:
        """The filter's exact state between two scans, as arrays (float64 kept as it is, the random
        generator's state as JSON): :meth:`restore` on a filter with the same configuration and
        lookup table continues bit for bit as this one would."""
        import json

        out = {
            "states": self.states.copy(),
            "log_weights": self.log_weights.copy(),
            "log_likelihoods": self.log_likelihoods.copy(),
            "meta": np.array(
                json.dumps(
                    {
                        "n": int(self.n),
                        "n_max": int(self.n_max),
                        "rng": self.rng.bit_generator.state,
                        "protected_index": self.protected_index,
                        "kld_bins": self.kld_bins,
                    }
                )
            ),
        }
        if self.dynamic is not None:
            out.update({f"dynamic_{k}": v for k, v in self.dynamic.checkpoint().items()})
        return out

    def restore(self, data: dict[str, np.ndarray]) -> None:
        """Take the state :meth:`checkpoint` saved."""
        import json

        meta = json.loads(str(data["meta"]))
        self.states = np.array(data["states"], dtype=np.float64)
        self.log_weights = np.array(data["log_weights"], dtype=np.float64)
        self.log_likelihoods = np.array(data["log_likelihoods"], dtype=np.float64)
        self.n = int(meta["n"])
        self.n_max = int(meta.get("n_max", self.cfg.n_particles))
        if self.states.shape != (self.n, N_STATE) or self.log_weights.shape != (self.n,):
            raise LidarlocError("particle filter checkpoint: inconsistent particle count")
        self.rng.bit_generator.state = meta["rng"]
        self.protected_index = meta["protected_index"]
        self.kld_bins = meta["kld_bins"]
        self._scan = self._scan_input = None
        if self.dynamic is not None:
            if "dynamic_keys" in data:
                self.dynamic.restore({k[len("dynamic_") :]: v for k, v in data.items() if k.startswith("dynamic_")})
            else:  # recorded without dynamic-point rejection
                self.dynamic.reset()

    def step(self, scan: np.ndarray, dt: float, protect: int | None = None) -> Estimate:
        """predict(dt) → update(scan) → estimate() → resample_if_needed(protect). The estimate is
        taken before resampling (the weighted set is the better summary); ``resampled`` says
        whether the particles were resampled afterwards."""
        self.predict(dt)
        self.update(scan)
        est = self.estimate()
        return replace(est, resampled=self.resample_if_needed(protect))
