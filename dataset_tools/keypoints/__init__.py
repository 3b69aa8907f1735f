"""ONNX 2D hand keypoint detection (MediaPipe order, full-image pixels) and model installation.

    from dataset_tools.keypoints import hand_keypoint_detector
    # after `manus-capture models install mediapipe-hand`:
    detector = hand_keypoint_detector("mediapipe-hand")
    keypoints = detector.detect(image_bgr, boxes)           # (N,21,3) [x, y, confidence]
"""

from manus_core.errors import InstallError, ModelError, ModelNotInstalledError

from .detector import Detector, hand_keypoint_detector
from .models import JOINT_NAMES, NUM_JOINTS

__all__ = ["Detector", "hand_keypoint_detector", "InstallError", "ModelError", "ModelNotInstalledError",
           "JOINT_NAMES", "NUM_JOINTS"]
