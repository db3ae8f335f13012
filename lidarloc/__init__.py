"""lidarloc: LiDAR-only localization in a prior map (scan-matching particle filter).

The code lives in the repository's top-level ``core/`` (the localizer, no UI imports) and
``app/`` (CLI and viewer) folders; they are installed as ``lidarloc.core`` and ``lidarloc.app``.
"""

__version__ = "0.1.0"
