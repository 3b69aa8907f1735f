"""Offline processing of recorded takes: calibration, keypoints, triangulation, hand fitting."""
