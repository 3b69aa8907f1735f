"""Calibration of the rig: target detection, intrinsics, extrinsics, bundle adjustment and the
camera file formats (`formats`: cameras.json, COLMAP, OpenCV YAML, EasyMocap, MANUS, anipose,
caliscope, CMU Panoptic)."""
