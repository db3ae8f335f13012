"""bench city's figures from its global-match rows: lidarloc's global localization on every row,
the exact tiled search's and the whole-map search's on the rows that ran them, and the scans a
search placed elsewhere, named by district on a generated city. Kept apart from
:mod:`.city_rows`, whose code fingerprints the kept rows: a change to how the rows are summed up
does not throw them away."""

from __future__ import annotations

import numpy as np

from .city_rows import missed
from .common import median


def global_figures(rows: list[dict], seq, whole_map: bool) -> dict:
    """The global matches' figures: lidarloc's (the candidates and the second opinion) on every
    row, the exact tiled search's (and the whole-map search's) on the rows that ran them."""
    out: dict = {"global_scans": len(rows)}
    out["global_match_ms_median"] = median(r["global_ms"] for r in rows)
    out["global_prepare_ms_median"] = median(r["prepare_ms"] for r in rows)
    out["global_success"] = float(np.mean([r["global_success"] for r in rows]))
    out["global_confident_wrong"] = sum(r["global_confident_wrong"] for r in rows)
    out["global_ambiguous"] = sum(r["global_ambiguous"] for r in rows)
    out["global_exact_fallbacks"] = sum(r["global_search"] == "exact" for r in rows)
    out["second_opinion_ms_median"] = median(r["second_ms"] for r in rows)
    out["second_opinion_agrees"] = float(np.mean([r["second_agrees"] for r in rows]))
    district_at = district_namer(seq)
    out["global_failed_scans"] = [
        missed({**r, "tiled_pose": r["global_pose"], "tiled_err_m": r["global_err_m"], "tiled_score": r["global_score"]},
               seq.pose(r["scan"]), district_at) | {"ambiguous": r["global_ambiguous"], "reason": r["global_reason"]}
        for r in rows if not r["global_success"]
    ]  # fmt: skip
    exact = [r for r in rows if "tiled_ms" in r]
    out["exact_scans"] = len(exact)
    out["exact_ms_median"] = median(r["tiled_ms"] for r in exact) if exact else None
    out["exact_success"] = float(np.mean([r["tiled_success"] for r in exact])) if exact else None
    # the same answer: both right, or both at the same place
    out["exact_agrees_with_candidates"] = (
        float(np.mean([r["tiled_success"] == r["global_success"] for r in exact])) if exact else None
    )
    out["exact_failed_scans"] = [missed(r, seq.pose(r["scan"]), district_at) for r in exact if not r["tiled_success"]]
    out["tiles_searched_median"] = median(r["tiled_tiles_searched"] for r in exact) if exact else None
    out["tiled_nodes_median"] = median(r["tiled_nodes"] for r in exact) if exact else None
    whole = [r for r in exact if "whole_ms" in r]
    if whole_map and whole:
        out["whole_map_ms_median"] = median(r["whole_ms"] for r in whole)
        out["whole_map_success"] = float(np.mean([r["whole_success"] for r in whole]))
        out["tiled_score_equals_whole_map"] = float(np.mean([r["same_as_whole"] for r in whole]))
        out["whole_map_nodes_median"] = median(r["whole_nodes"] for r in whole)
    else:
        out["whole_map_ms_median"] = out["whole_map_success"] = None
    return out


def district_namer(seq):
    """``(x, y) → district name`` on a generated city (its district map), else None."""
    districts = getattr(getattr(seq, "town", None), "districts", None)
    if districts is None:
        return None
    from ...core.sim.town.districts import STYLE_NAMES

    return lambda x, y: STYLE_NAMES[int(districts.style_at(x, y))]
