"""lidarloc: LiDAR-only localization in a prior map (scan-matching particle filter).

The repository's root is the ``lidarloc`` package: ``core/`` (the localizer, no UI imports) is
``lidarloc.core`` and ``app/`` (the command line, the viewer, the benchmarks) is ``lidarloc.app``.
Inside the package, modules import each other relatively, so editors and other tools that read
the tree without installing it follow every import.
"""

import os as _os

# numba's default threading layer tries TBB first; the TBB that ships beside open3d is too old
# for numba and it warns on every run. OpenMP works, and unlike the "workqueue" fallback it is
# safe when the PF and S2M threads launch parallel kernels at the same time. Users may override.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

__version__ = "0.1.0"
