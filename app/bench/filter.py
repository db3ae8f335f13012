"""``lidarloc bench filter``: does the filter's uncertainty mean something while it tracks?

The tracking study behind the choice of likelihood: each likelihood option runs with the
particles started around the true first pose (σ 1 m, 5°: a tracking start, no global search), no
S2M (so only the PF's own likelihood decides), over the whole source, for several seeds. Per
option, medians over the runs of:

- ``n_eff_share``: N_eff / N after the first 5 scans. With the paper's likelihood summed over
  ~10⁴ points the weights sit on one particle (N_eff ≈ 1, a share of 0.001 at 1000 particles):
  the std, the ellipse and the localization rule then say nothing;
- ``error_m``: the position error against the truth (median over scans, then over runs);
- ``consistency_2sigma``: the share of scans whose true x-y position lies inside the estimate's
  2σ ellipse (target ≥ 85 % for a filter whose uncertainty can be trusted);
- ``pf_ms``: the PF step (median), as a cost indication (the machine's load is reported).

Options (``--set`` names), each over the paper's likelihood (untempered, every point, no
unexplained share, a fixed particle count) whatever the defaults: ``paper``, ``default`` (the
defaults' likelihood: unexplained share, temperature, point budget and KLD-sampling as in
``core/config.py``), ``T=10``, ``T=100``, ``T=<any>`` (``pf.temperature``), ``per-point mean``
(``pf.temperature=0``), ``unexplained 0.1`` (``pf.unexplained_share=0.1``, the beam model's
z_rand at the paper's temperature). Other ``--set`` values apply to every option.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from ...core.config import PRESETS, Config, PFConfig, apply_overrides
from ...core.geometry import pose_to_xyz_ypr
from ...core.localizer import Localizer
from ...core.rules.truth import inside_2sigma
from .common import load_avg, machine

# the filter's settings as the paper preset pins them; every option starts from these, and
# "default" puts the same settings back to the defaults
_PAPER_PF = {key: value for key, value in PRESETS["paper"].items() if key.startswith("pf.")}
PAPER_LIKELIHOOD = [f"{key}={value}" for key, value in _PAPER_PF.items()]
OPTIONS: dict[str, list[str]] = {
    "paper": [],
    "default": [f"{key}={getattr(PFConfig(), key[len('pf.') :])}" for key in _PAPER_PF],
    "T=10": ["pf.temperature=10"],
    "T=100": ["pf.temperature=100"],
    "per-point mean": ["pf.temperature=0"],
    "unexplained 0.1": ["pf.unexplained_share=0.1"],
}
BURN_IN = 5  # scans the start's spread needs to settle
INIT_SIGMA_XY = 1.0  # m
INIT_SIGMA_YAW_DEG = 5.0
TARGET_CONSISTENCY = 0.85


def _tempered(name: str) -> list[str] | None:
    """``T=<number>``: any temperature, for a sweep."""
    if name.startswith("T="):
        try:
            t = float(name[2:])
        except ValueError:
            return None
        return [f"pf.temperature={t:g}"] if t >= 1 else None
    return None


def _tracking_spec(spec, seq):
    x, y, _, yaw, _, _ = pose_to_xyz_ypr(seq.pose(0))
    return dataclasses.replace(spec, init=f"{x},{y},{np.degrees(yaw)},{INIT_SIGMA_XY},{INIT_SIGMA_YAW_DEG}")


def _one_run(seq, cfg: Config, cache_root) -> dict:
    with Localizer(seq, cfg, cache_root) as loc:
        share, err, inside, pf = [], [], [], []
        while not loc.done:
            snap = loc.step()
            pf.append(snap.pf_ms)
            if snap.scan_index < BURN_IN or snap.gt_pose is None:
                continue
            share.append(snap.n_eff_share)
            err.append(snap.error_m)
            inside.append(inside_2sigma(snap.mean_pose[:2, 3] - snap.gt_pose[:2, 3], snap.cov_xyz[:2, :2]))
    return {
        "n_eff_share": float(np.median(share)),
        "error_m": float(np.median(err)),
        "consistency_2sigma": float(np.mean(inside)),
        "pf_ms": float(np.median(pf)),
    }


def run(
    spec, open_seq, cfg: Config, seeds: int = 3, options: list[str] | None = None, cache_root=None, progress=None
) -> dict:
    """The study on ``spec`` (``open_seq(spec)`` opens it); ``cfg`` is the base configuration."""
    names = options or list(OPTIONS)
    chosen = {n: OPTIONS[n] if n in OPTIONS else _tempered(n) for n in names}
    unknown = [n for n, sets in chosen.items() if sets is None]
    if unknown:
        from ...core.errors import LidarlocError

        raise LidarlocError(f"unknown filter option {unknown[0]!r}: choose from {', '.join(OPTIONS)} or T=<number ≥ 1>")
    seq = open_seq(spec)
    if not seq.has_poses:
        from ...core.errors import LidarlocError

        raise LidarlocError("bench filter needs a source with ground truth (the start is placed around it)")
    seq = open_seq(_tracking_spec(spec, seq))
    results = {}
    done = 0
    for name in names:
        runs = []
        for seed in range(seeds):
            c = apply_overrides(
                copy.deepcopy(cfg),
                ["s2m.enabled=false", "localize.recorded_odometry=true", *PAPER_LIKELIHOOD, *chosen[name]],
            )
            c.seed = seed
            runs.append(_one_run(seq, c, cache_root))
            done += 1
            if progress is not None:
                progress(done, len(names) * seeds)
        results[name] = {key: round(float(np.median([r[key] for r in runs])), 4) for key in runs[0]}
        results[name]["set"] = chosen[name]
    return {
        "options": results,
        "seeds": seeds,
        "particles": cfg.pf.n_particles,
        "scans": len(seq),
        "start": f"around the true first pose, σ {INIT_SIGMA_XY:g} m, {INIT_SIGMA_YAW_DEG:g}°; no S2M",
        "target_consistency_2sigma": TARGET_CONSISTENCY,
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
    }
