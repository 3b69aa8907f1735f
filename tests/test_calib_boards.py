"""board.toml and tags.json: validation messages name the file and the key; geometry is OpenCV's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dataset_tools.calibration.boards import board_from_dict, load_board, load_tags
from manus_core.errors import BoardError


@pytest.mark.parametrize("text, message", [
    ('type = "chessboard"\ncols = 9\nrows = 6\nsquare = 0.025\ncolour = "red"\n', "unknown key 'colour'"),
    ('cols = 9\nrows = 6\nsquare = 0.025\n', "key 'type' is missing"),
    ('type = "circles"\ncols = 9\nrows = 6\nsquare = 0.025\n', "key 'type' is 'circles'"),
    ('type = "chessboard"\ncols = 9.5\nrows = 6\nsquare = 0.025\n', "key 'cols' must be an integer >= 2"),
    ('type = "chessboard"\ncols = 9\nrows = 6\nsquare = 25\n', "key 'square' is 25.0 m; lengths are in metres"),
    ('type = "charuco"\ncols = 4\nrows = 5\nsquare = 0.054\nmarker = 0.06\ndictionary = "DICT_4X4_50"\n',
     "key 'marker' must be > 0 and smaller than 'square'"),
    ('type = "charuco"\ncols = 4\nrows = 5\nsquare = 0.054\nmarker = 0.04\ndictionary = "DICT_4X4"\n',
     "key 'dictionary' is 'DICT_4X4', not an OpenCV dictionary"),
    ('type = "charuco"\ncols = 20\nrows = 20\nsquare = 0.01\nmarker = 0.007\ndictionary = "DICT_4X4_50"\n',
     "the board needs 200 markers but DICT_4X4_50 has 50"),
    ('type = "chessboard"\ncols = 9\nrows = 6\nsquare = 0.025\ninverted = "yes"\n', "key 'inverted' must be true or false"),
    ('type = "chessboard"\ncols = 9\nrows = [6]\n', "key 'rows' must be an integer"),
    ('type = chessboard\n', "not valid TOML"),
])
def test_board_errors_name_file_and_key(tmp_path, text, message):
    path = tmp_path / "board.toml"
    path.write_text(text)
    with pytest.raises(BoardError) as err:
        load_board(path)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value)
    assert err.value.exit_code == 2


def test_board_points_follow_opencv():
    charuco = board_from_dict({"type": "charuco", "cols": 4, "rows": 5, "square": 0.054, "marker": 0.0405,
                               "dictionary": "DICT_4X4_1000"})
    assert charuco.n_points == 12
    assert np.allclose(charuco.object_points(), charuco.opencv_board().getChessboardCorners())
    grid = board_from_dict({"type": "apriltag-grid", "cols": 3, "rows": 2, "square": 0.05, "marker": 0.04})
    assert grid.dictionary == "DICT_APRILTAG_36h11"
    assert np.allclose(grid.object_points(), np.array(grid.opencv_board().getObjPoints()).reshape(-1, 3))
    chess = board_from_dict({"type": "chessboard", "cols": 9, "rows": 6, "square": 0.025})
    pairs = chess.neighbour_pairs()
    d = np.linalg.norm(np.diff(chess.object_points()[pairs], axis=1), axis=2)
    assert len(pairs) == 8 * 6 + 9 * 5 and np.allclose(d, 0.025)


def test_tag_layout_errors(tmp_path):
    path = tmp_path / "tags.json"
    good = {"family": "tag36h11", "size": 0.1, "tags": {"3": [[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]]}}
    path.write_text(json.dumps(good))
    layout = load_tags(path)
    pid, world = layout.points()
    assert pid.tolist() == [12, 13, 14, 15] and world.shape == (4, 3)
    for change, message in [({"family": "tag99"}, "key 'family' is 'tag99'"),
                            ({"size": 100}, "key 'size' must be the tag side in metres"),
                            ({"tags": {"3": [[0, 0, 0]]}}, "key 'tags.3' must hold 4 corners"),
                            ({"tags": {"3": [[0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0]]}},
                             "key 'tags.3' has sides [100.0, 100.0, 100.0, 100.0] m, not the tag size 0.1 m")]:
        path.write_text(json.dumps({**good, **change}))
        with pytest.raises(BoardError, match=f"{path}: {message}".replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
            load_tags(path)
