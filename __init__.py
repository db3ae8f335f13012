"""lidarloc: LiDAR-only localization in a prior map (scan-matching particle filter).

The public API — what scripts, notebooks and the examples use; everything else may move::

    from lidarloc import Localizer, SourceSpec, load_config, open_sequence

    cfg = load_config(overrides=["pf.sigma=0.7"])        # the paper's defaults, then changes
    seq = open_sequence(SourceSpec(scans=40), cfg)        # the built-in town (or KITTI, a bag …)
    with Localizer(seq, cfg) as loc:
        loc.run()                                          # loc.records: one ScanRecord a scan

- the localizer: :class:`Localizer`, :class:`Config` and :func:`load_config`;
- sources and maps: :class:`SourceSpec`, :func:`open_sequence`, :func:`open_world` (the prior
  map and its precomputed tables, :class:`World`);
- runs: :func:`open_recording` (a recorded run's arrays), :func:`open_branch` (a recorded run
  continued from one of its scans with other settings), :func:`summarize_run` and
  :func:`write_run` (the files ``lidarloc run`` writes);
- what a run yields: :class:`Snapshot` (the state after a scan), :class:`ScanRecord` (one row of
  ``scans.csv``), :class:`Event`, :class:`S2MView`, :class:`Recording`;
- :class:`LidarlocError`: every refusal and bad input (one line, meant for the user).

The names load on first use, so ``import lidarloc`` stays quick (the command line starts from
it). The repository's root is the ``lidarloc`` package: ``core/`` (the localizer, no UI imports)
is ``lidarloc.core`` and ``app/`` (the command line, the viewer, the benchmarks) is
``lidarloc.app``; inside the package, modules import each other relatively.
"""

from __future__ import annotations

import importlib as _importlib
import os as _os
from typing import TYPE_CHECKING

# numba's default threading layer tries TBB first; the TBB that ships beside open3d is too old
# for numba and it warns on every run. OpenMP works, and unlike the "workqueue" fallback it is
# safe when the PF and S2M threads launch parallel kernels at the same time. Users may override.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

from .core.version import VERSION as __version__  # (core keeps it: core never imports this file)

#: Each public name and the module it lives in (relative to this package).
_PUBLIC = {
    "Config": ".core.config",
    "load_config": ".core.config",
    "Localizer": ".core.localizer",
    "SourceSpec": ".core.sequences.factory",
    "open_sequence": ".core.sequences.factory",
    "World": ".core.maps.world",
    "open_world": ".core.maps.world",
    "Recording": ".core.runs.recording",
    "open_recording": ".core.runs.branch",
    "open_branch": ".core.runs.branch",
    "summarize_run": ".core.runs.results",
    "write_run": ".core.runs.results",
    "Event": ".core.snapshot",
    "S2MView": ".core.snapshot",
    "ScanRecord": ".core.snapshot",
    "Snapshot": ".core.snapshot",
    "LidarlocError": ".core.errors",
}

__all__ = [  # the keys of _PUBLIC (a test keeps them equal), written out for linters and editors
    "Config",
    "Event",
    "LidarlocError",
    "Localizer",
    "Recording",
    "S2MView",
    "ScanRecord",
    "Snapshot",
    "SourceSpec",
    "World",
    "__version__",
    "load_config",
    "open_branch",
    "open_recording",
    "open_sequence",
    "open_world",
    "summarize_run",
    "write_run",
]

if TYPE_CHECKING:  # what editors and type checkers see; at run time the names load on first use
    from .core.config import Config, load_config
    from .core.errors import LidarlocError
    from .core.localizer import Localizer
    from .core.maps.world import World, open_world
    from .core.runs.branch import open_branch, open_recording
    from .core.runs.recording import Recording
    from .core.runs.results import summarize_run, write_run
    from .core.sequences.factory import SourceSpec, open_sequence
    from .core.snapshot import Event, S2MView, ScanRecord, Snapshot


def __getattr__(name: str):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'lidarloc' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module, __name__), name)
    globals()[name] = value  # the next lookup is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
