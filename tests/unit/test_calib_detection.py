"""Chessboard detection mapped to INTERFACES.md's chart frame: synthetic chart images drawn
by a known homography, at every in-plane orientation, against the true corner pixels."""

import cv2
import numpy as np
import pytest

from calib_node.chart_detection import (
    cells_alternate,
    chart_points,
    detect_chessboard,
    orient_corners,
)

ROWS, COLS, SPACING = 6, 9, 0.025
SIZE = (640, 480)


def draw_chart(H, size=SIZE, supersample=3):
    """Image of the printed chart (INTERFACES.md colours: the square outside corner (0, 0)
    black) through the homography H (chart metres -> pixels), antialiased."""
    width, height = size
    u, v = np.meshgrid(
        (np.arange(width * supersample) + 0.5) / supersample - 0.5,
        (np.arange(height * supersample) + 0.5) / supersample - 0.5,
    )
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    chart = np.linalg.inv(H) @ pixels
    x, y = chart[0] / chart[2], chart[1] / chart[2]
    i, j = np.floor(x / SPACING), np.floor(y / SPACING)
    on_squares = (i >= -1) & (i <= COLS - 1) & (j >= -1) & (j <= ROWS - 1)
    black = on_squares & (((i + j).astype(int) & 1) == 0)
    plate = (
        (x > -2 * SPACING)
        & (x < (COLS + 1) * SPACING)
        & (y > -2 * SPACING)
        & (y < (ROWS + 1) * SPACING)
    )
    grey = np.where(plate, np.where(black, 15.0, 230.0), 60.0).reshape(u.shape)
    grey = grey.reshape(height, supersample, width, supersample).mean(axis=(1, 3))
    return np.clip(np.round(grey), 0, 255).astype(np.uint8)


def homography(angle, scale=1300.0, centre=(320.0, 240.0), tilt=0.6):
    """Chart [m] -> pixels: the board's middle at ``centre``, turned by ``angle`` in its
    plane, in perspective (``tilt`` [1/m] of the last row: a slightly tilted board)."""
    c, s = np.cos(angle), np.sin(angle)
    middle = np.array([(COLS - 1) * SPACING / 2, (ROWS - 1) * SPACING / 2])
    H = np.eye(3)
    H[:2, :2] = scale * np.array([[c, -s], [s, c]])
    H[2, :2] = [tilt, 0.5 * tilt]
    H[:2, 2] = np.asarray(centre) * (H[2, :2] @ middle + 1) - H[:2, :2] @ middle
    return H


def project(H, points):
    p = np.column_stack([points[:, :2], np.ones(len(points))]) @ H.T
    return p[:, :2] / p[:, 2:]


@pytest.mark.parametrize('angle_deg', [0, 35, 90, 150, 180, 235, 270, 330])
def test_corners_in_chart_order_at_any_orientation(angle_deg):
    H = homography(np.radians(angle_deg))
    image = draw_chart(H)
    detection = detect_chessboard(image, ROWS, COLS)
    assert detection.corners is not None, detection.reason
    truth = project(H, chart_points(ROWS, COLS, SPACING))
    error = np.linalg.norm(detection.corners - truth, axis=1)
    assert error.max() < 0.3, error.max()  # subpixel, and corner (r, c) is corner (r, c)
    # the node passes float grey levels (vgm_common.image_to_grey): the same corners
    as_float = detect_chessboard(image.astype(np.float32), ROWS, COLS)
    np.testing.assert_array_equal(as_float.corners, detection.corners)


def test_mirrored_and_reversed_opencv_orders_are_repaired():
    H = homography(np.radians(20))
    image = draw_chart(H)
    truth = project(H, chart_points(ROWS, COLS, SPACING)).reshape(ROWS, COLS, 2)
    for order in (truth, truth[::-1, ::-1], truth[:, ::-1], truth[::-1]):
        corners, reason = orient_corners(image, order.reshape(-1, 2), ROWS, COLS)
        np.testing.assert_allclose(corners, truth.reshape(-1, 2), err_msg=reason)


def test_no_chart_partial_chart_and_blur_are_rejected():
    flat = np.full(SIZE[::-1], 128, np.uint8)
    assert detect_chessboard(flat, ROWS, COLS).corners is None
    # the board half out of the image: partial, not found
    H = homography(0.0, centre=(40.0, 240.0))
    partial = detect_chessboard(draw_chart(H), ROWS, COLS)
    assert partial.corners is None and 'chessboard' in partial.reason
    blurred = cv2.GaussianBlur(draw_chart(homography(0.3)), (0, 0), 2.5)
    detection = detect_chessboard(blurred, ROWS, COLS, max_blur_px=3.0)
    assert detection.corners is None and 'blurred' in detection.reason
    assert detection.sharpness > 3.0


def test_a_symmetric_board_is_ambiguous():
    # A uniform image gives no colour difference between the two ends of a corner grid.
    grid = project(homography(0.0), chart_points(ROWS, COLS, SPACING))
    corners, reason = orient_corners(np.full(SIZE[::-1], 100, np.uint8), grid, ROWS, COLS)
    assert corners is None and 'ambiguous' in reason


def test_a_sheared_grid_of_saddle_points_is_not_a_chessboard():
    # What OpenCV once returned on a strongly slanted board: row r shifted by r squares.
    # Its corners are all saddle points of the board, but its cells straddle square edges.
    H = homography(np.radians(10))
    image = draw_chart(H)
    r, c = np.divmod(np.arange(4 * 5), 5)
    sheared = project(H, np.column_stack([(c + r) * SPACING, r * SPACING]))
    assert not cells_alternate(image, sheared, 4, 5)
    true = project(H, chart_points(ROWS, COLS, SPACING))
    assert cells_alternate(image, true, ROWS, COLS)
