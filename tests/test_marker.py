"""Metric scale from a ChArUco mat under the object (recon.marker): a synthetic tabletop capture
with the board printed on the table, true cameras in scene units; the printed square is given
in metres and the scale must come out within 1 %."""

import numpy as np
import pytest
from _tabletop_scene import MAT_TEST, MAT_TEST_SQUARE_UNITS, tabletop_capture

from recon.io.cameras import load_cameras
from recon.io.images import read_exr
from recon.marker import MarkerBoard, MarkerError, marker_scale, marker_scale_from_dirs


@pytest.fixture(scope="module")
def mat_capture(tmp_path_factory):
    return tabletop_capture(tmp_path_factory.getbasetemp(), **MAT_TEST)


def test_scale_from_the_mat_within_one_percent(mat_capture):
    square_m = 0.03  # the printed square's side
    mpu, info = marker_scale_from_dirs(mat_capture / "images", mat_capture / "gt" / "cameras.json",
                                       MarkerBoard(square_m))
    true = square_m / MAT_TEST_SQUARE_UNITS  # metres per scene unit
    assert abs(mpu / true - 1) < 0.01, info
    assert info["views_with_corners"] >= 6 and info["neighbour_pairs"] >= 6
    assert info["reprojection_px"] < 1.0


def test_no_mat_is_a_clear_error(mat_capture):
    cams = load_cameras(mat_capture / "gt" / "cameras.json")
    images = {c.stem: np.zeros_like(read_exr(mat_capture / "images" / f"{c.stem}.exr")) for c in cams}
    with pytest.raises(MarkerError, match="object_height_m"):
        marker_scale(images, cams, MarkerBoard(0.03))


def test_board_layout():
    b = MarkerBoard(0.02)
    pairs = b.neighbours()
    assert len(pairs) == 3 * 6 + 4 * 5  # 4 x 6 inner corners: row and column neighbours
    assert (0, 1) in pairs and (0, 4) in pairs and (3, 4) not in pairs
    for bad in (dict(square_m=0.0), dict(square_m=0.02, squares=(1, 7)), dict(square_m=0.02, marker_fraction=1.2)):
        with pytest.raises(ValueError):
            MarkerBoard(**bad)
