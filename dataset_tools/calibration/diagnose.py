"""Why a board is found in none of the images: the usual mistakes in board.toml, tried one by one."""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import cv2
import numpy as np

from .boards import Board, get_dictionary
from .detect import BoardDetector, Detection
from .frames import to_gray


def diagnose_board(images: Sequence[np.ndarray], board: Board) -> str:
    """Why `board` is found in none of `images`: the usual mistakes tried one by one.

    Returns one sentence naming the parameter of board.toml that is likely wrong (the most common
    complaint about anipose and FreeMoCap is a board silently matching nothing).
    """
    grays = [to_gray(i) for i in images]
    n = len(grays)
    b = board
    c, r = b.cols, b.rows
    low = 2 if b.type != "charuco" else 3
    shapes = [(c, r), (r, c), (c - 1, r - 1), (r - 1, c - 1), (c + 1, r + 1), (r + 1, c + 1)]
    best, best_points = None, 0
    # the print's polarity last: ties go to the variant that keeps it
    for inverted in (b.inverted, not b.inverted):
        for cols, rows in dict.fromkeys(s for s in shapes if min(s) >= low):
            variant = replace(b, cols=cols, rows=rows, inverted=inverted)
            if variant == b:
                continue
            det = BoardDetector(variant, quick=True)
            points = sum(len(d) for d in map(det.detect, grays) if _planar_fit(d, variant))
            if points > best_points:
                best, best_points = variant, points
    if best is not None:
        changes = [f"{k} = {str(getattr(best, k)).lower() if k == 'inverted' else getattr(best, k)}"
                   for k in ("cols", "rows", "inverted") if getattr(best, k) != getattr(b, k)]
        hint = ""
        if (best.cols, best.rows) != (c, r) and {best.cols, best.rows} != {c, r}:
            hint = (" (a chessboard's cols and rows count inner corners)" if b.type == "chessboard" else
                    " (a charuco board's cols and rows count squares)" if b.type == "charuco" else "")
        elif (best.cols, best.rows) == (r, c):
            hint = " (cols and rows swapped)"
        return (f"{b.source}: the board is found in none of {n} images as described, but with "
                f"{', '.join(changes)}{hint} it is ({best_points} points)")
    if b.type == "chessboard":
        return (f"{b.source}: no {b.cols}x{b.rows} chessboard in {n} images, nor with the usual mistakes "
                f"(swapped, squares instead of inner corners, inverted): is the board in view, sharp and evenly lit?")
    counts = {}
    for name in (b.dictionary, *_COMMON_DICTIONARIES):
        det = cv2.aruco.ArucoDetector(get_dictionary(name))
        for inv in (False, True):
            counts[(name, inv)] = sum(len(det.detectMarkers(255 - g if inv else g)[0]) for g in grays)
    # ties: the larger dictionary (DICT_4X4_1000 holds every marker of DICT_4X4_50)
    (best, inv), found = max(counts.items(), key=lambda kv: (kv[1], len(get_dictionary(kv[0][0]).bytesList)))
    if found == 0:
        return f"{b.source}: no marker of any common dictionary in {n} images: is the board in view, sharp and evenly lit?"
    if best != b.dictionary:
        return (f"{b.source}: {found} markers of {best} but {counts[(b.dictionary, b.inverted)]} of {b.dictionary} "
                f"were found: set dictionary = \"{best}\"" + (f" and inverted = {str(inv).lower()}" if inv != b.inverted else ""))
    return (f"{b.source}: markers of {b.dictionary} are found ({found}) but never the board: check cols, rows, "
            f"square and marker (boards made by OpenCV before 4.6 with an even number of rows use the old "
            f"'legacy' layout)")


# Dictionaries people print boards from, tried when a board matches nothing.
_COMMON_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_1000", "DICT_5X5_100", "DICT_5X5_1000", "DICT_6X6_250",
                        "DICT_6X6_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11")


def _planar_fit(det: Detection, board: Board, tol_px: float = 3.0) -> bool:
    """True when the detected points fit one homography of the board plane (a real board, not
    corners interpolated from markers of a board with another layout)."""
    if len(det) < 6:
        return False
    obj = board.object_points()[det.ids, :2]
    H, _ = cv2.findHomography(obj, det.xy, 0)
    if H is None:
        return False
    proj = cv2.perspectiveTransform(obj.reshape(-1, 1, 2), H).reshape(-1, 2)
    return bool(np.median(np.linalg.norm(proj - det.xy, axis=1)) < tol_px)
