"""Measuring the result: stabilization metrics, evaluation against ground truth (relative pose
error, OpenCV odometry, shake), the paper's protocol and re-runs of a stage on a recording.

Imports only core, stream and io below it.
"""
