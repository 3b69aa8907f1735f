"""The Python surface of manus-capture: the pipeline as functions, in the order it runs.

    from manus_capture import api

    rig = api.make_rig("cube53", cameras=12, resolution=(320, 180), sync="software-trigger")
    taken = api.record_take(rig, "s01", "calib", "calibration", 1.0)             # -> TakeResult
    report = api.sync_take("s01/calib")                                           # sync_report.json
    calib = api.calibrate_rig(take="s01/calib", tags="s01/tags.json", intrinsics="lenses.json",
                              output="calib")                                     # -> RigCalibration
    cams = api.load_cameras("calib")                                              # -> CameraRig
    done = api.annotate(["s01/grasp"], "calib", "DATASET.h5")                     # -> AnnotateSummary
    masks = api.segment_take("s01/grasp", cams, "s01/calib")                      # -> Segmentation
    inputs = api.ModelInputs.prepare(cams, "DATASET.h5", "s01/hand", "s01/object", "s01/calib")
    models = inputs.train(range(len(cams)))                                       # -> TrainedModels
    fit = api.refine_take("DATASET.h5", "s01/grasp", "s01/grasp", cams, models.hand)   # -> RefineResult
    api.write_refined("DATASET.h5", "s01/grasp", fit, {})                          # joint_angles_refined
    maps = api.model_contacts(models.hand, angles, models.object)                 # -> ContactMaps
    scores, _ = api.score_contacts(models.hand, pose, maps.accumulated, cams, paint, views)  # -> Scores

Long functions take `progress=` (a `Progress`: progress(stage, done, total)); every error they
raise on purpose is a `ManusError` whose `exit_code` the CLI uses. docs/architecture.md says
where each piece lives.
"""

from __future__ import annotations

from dataset_tools.annotate import AnnotateOptions, AnnotateSummary, annotate
from dataset_tools.calibration.formats import load_cameras, save_cameras
from dataset_tools.calibration.result import RigCalibration
from dataset_tools.calibration.rig import calibrate_rig
from dataset_tools.hand.ik import fit_hand
from dataset_tools.keypoints import Detector, hand_keypoint_detector
from dataset_tools.keypoints.keypoints2d import CameraKeypoints, detect_take
from dataset_tools.one_euro import one_euro
from dataset_tools.segmentation.takes import Segmentation, segment_take, write_masks
from dataset_tools.sync import TakeGroups, frame_groups, sync_take
from dataset_tools.triangulation import triangulate
from dataset_tools.undistort import undistort_points
from manus_capture.builder import ModelInputs, TrainedModels
from manus_capture.contacts import ContactMaps, model_contacts, write_contacts
from manus_capture.evaluate import Scores, canonical_pose, pick_views, score_contacts
from manus_capture.refine import RefineOptions, RefineResult, refine_take, write_refined
from manus_capture.splat import rasterize
from manus_capture.splat.checkpoint import load_checkpoint, save_checkpoint
from manus_capture.template import capsule_template
from manus_core.cameras import CameraRig
from manus_core.dataset import Dataset, TakeAnnotation, read_dataset, take_key
from manus_core.errors import InputError, ManusError
from manus_core.progress import Progress, silent
from manus_core.rig_config import RigConfig, load_rig
from manus_core.skeleton import HandSkeleton
from manus_core.take import Take
from rig.layouts import make_rig
from rig.record import RecordOptions, TakeResult, record_take

__all__ = [
    # errors and progress
    "ManusError", "InputError", "Progress", "silent",
    # 1. record: a rig configuration, one take of every camera
    "RigConfig", "load_rig", "make_rig", "RecordOptions", "TakeResult", "record_take", "Take",
    # 2. sync: the validation report and the frame groups every later stage uses
    "sync_take", "TakeGroups", "frame_groups",
    # 3. calibrate
    "calibrate_rig", "RigCalibration", "CameraRig", "load_cameras", "save_cameras",
    # 4. detect and annotate: 2D keypoints, triangulation, IK, filter -> DATASET.h5
    "hand_keypoint_detector", "Detector", "detect_take", "CameraKeypoints",
    "annotate", "AnnotateOptions", "AnnotateSummary", "take_key", "read_dataset", "Dataset", "TakeAnnotation",
    # 5. segment: hand, object and paint masks
    "segment_take", "Segmentation", "write_masks",
    # 6. reconstruct: the object's Gaussians and MANUS-Hand
    "ModelInputs", "TrainedModels", "save_checkpoint", "load_checkpoint",
    # 6b. refine: the poses against the images through MANUS-Hand
    "refine_take", "RefineOptions", "RefineResult", "write_refined",
    # 7. contacts and 8. evaluate
    "model_contacts", "ContactMaps", "write_contacts", "canonical_pose", "pick_views", "score_contacts", "Scores",
    "capsule_template",
    # the low-level pieces
    "undistort_points", "triangulate", "one_euro", "HandSkeleton", "fit_hand", "rasterize",
]
