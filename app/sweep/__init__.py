"""Many runs of one source: parameter sweeps (``lidarloc sweep``), automatic tuning (``lidarloc
tune``) and the robustness matrix, in a local process pool or on Ray."""
