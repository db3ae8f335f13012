"""The prior map and what is precomputed from it once and cached: fusion of the mapping drive's
scans or a map file, road removal, the nearest-distance lookup table, the bird's-eye-view pyramid.
"""
