"""Baselines the benchmark compares the pipeline with: GNSS-only and RoadMap-style ICP.

Both share :mod:`csr_core.baselines.gnss_poses` (raw GNSS poses, outages bridged by odometry)
and :mod:`csr_core.baselines.naive_fusion` (elements placed with the poses, stitched per trip),
so they differ only in how the trips' poses are obtained, as the paper's comparison does.
"""
