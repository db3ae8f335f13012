"""Continue a recorded run from one of its scans with another σ, and compare the two runs.

    python examples/branch_and_compare.py out/run0 --step 20 --sigma 0.7 --out out/run0-sigma

The branch starts from the filter's exact state after that step (particles, random generator,
odometry, the match in flight) and plays on to the end with the new σ; with the replay clock a
branch with no change would repeat the original bit for bit.
"""

import argparse
from pathlib import Path

import numpy as np
from lidarloc import open_branch, open_recording, summarize_run, write_run


def after(rec, step: int) -> np.ndarray:
    errors = np.asarray(rec.error_m, float)[step + 1 :]
    return errors[np.isfinite(errors)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--step", type=int, required=True)
    parser.add_argument("--sigma", type=float, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    original = open_recording(args.run)
    with open_branch(original, args.step, [f"pf.sigma={args.sigma}"]) as loc:
        errors = []
        while not loc.done:
            snap = loc.step()
            errors.append(np.nan if snap.error_m is None else snap.error_m)
        write_run(loc, args.out, summarize_run(loc, 0.0))

    def rmse(e):
        e = np.asarray(e, float)
        e = e[np.isfinite(e)]
        return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")

    print(
        f"after step {args.step}: RMSE original σ {rmse(after(original, args.step)):.3f} m, "
        f"σ {args.sigma:g} {rmse(errors):.3f} m; branch written to {args.out}"
    )


if __name__ == "__main__":
    main()
