"""The comparison's plots: per regressed drive, both runs' error against the truth and inlier share
over the scans, the regressed stretches shaded and the first diverging scan marked, as PNG bytes
for the HTML report to carry inline (base64): one file that opens from disk, anywhere."""

from __future__ import annotations

import base64
import io

import numpy as np

from .figures import DriveRun

BASE_COLOR, NEW_COLOR, STRETCH_COLOR = "#7f7f7f", "#d62728", "#ff7f0e"


def _panels(base: DriveRun, new: DriveRun) -> list[tuple[str, str]]:
    """(column, axis label) of the curves worth drawing: the error only where there is truth."""
    panels = []
    if any(np.isfinite(d.table.get("error_m", np.zeros(0))).any() for d in (base, new)):
        panels.append(("error_m", "error (m, log)"))
    panels.append(("inlier_share", "inlier share"))
    return panels


def drive_plot_png(base: DriveRun, new: DriveRun, entries: list[dict], diverging: int | None) -> bytes:
    """The drive's plot (PNG): BASE grey, NEW red, ``entries``' stretches shaded."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    panels = _panels(base, new)
    fig, axes = plt.subplots(len(panels), 1, figsize=(8, 1.9 * len(panels) + 0.6), sharex=True, squeeze=False)
    try:
        for ax, (column, label) in zip(axes[:, 0], panels):
            for drive, color, name in ((base, BASE_COLOR, "BASE"), (new, NEW_COLOR, "NEW")):
                t = drive.table
                if column in t:
                    ax.plot(t["scan"], t[column], color=color, lw=1.0, label=name)
            for e in entries:
                if e["stretch"] is not None:
                    ax.axvspan(
                        e["stretch"]["first_scan"] - 0.5,
                        e["stretch"]["last_scan"] + 0.5,
                        color=STRETCH_COLOR,
                        alpha=0.2,
                    )
            if diverging is not None:
                ax.axvline(diverging, color="k", ls="--", lw=0.8)
            if column == "error_m":  # metres before the first fix, centimetres after: both visible
                ax.set_yscale("log")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0, 0].legend(loc="upper right", fontsize=8)
        where = "" if diverging is None else f" · first diverging scan {diverging} (dashed)"
        axes[0, 0].set_title(f"{new.name}: BASE grey, NEW red{where}", fontsize=9)
        axes[-1, 0].set_xlabel("scan")
        fig.tight_layout()
        buf = io.BytesIO()
        # no Software entry: the file names nothing outside itself
        fig.savefig(buf, format="png", dpi=72, metadata={"Software": None})
        return buf.getvalue()
    finally:
        plt.close(fig)


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")
