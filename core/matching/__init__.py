"""Scan-to-map matching (RS, S2M and SU blocks): M3RSM branch and bound on the BEV pyramid, GICP
refinement, its child process, and when a match starts, lands or is cancelled.
"""
