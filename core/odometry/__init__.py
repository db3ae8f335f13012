"""Relative pose estimation (RPE block): KISS-ICP in its child process, the odometry feed the
localizer reads, recorded odometry, de-skewing.
"""
