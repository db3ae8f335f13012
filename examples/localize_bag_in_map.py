"""Localize a ROS bag in a point-cloud map and plot the error against the ground truth.

    python examples/localize_bag_in_map.py MAP.pcd DRIVE.mcap GT.tum [--out error.png]

The map file gives the prior map (its frame is the truth's); the bag's only PointCloud2 topic
gives the scans; the TUM file gives the truth, matched to the scans by time.
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from lidarloc import Localizer, SourceSpec, load_config, open_sequence


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", type=Path)
    parser.add_argument("bag", type=Path)
    parser.add_argument("gt", type=Path)
    parser.add_argument("--out", type=Path, default=Path("error.png"))
    args = parser.parse_args()

    cfg = load_config()  # the defaults; load_config(overrides=[...]) to change them
    seq = open_sequence(SourceSpec(map=args.map, bag=args.bag, gt=args.gt), cfg)
    with Localizer(seq, cfg) as loc:
        loc.run()
        scans = np.array([r.scan for r in loc.records])
        error = np.array([np.nan if r.error_m is None else r.error_m for r in loc.records])
        localized = np.array([r.localized for r in loc.records])

    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(scans, error, label="position error")
    ax.fill_between(scans, 0, np.nanmax(error), where=localized, alpha=0.15, label="localized")
    ax.set_xlabel("scan")
    ax.set_ylabel("error to the truth (m)")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    after = error[localized]
    rmse = float(np.sqrt(np.mean(after**2))) if after.size else float("nan")
    print(
        f"localized at scan {scans[localized][0] if localized.any() else None}; RMSE after: {rmse:.2f} m; plot: {args.out}"
    )


if __name__ == "__main__":
    main()
