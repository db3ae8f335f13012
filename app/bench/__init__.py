"""The measurements behind BENCHMARKS.md, one module per ``lidarloc bench`` command."""
