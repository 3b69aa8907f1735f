"""The paint carried onto the hand's surface: a contact value per point of the capsule template.

The per-view paint masks of a canonical take say where paint is in the images; with the
calibration and the pose annotate fitted for the frame group the paint was segmented in, every
template point gets the share of the views that see it (in front, facing the camera, inside the
hand mask) that see paint there (dataset_tools.segmentation.contact_votes). The template's points
are the hand's surface in the rest pose of the subject's bone lengths, so the values can be
compared across takes and with any model built on the same skeleton.
"""

from __future__ import annotations

import numpy as np

from dataset_tools.segmentation import contact_votes
from manus_core.cameras import CameraRig

from .template import capsule_template


def paint_on_surface(rig: CameraRig, paint: np.ndarray, hand_masks: np.ndarray, angles: np.ndarray,
                     bone_lengths: np.ndarray) -> dict[str, np.ndarray]:
    """Arrays for DATASET.h5: `paint/contact` (P,) float32 in [0, 1] (NaN: no view sees the point),
    `paint/voters` (P,) the views that voted, `paint/points_rest` (P,3) and `paint/bone` (P,) the
    template's points. paint and hand_masks (C,H,W) of the rig's cameras; angles (26,) the pose."""
    template = capsule_template(bone_lengths)
    points, normals = template.posed(angles, normals=True)
    value, voters = contact_votes(rig, points, paint, hand_masks, normals)
    return {"paint/contact": value.astype(np.float32), "paint/voters": voters.astype(np.int32),
            "paint/points_rest": template.points_rest.astype(np.float32), "paint/bone": template.bone.astype(np.int32)}
