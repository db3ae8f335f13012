"""The particle filter (PF block): the 11-state motion model, scan preparation, the lookup-table
likelihood, KLD-sampling, dynamic points, and the "why" computations on its own kernel.
"""
