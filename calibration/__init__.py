"""Calibration: camera intrinsics, camera-to-floor geometry, the P(loop | score) curve."""
