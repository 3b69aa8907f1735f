"""Tags whose place in tags.json disagrees with the images: moved, mirrored, rotated or printed at
another size. Each tag's corners are triangulated by the calibrated cameras and compared with the
file; the calibration names these tags and solves again without them (rig.py)."""

from __future__ import annotations

import numpy as np

from manus_core.cameras import CameraRig

from ..triangulation import triangulate
from .boards import TagLayout
from .detect import Detection
from .tag_intrinsics import corner_pixels, without_poor_tags

# A tag whose four corners are all this far from tags.json is named. A tag printed 4 % small (the
# most tags.json's own check lets through) is 2.5 mm off at every corner; on the calibrated
# simulated cube (53 cameras, 640x360) the corners of correct tags triangulate 0.07 mm (median)
# from their place, a few single corners seen by two cameras at a slant up to 2.9 mm.
OFF_MM = 1.5
# with --refine-tags tags.json is a measurement by hand, which the adjustment holds to 2 mm (one
# sigma): a tag is named when it is four sigma off
REFINED_OFF_MM = 8.0
# a reordering of the corners explains a tag when it brings every corner this close
EXPLAINED_MM = 1.0
REORDERINGS = {"mirrored left to right": [1, 0, 3, 2], "mirrored top to bottom": [3, 2, 1, 0],
               "mirrored about a diagonal": [0, 3, 2, 1], "mirrored about the other diagonal": [2, 1, 0, 3],
               "rotated by 90 deg": [1, 2, 3, 0], "rotated by 180 deg": [2, 3, 0, 1],
               "rotated by 270 deg": [3, 0, 1, 2]}


def check_layout(rig: CameraRig, detections: dict[str, dict[int, Detection]], layout: TagLayout,
                 off_mm: float = OFF_MM) -> dict:
    """report.json's check of tags.json against the images: every tag two calibrated cameras see
    (not small, not at a slant) is triangulated; `disagreeing` (tag id -> what is wrong) holds those
    whose every corner is more than off_mm from where the layout puts it, and `median_mm`, `max_mm`
    how far the others' corners are."""
    cams = [c for c in rig.ids if detections.get(c)]
    pid, world = layout.points()
    column = {int(p): i for i, p in enumerate(pid)}
    table = np.full((len(cams), len(pid), 2), np.nan)
    for k, cam in enumerate(cams):
        ids, xy = corner_pixels(without_poor_tags(detections[cam]))
        known = np.isin(ids, pid)
        table[k, [column[int(i)] for i in ids[known]]] = xy[known]
    X, _ = triangulate(rig.subset(cams), table, threshold_px=3.0) if len(cams) >= 2 else \
        (np.full_like(world, np.nan), None)
    off = np.linalg.norm(X - world, axis=1).reshape(-1, 4) * 1000
    seen = np.isfinite(off).all(axis=1)
    bad = seen & (np.nan_to_num(off).min(axis=1) > off_mm)
    good = off[seen & ~bad]
    return {"tags_checked": int(seen.sum()),
            "median_mm": round(float(np.median(good)), 3) if good.size else None,
            "max_mm": round(float(good.max()), 3) if good.size else None,
            "disagreeing": {str(layout.ids[t]): _why(X.reshape(-1, 4, 3)[t], layout.corners[t])
                            for t in np.flatnonzero(bad)}}


def _why(found: np.ndarray, listed: np.ndarray) -> str:
    """How the corners a tag was found at (4,3) differ from those tags.json lists (4,3)."""
    for name, order in REORDERINGS.items():
        if np.linalg.norm(found[order] - listed, axis=1).max() < EXPLAINED_MM / 1000:
            return f"{name} in tags.json"
    side, listed_side = (float(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1).mean()) for c in (found, listed))
    if abs(side / listed_side - 1) > 0.02:
        return (f"its side is {1000 * side:.1f} mm, tags.json gives {1000 * listed_side:.1f} mm "
                "(printed at another size?)")
    shift = 1000 * float(np.linalg.norm(found.mean(axis=0) - listed.mean(axis=0)))
    return f"it is {shift:.1f} mm from where tags.json puts it (moved?)"
