"""lidarloc: LiDAR-only localization in a prior map (scan-matching particle filter).

The code lives in the repository's top-level ``core/`` (the localizer, no UI imports) and
``app/`` (CLI and viewer) folders; they are installed as ``lidarloc.core`` and ``lidarloc.app``.
"""

import os as _os

# numba's default threading layer tries TBB first; the TBB that ships beside open3d is too old
# for numba and it warns on every run. OpenMP works, and unlike the "workqueue" fallback it is
# safe when the PF and S2M threads launch parallel kernels at the same time. Users may override.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

__version__ = "0.1.0"
