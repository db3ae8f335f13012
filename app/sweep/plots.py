"""A sweep's plots: each metric against each swept entry (every run as a dot, the median per value
as a line), and with two swept entries a heat map of the median RMSE and the success share."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: the run figures plotted against each swept entry
PLOTTED = ("rmse_after_localized_m", "success", "consistency_2sigma", "pf_ms_median")


def median_or_none(values) -> float | None:
    """The median of the values that are not None (None when there are none)."""
    vals = [float(v) for v in values if v is not None]
    return float(np.median(vals)) if vals else None


def _num(v) -> float | None:
    if isinstance(v, bool):
        return float(v)
    return float(v) if isinstance(v, (int, float)) else None


def write_plots(folder: Path, keys: list[str], rows: list[dict], combos: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    done = [r for r in rows if r["status"] == "done"]
    for key in keys:
        values = list(dict.fromkeys(r[key] for r in rows))
        fig, axes = plt.subplots(1, len(PLOTTED), figsize=(4 * len(PLOTTED), 3.2))
        for ax, metric in zip(axes, PLOTTED):
            for i, v in enumerate(values):
                ys = [_num(r[metric]) for r in done if r[key] == v]
                ys = [y for y in ys if y is not None]
                ax.plot([i] * len(ys), ys, "o", color="tab:blue", alpha=0.4, ms=4)
            med = [median_or_none(_num(r[metric]) for r in done if r[key] == v) for v in values]
            ax.plot(range(len(values)), [np.nan if m is None else m for m in med], "-", color="tab:red")
            ax.set_xticks(range(len(values)), [str(v) for v in values])
            ax.set_xlabel(key)
            ax.set_title(metric, fontsize=9)
            ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(folder / f"{key}.png", dpi=90)
        plt.close(fig)
    if len(keys) == 2:
        _heatmap(folder / "heatmap.png", keys, combos, plt)


def _heatmap(path: Path, keys: list[str], combos: list[dict], plt) -> None:
    xs = list(dict.fromkeys(c[keys[0]] for c in combos))
    ys = list(dict.fromkeys(c[keys[1]] for c in combos))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (field, title, cmap, lim) in zip(
        axes,
        (
            ("rmse_after_localized_m_median", "RMSE after localization, median (m)", "viridis_r", (0.0, None)),
            ("success", "success (share of runs)", "RdYlGn", (0.0, 1.0)),
        ),
    ):
        grid = np.full((len(ys), len(xs)), np.nan)
        for c in combos:
            v = c[field]
            grid[ys.index(c[keys[1]]), xs.index(c[keys[0]])] = np.nan if v is None else v
        im = ax.imshow(grid, cmap=cmap, vmin=lim[0], vmax=lim[1], origin="lower", aspect="auto")
        for (j, i), v in np.ndenumerate(grid):
            # white on the dark end of the colour map, black on the light end
            shade = 0.5 if np.isnan(v) else float(im.norm(v))
            dark = shade > 0.6 if cmap == "viridis_r" else False
            ax.text(
                i,
                j,
                "–" if np.isnan(v) else f"{v:.2f}",
                ha="center",
                va="center",
                fontsize=8,
                color="white" if dark else "black",
            )
        ax.set_xticks(range(len(xs)), [str(x) for x in xs])
        ax.set_yticks(range(len(ys)), [str(y) for y in ys])
        ax.set_xlabel(keys[0])
        ax.set_ylabel(keys[1])
        ax.set_title(title, fontsize=9)
        fig.colorbar(im, ax=ax)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
