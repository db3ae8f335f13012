"""A run's outputs and afterlife: result files, the recording (format, writer, reader), resuming
and branching from any recorded step.
"""
