"""The real images fetched from Debian's opencv-doc package (no skip: a machine that
cannot fetch them fails here with the reason)."""

import cv2
import numpy as np

from vgm_common.sample_data import (
    ALOE_FILES,
    CHESSBOARD_INNER_CORNERS,
    STEREO_CALIBRATION_FILES,
    opencv_sample_dir,
)


def test_aloe_pair_and_ground_truth():
    data = opencv_sample_dir()
    left, right, truth = (
        cv2.imread(str(data / name), cv2.IMREAD_UNCHANGED) for name in ALOE_FILES
    )
    assert left.shape == right.shape and left.shape[2] == 3
    assert truth.shape[:2] == left.shape[:2]
    # Middlebury ground truth: disparity in pixels (0 = unknown), mostly known.
    assert np.count_nonzero(truth) > 0.8 * truth[..., 0].size


def test_stereo_calibration_photographs_show_the_chessboard():
    data = opencv_sample_dir()
    assert len(STEREO_CALIBRATION_FILES) == 26
    grey = cv2.imread(str(data / 'left01.jpg'), cv2.IMREAD_GRAYSCALE)
    found, corners = cv2.findChessboardCorners(grey, CHESSBOARD_INNER_CORNERS)
    assert found and len(corners) == 54
