"""Calibration targets: the `board.toml` file of DESIGN.md and the tag layout `tags.json`.

A board is described in one small TOML file:

    type = "charuco"          # chessboard | charuco | apriltag-grid
    cols = 4                  # chessboard: inner corners; charuco: squares; grid: tags
    rows = 5
    square = 0.054            # metres (grid: distance between neighbouring tag origins)
    marker = 0.0405           # metres (charuco marker side, grid tag side)
    dictionary = "DICT_4X4_1000"
    inverted = true           # white-on-black print

Every board point has an integer id: chessboard and ChArUco corners are numbered row by row
(id = row * (inner columns) + col, as OpenCV numbers them); an AprilTag grid has four points per
tag, id = tag_id * 4 + corner in OpenCV's corner order. The same numbering is used for the tags
on the walls of a rig, so every later stage handles boards and tags alike.
"""

from __future__ import annotations

import json
import os
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import cv2
import numpy as np
from pydantic import AfterValidator, Field
from pydantic_core import PydanticCustomError

from manus_core.errors import BoardError
from manus_core.validation import CLOSED, NOT_A_KEY, Bool, Float, Int, Problem, Str, known_keys, validate, worded

BoardType = Literal["chessboard", "charuco", "apriltag-grid"]
BOARD_TYPES = get_args(BoardType)
# tags.json names families the way the AprilTag library does; OpenCV names them as dictionaries.
TAG_FAMILIES = {"tag36h11": "DICT_APRILTAG_36h11", "tag25h9": "DICT_APRILTAG_25h9",
                "tag36h10": "DICT_APRILTAG_36h10", "tag16h5": "DICT_APRILTAG_16h5"}


def dictionary_names() -> list[str]:
    """The predefined marker dictionaries OpenCV knows (DICT_4X4_50 ... DICT_APRILTAG_36h11)."""
    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int))


def get_dictionary(name: str):
    """The OpenCV dictionary called `name` (e.g. "DICT_4X4_1000")."""
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _in_metres(square: float) -> float:
    if square > 1.0:
        raise PydanticCustomError("worded", f"is {square} m; lengths are in metres (a 25 mm square is 0.025)")
    return square


# no printable board has more than 100 squares or tags to a side
Count = Annotated[Int, Field(ge=2, le=100), worded("must be an integer >= 2 and <= 100, got {value}")]


@dataclass(frozen=True)
class Board:
    """A planar calibration target; `object_points()[i]` is the board point with id i."""

    __pydantic_config__ = CLOSED   # unknown keys are errors

    type: Annotated[BoardType, worded(f"is {{value}}, expected one of {', '.join(BOARD_TYPES)}")]
    cols: Count
    rows: Count
    square: Annotated[Float, Field(ge=0.001), worded("must be a length in metres >= 0.001 (1 mm), got {value}"),
                      AfterValidator(_in_metres)]
    marker: Annotated[Float, Field(ge=0), worded("must be a length in metres >= 0, got {value}")] = 0.0
    dictionary: Annotated[Str, worded("must be a string, got {value}")] = ""
    inverted: Annotated[Bool, worded("must be true or false, got {value}")] = False
    source: Annotated[str, NOT_A_KEY] = "board.toml"

    @property
    def corner_grid(self) -> tuple[int, int]:
        """(columns, rows) of the chessboard corners found on this board (chessboard and charuco)."""
        if self.type == "chessboard":
            return self.cols, self.rows
        return self.cols - 1, self.rows - 1

    @property
    def n_points(self) -> int:
        if self.type == "apriltag-grid":
            return 4 * self.cols * self.rows
        cols, rows = self.corner_grid
        return cols * rows

    def object_points(self) -> np.ndarray:
        """Board coordinates (n_points, 3) in metres, z = 0 on the board plane."""
        if self.type == "apriltag-grid":
            # Tag k sits at column k % cols, row k // cols; OpenCV corner order (clockwise from
            # the tag's top-left as printed), y down the board like the chessboard rows.
            k = np.arange(self.cols * self.rows)
            origin = np.stack([k % self.cols, k // self.cols], axis=1) * self.square
            offsets = np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) * self.marker
            xy = (origin[:, None, :] + offsets[None]).reshape(-1, 2)
        else:
            cols, rows = self.corner_grid
            first = 0.0 if self.type == "chessboard" else self.square
            xy = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1).reshape(-1, 2) * self.square + first
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    def neighbour_pairs(self) -> np.ndarray:
        """(P,2) ids of board points one square apart along a row or column (scale checks)."""
        if self.type == "apriltag-grid":
            tags = np.arange(self.cols * self.rows)[:, None] * 4
            return np.concatenate([tags + [0, 1], tags + [1, 2], tags + [2, 3], tags + [3, 0]])
        cols, rows = self.corner_grid
        ids = np.arange(cols * rows).reshape(rows, cols)
        return np.concatenate([np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], 1),
                               np.stack([ids[:-1].ravel(), ids[1:].ravel()], 1)])

    def neighbour_distance(self) -> float:
        """The true distance between the points of `neighbour_pairs` (metres)."""
        return self.marker if self.type == "apriltag-grid" else self.square

    def opencv_board(self, cols: int | None = None, rows: int | None = None, dictionary: str | None = None):
        """The cv2.aruco board object (CharucoBoard or GridBoard); None for a chessboard.

        cols/rows/dictionary override the file's values, for the diagnosis of a board that
        matches nothing.
        """
        if self.type == "chessboard":
            return None
        size = (cols or self.cols, rows or self.rows)
        dic = get_dictionary(dictionary or self.dictionary)
        if self.type == "charuco":
            return cv2.aruco.CharucoBoard(size, self.square, self.marker, dic)
        return cv2.aruco.GridBoard(size, self.marker, self.square - self.marker, dic)


def _line(problem: Problem) -> str:
    """A problem worded as board.toml and tags.json errors are: "key 'cols' must be ..."."""
    if problem.kind == "extra_forbidden":
        return f"unknown key '{problem.key}' (known: {', '.join(known_keys(Board))})"
    if problem.kind == "missing":
        hint = f" (one of {', '.join(BOARD_TYPES)})" if problem.key == "type" else ""
        return f"key '{problem.key}' is missing{hint}"
    return f"key '{problem.key}' {problem.text}"


def board_from_dict(doc: dict, source: str = "board.toml") -> Board:
    """Validate a board table; every error names `source` and the key."""
    board = validate(Board, doc, source, BoardError, _line)
    kind, square, marker = board.type, board.square, board.marker
    if kind == "charuco" and min(board.cols, board.rows) < 3:
        raise BoardError(f"{source}: a charuco board needs at least 3 squares in 'cols' and 'rows'")
    if kind != "chessboard" and not 0 < marker < square + (1e-9 if kind == "charuco" else 0):
        raise BoardError(f"{source}: key 'marker' must be > 0 and smaller than 'square' ({square} m), got {marker}")
    dictionary = board.dictionary or ("DICT_APRILTAG_36h11" if kind == "apriltag-grid" else "")
    if kind != "chessboard":
        if dictionary not in dictionary_names():
            raise BoardError(f"{source}: key 'dictionary' is {dictionary!r}, not an OpenCV dictionary "
                             f"(e.g. DICT_4X4_1000, DICT_APRILTAG_36h11)")
        needed = (board.cols * board.rows + 1) // 2 if kind == "charuco" else board.cols * board.rows
        size = len(get_dictionary(dictionary).bytesList)
        if needed > size:
            raise BoardError(f"{source}: the board needs {needed} markers but {dictionary} has {size}")
    return replace(board, dictionary=dictionary, source=source)


def _read(path: Path, parse, what: str) -> dict:
    try:
        doc = parse(path.read_text())
    except FileNotFoundError:
        raise BoardError(f"{path}: no such {what} file") from None
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BoardError(f"{path}: not valid {'TOML' if parse is tomllib.loads else 'JSON'} ({exc})") from None
    if not isinstance(doc, dict):
        raise BoardError(f"{path}: expected a {what} table, got {type(doc).__name__}")
    return doc


def load_board(path: str | os.PathLike) -> Board:
    """Read and validate a board.toml."""
    return board_from_dict(_read(Path(path), tomllib.loads, "board"), str(path))


@dataclass(frozen=True)
class TagLayout:
    """Known world positions of wall tags: `corners[i]` (4,3) belongs to tag `ids[i]`."""

    family: str
    size: float
    ids: np.ndarray
    corners: np.ndarray
    source: str = "tags.json"

    @property
    def dictionary(self) -> str:
        return TAG_FAMILIES[self.family]

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """(point ids (4T,), world points (4T,3)) with point id = tag_id * 4 + corner."""
        pid = (self.ids[:, None] * 4 + np.arange(4)).ravel()
        return pid, self.corners.reshape(-1, 3)

    def without(self, tags) -> "TagLayout":
        """The layout without these tag ids."""
        keep = ~np.isin(self.ids, list(tags))
        return replace(self, ids=self.ids[keep], corners=self.corners[keep])

    def edge_pairs(self) -> np.ndarray:
        """(4T,2) point ids of neighbouring corners of each tag, `size` apart (scale checks)."""
        edges = np.stack([np.arange(4), (np.arange(4) + 1) % 4], axis=1)
        return (self.ids[:, None, None] * 4 + edges[None]).reshape(-1, 2)


def load_tags(path: str | os.PathLike) -> TagLayout:
    """Read and validate tags.json ({"family", "size", "tags": {"ID": [[x,y,z] x 4]}})."""

    def unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        # json.loads keeps the last of two equal keys without a word: a tag given twice is an error
        keys = [k for k, _ in pairs]
        twice = next((k for k in keys if keys.count(k) > 1), None)
        if twice is not None:
            raise BoardError(f"{path}: key {twice!r} is given twice")
        return dict(pairs)

    return tags_from_dict(_read(Path(path), lambda text: json.loads(text, object_pairs_hook=unique_keys),
                                "tag layout"), str(path))


@dataclass(frozen=True)
class _TagsFile:
    """tags.json as written; the corners are checked as arrays in tags_from_dict."""

    family: Annotated[Literal[tuple(TAG_FAMILIES)], worded(f"is {{value}}, expected one of {', '.join(TAG_FAMILIES)}")]
    size: Annotated[Float, Field(gt=0, lt=2), worded("must be the tag side in metres, got {value}")]
    tags: Annotated[dict[str, Any], Field(min_length=1),
                    worded("must be a non-empty object of tag id -> 4 corners")]


def tags_from_dict(doc: dict, source: str = "tags.json") -> TagLayout:
    """Validate a tag layout; errors name the file and the key."""
    layout = validate(_TagsFile, doc, source, BoardError, _line)
    family_size = len(get_dictionary(TAG_FAMILIES[layout.family]).bytesList)
    ids, corners = [], []
    for key, value in layout.tags.items():
        try:
            tag_id = int(key)
            c = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise BoardError(f"{source}: key 'tags.{key}' is not an integer id with 4 [x, y, z] corners") from None
        if not 0 <= tag_id < family_size:
            raise BoardError(f"{source}: key 'tags.{key}' is not a tag of {layout.family} (ids 0..{family_size - 1})")
        if tag_id in ids:
            raise BoardError(f"{source}: key 'tags.{key}' is tag {tag_id} again")
        if c.shape != (4, 3) or not np.isfinite(c).all():
            raise BoardError(f"{source}: key 'tags.{key}' must hold 4 corners [x, y, z], got shape {c.shape}")
        sides = np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)
        if np.abs(sides - layout.size).max() > 0.05 * layout.size:
            raise BoardError(f"{source}: key 'tags.{key}' has sides {np.round(sides, 4).tolist()} m, "
                             f"not the tag size {layout.size} m (units are metres)")
        ids.append(tag_id)
        corners.append(c)
    order = np.argsort(ids)
    return TagLayout(layout.family, layout.size, np.asarray(ids)[order], np.asarray(corners)[order], source)
