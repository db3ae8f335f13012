"""Open a recorded run and plot its particles' N_eff and its error to the truth, scan by scan.

    python examples/plot_recording.py out/run0 [--out run0.png]

Every ``lidarloc run`` records into its folder (``recording/``); a recording reads as arrays, one
entry per processed scan, without running anything again.
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from lidarloc import open_recording


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--out", type=Path, default=Path("recording.png"))
    args = parser.parse_args()

    rec = open_recording(args.run)
    scans = rec.scan_index
    n_eff_share = rec.n_eff / rec.n_particles
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    top.plot(scans, 100 * n_eff_share)
    top.set_ylabel("N_eff (% of particles)")
    bottom.plot(scans, rec.error_m)
    bottom.set_ylabel("error to the truth (m)")
    bottom.set_xlabel("scan")
    for _step, event in rec.events:
        if event.kind == "localized":
            for ax in (top, bottom):
                ax.axvline(event.scan, color="green", linestyle=":")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"{rec.n} steps; N_eff {100 * n_eff_share.min():.1f}–{100 * n_eff_share.max():.1f} %; plot: {args.out}")


if __name__ == "__main__":
    main()
