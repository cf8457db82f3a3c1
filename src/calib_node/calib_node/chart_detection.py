"""Chessboard detection mapped to the chart frame of INTERFACES.md ("The calibration chart").

The chart has ``rows`` x ``cols`` inner corners; corner (r, c) is at (c s, r s, 0) in the
chart frame, z = x cross y points away from a camera that sees the printed face, and the
square diagonally outside corner (0, 0) is black. ``rows + cols`` is odd, so the two ends
of the board differ: at corner (0, 0) both diagonal squares are black, at corner
(rows-1, cols-1) both are white.

OpenCV returns the corners row by row (``cols`` per row) starting at any of the four
outer corners, and possibly mirrored. We fix the order in two steps: the handedness (the
image of chart x cross chart y must point along the optical axis, i.e. be positive in
(u right, v down) pixel coordinates), then the colours (the darker end is corner (0, 0)).
No rclpy.
"""

from __future__ import annotations

import threading
from typing import NamedTuple, Optional

import cv2
import numpy as np
import numpy.typing as npt

from vgm_common.charuco import charuco_board
from vgm_common.geometry import FloatArray

SHARPNESS_FAILED = 9999.0  # what estimateChessboardSharpness returns when it cannot measure


class Detection(NamedTuple):
    """A chart detection in one image (:func:`detect_chessboard`): the corners in chart
    order, or None and the reason it was rejected."""

    corners: Optional[np.ndarray]  # (rows * cols, 2) [px] in chart order (r * cols + c)
    reason: str  # why there is no detection ('' when found)
    sharpness: float  # OpenCV's edge width estimate [px] (nan when not measured)


def chart_points(rows: int, cols: int, spacing: float) -> FloatArray:
    """Inner corners (rows * cols, 3) in the chart frame [m]: index r * cols + c is
    (c spacing, r spacing, 0)."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    return np.column_stack([c * spacing, r * spacing, np.zeros(rows * cols)])


def _mean_grey(grey: np.ndarray, points: npt.ArrayLike, radius: int) -> float:
    """Mean grey level in (2 radius + 1)^2 windows around (K, 2) points, averaged."""
    height, width = grey.shape
    values = []
    for u, v in np.round(np.asarray(points)).astype(int):
        u0, u1 = max(u - radius, 0), min(u + radius + 1, width)
        v0, v1 = max(v - radius, 0), min(v + radius + 1, height)
        if u1 > u0 and v1 > v0:
            values.append(grey[v0:v1, u0:u1].mean())
    return float(np.mean(values)) if values else np.nan


def _end_squares(grid: FloatArray) -> tuple[FloatArray, float]:
    """Centres [px] of the inner and the outer diagonal square at corner (0, 0) of a
    (rows, cols, 2) corner grid, by the local affine map of the neighbouring corners."""
    g00, g01, g10, g11 = grid[0, 0], grid[0, 1], grid[1, 0], grid[1, 1]
    inner = (g00 + g01 + g10 + g11) / 4
    outer = g00 - 0.5 * (g01 - g00) - 0.5 * (g10 - g00)
    return np.array([inner, outer]), np.linalg.norm(g11 - g00) / np.sqrt(2)


def cells_alternate(grey: np.ndarray, corners: npt.ArrayLike, rows: int, cols: int) -> bool:
    """Whether the (rows - 1) x (cols - 1) cells between the corners alternate black and
    white: every cell of one colour darker than every cell of the other. OpenCV now and
    then returns a sheared grid on a strongly slanted board, whose corners fit a
    homography but whose cells straddle the squares' edges (mid-grey)."""
    grid = np.asarray(corners, dtype=float).reshape(rows, cols, 2)
    centres = (grid[:-1, :-1] + grid[:-1, 1:] + grid[1:, :-1] + grid[1:, 1:]) / 4
    size = np.median(np.linalg.norm(grid[1:, 1:] - grid[:-1, :-1], axis=2)) / np.sqrt(2)
    radius = max(1, int(0.2 * size))
    means = np.array([[_mean_grey(grey, [centre], radius) for centre in row] for row in centres])
    r, c = np.indices(means.shape)
    even, odd = means[(r + c) % 2 == 0], means[(r + c) % 2 == 1]
    return bool(even.max() < odd.min() or odd.max() < even.min())


def orient_corners(
    grey: np.ndarray, corners: npt.ArrayLike, rows: int, cols: int, min_contrast: float = 0.2
) -> tuple[Optional[FloatArray], str]:
    """Reorder OpenCV's (rows * cols, 2) corners into the chart order.

    Returns (corners (rows * cols, 2) or None, reason). None when the two ends of the board
    are not clearly different (``min_contrast``: the grey difference of the ends as a
    fraction of the board's black-white difference).
    """
    grid = np.asarray(corners, dtype=float).reshape(rows, cols, 2)
    along_cols = (grid[:, -1] - grid[:, 0]).sum(axis=0)
    along_rows = (grid[-1] - grid[0]).sum(axis=0)
    if along_cols[0] * along_rows[1] - along_cols[1] * along_rows[0] < 0:
        grid = grid[:, ::-1]  # mirrored order: make chart x cross y point into the image
    start_squares, start_size = _end_squares(grid)
    end_squares, end_size = _end_squares(grid[::-1, ::-1])
    radius = max(1, int(0.2 * min(start_size, end_size)))
    start = _mean_grey(grey, start_squares, radius)
    end = _mean_grey(grey, end_squares, radius)
    # The board's own contrast: a black and a white square of the first row.
    black_white = abs(
        _mean_grey(grey, start_squares[:1], radius)
        - _mean_grey(grey, [(grid[0, 1] + grid[0, 2] + grid[1, 1] + grid[1, 2]) / 4], radius)
    )
    if not np.isfinite(start - end) or abs(start - end) < min_contrast * max(black_white, 1.0):
        return None, (
            f'ambiguous chart orientation: the board ends differ by '
            f'{abs(start - end):.1f} grey levels only'
        )
    if start > end:
        grid = grid[::-1, ::-1]  # the darker end is corner (0, 0)
    return grid.reshape(-1, 2), ''


REFINE_WINDOW_FRACTION = 0.45  # cornerSubPix half-window / the smallest square's side
REFINE_WINDOW_RANGE = (2, 15)  # [px]
SADDLE_SIGMA_FRACTION = 0.15  # smoothing of the saddle fit / the smallest square's side
SADDLE_HALF_WIDTH = 2.0  # half-width of the fitted patch [smoothing sigmas]


def refine_corners(grey: np.ndarray, corners: npt.ArrayLike, rows: int, cols: int) -> FloatArray:
    """Sub-pixel corners: ``cv2.cornerSubPix`` (half-window ``REFINE_WINDOW_FRACTION`` of
    the smallest square side, clipped to ``REFINE_WINDOW_RANGE``), then
    :func:`saddle_points`.

    Measured on rendered charts (``rig_generator``, no blur, noise 0-2 grey levels,
    tilts 0-35 deg, k1 0 / -0.3): cornerSubPix alone is 0.05-0.10 px RMS from the truth
    (findChessboardCornersSB's own corners 0.09-0.17 px; a fixed 11 x 11 window breaks on
    squares under ~12 px); the saddle fit brings it to 0.006-0.05 px."""
    grid = np.asarray(corners, dtype=float).reshape(rows, cols, 2)
    side = min(
        np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
        np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
    )
    half = int(np.clip(np.floor(REFINE_WINDOW_FRACTION * side), *REFINE_WINDOW_RANGE))
    refined = cv2.cornerSubPix(
        grey,
        np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2),
        (half, half),
        (-1, -1),
        (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4),
    )
    return saddle_points(grey, refined.reshape(-1, 2).astype(float), side)


def saddle_points(
    grey: np.ndarray, corners: npt.ArrayLike, side: float, iterations: int = 8
) -> FloatArray:
    """Each (K, 2) corner moved to the saddle point of the smoothed image.

    A chessboard corner (two straight edges crossing at any angle, opposite sectors of one
    colour) is point-symmetric about itself, and stays so under a symmetric blur: the
    smoothed image has its saddle exactly at the corner, whatever the perspective and
    the local distortion (unlike cornerSubPix's gradient condition, biased by the pixels'
    box sampling of a sharp edge). We smooth with a Gaussian of sigma
    ``SADDLE_SIGMA_FRACTION`` * side (>= 1 px), fit a quadric to a patch of half-width
    ``SADDLE_HALF_WIDTH`` sigmas resampled about the current estimate (so the fit is
    symmetric about it; its fixed point is the saddle), and step to the quadric's
    stationary point. A corner whose step leaves the patch or whose quadric is not a
    saddle keeps its cornerSubPix position."""
    sigma = max(1.0, SADDLE_SIGMA_FRACTION * side)
    half = max(2, int(round(SADDLE_HALF_WIDTH * sigma)))
    smooth = cv2.GaussianBlur(np.asarray(grey, dtype=np.float32), (0, 0), sigma)
    y, x = np.mgrid[-half : half + 1, -half : half + 1].astype(float)
    x, y = x.ravel(), y.ravel()
    fit = np.linalg.pinv(np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)]))
    out = np.array(corners, dtype=float)
    size = (2 * half + 1, 2 * half + 1)
    for i, start in enumerate(out):
        point = start.copy()
        for _ in range(iterations):
            patch = cv2.getRectSubPix(smooth, size, (float(point[0]), float(point[1])))
            a, b, c, d, e, _ = fit @ patch.ravel().astype(float)
            hessian = np.array([[2 * a, b], [b, 2 * c]])
            if np.linalg.det(hessian) >= 0:  # not a saddle
                point = start
                break
            step = np.linalg.solve(hessian, -np.array([d, e]))
            point = point + step
            if np.linalg.norm(point - start) > half:
                point = start
                break
            if np.linalg.norm(step) < 1e-4:
                break
        out[i] = point
    return out


def detect_chessboard(
    grey: np.ndarray, rows: int, cols: int, max_blur_px: float = 4.0, min_contrast: float = 0.2
) -> Detection:
    """Find the rows x cols inner corners of the chart in a grey image (0..255).

    OpenCV's sector-based detector (``findChessboardCornersSB``, robust) first, the
    classic one as a fallback; then :func:`refine_corners`. A board must be found whole
    (partial boards are not found), be sharp enough (OpenCV's edge-width estimate at most
    ``max_blur_px``), alternate black and white cell by cell (``cells_alternate``) and
    have distinguishable ends (``orient_corners``).

    Returns:
        :class:`Detection` (corners None and a reason when rejected).
    """
    if grey.dtype != np.uint8:  # OpenCV's detectors take 8-bit images only
        grey = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
    grey = np.ascontiguousarray(grey)
    size = (int(cols), int(rows))
    found, corners = cv2.findChessboardCornersSB(
        grey, size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
    )
    if not found:
        # The fast check gives up at once on an image with no chessboard-like quads
        # (0.07 s on a 640x480 noise image, 0.5 s without it): a stream of views without
        # the chart must not back the worker up.
        found, corners = cv2.findChessboardCorners(
            grey,
            size,
            flags=cv2.CALIB_CB_ADAPTIVE_THRESH
            | cv2.CALIB_CB_NORMALIZE_IMAGE
            | cv2.CALIB_CB_FAST_CHECK,
        )
        if not found:
            return Detection(None, f'no {rows}x{cols} chessboard found', np.nan)
    corners = refine_corners(grey, corners, rows, cols)
    retval = cv2.estimateChessboardSharpness(
        grey, size, corners.astype(np.float32).reshape(-1, 1, 2)
    )[0]
    # retval is a 4-element Scalar (edge width first); the stub's Scalar also allows a float
    sharpness = float(retval[0])  # type: ignore[index]
    if sharpness >= SHARPNESS_FAILED:  # OpenCV could not measure it (e.g. tiny squares)
        sharpness = np.nan
    if np.isfinite(sharpness) and sharpness > max_blur_px:
        return Detection(
            None, f'chart too blurred (edge width {sharpness:.1f} px > {max_blur_px:g})', sharpness
        )
    if not cells_alternate(grey, corners, rows, cols):
        return Detection(
            None,
            'the corners found do not form a chessboard (its cells '
            'do not alternate black and white)',
            sharpness,
        )
    ordered, reason = orient_corners(grey, corners, rows, cols, min_contrast)
    if ordered is not None and second_board(grey, ordered, rows, cols):
        return Detection(
            None, 'two charts in view (which one the pose belongs to is ambiguous)', sharpness
        )
    return Detection(ordered, reason, sharpness)


def second_board(grey: np.ndarray, corners: npt.ArrayLike, rows: int, cols: int) -> bool:
    """Whether another rows x cols board is in the image once the found one (its corners'
    hull grown by two squares) is painted over with the image's median grey
    (``findChessboardCorners`` with the fast check: cheap when there is none)."""
    grid = np.asarray(corners, dtype=float).reshape(rows, cols, 2)
    centre = grid.reshape(-1, 2).mean(axis=0)
    square = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2))
    outline = np.array([grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]])
    grown = centre + (outline - centre) * (
        1 + 2.5 * square / np.maximum(np.linalg.norm(outline - centre, axis=1, keepdims=True), 1.0)
    )
    masked = grey.copy()
    cv2.fillConvexPoly(masked, np.rint(grown).astype(np.int32), int(np.median(grey)))
    found, _ = cv2.findChessboardCorners(
        masked,
        (int(cols), int(rows)),
        flags=cv2.CALIB_CB_ADAPTIVE_THRESH
        | cv2.CALIB_CB_NORMALIZE_IMAGE
        | cv2.CALIB_CB_FAST_CHECK,
    )
    return bool(found)


CHARUCO_SADDLE_SCALE = 0.35  # saddle_points' patch on a ChArUco corner / a chessboard's


class CharucoChart:
    """A ChArUco chart's detector (``cv2.aruco.CharucoDetector``), built once: the
    board's parameters are checked at construction (ValueError, see :func:`charuco_board`)."""

    def __init__(
        self,
        rows: int,
        cols: int,
        spacing: float,
        marker_size: float = 0.0,
        dictionary: str = 'DICT_5X5_100',
        min_corners: int = 6,
    ) -> None:
        self.rows, self.cols = int(rows), int(cols)
        self.min_corners = int(min_corners)
        self.board = charuco_board(self.rows, self.cols, spacing, marker_size, dictionary)
        self._detector = cv2.aruco.CharucoDetector(self.board)
        self._lock = threading.Lock()  # one detector object: not known to be reentrant

    def detect(self, grey: np.ndarray) -> Detection:
        """The inner corners the markers identify in a grey image (0..255): ``corners``
        (rows * cols, 2) [px] in chart order with NaN rows for the corners not seen
        (partial and occluded views are views), refined as the chessboard's
        (:func:`saddle_points`); None when fewer than ``min_corners`` are found. The
        corners must not all lie on one line (no pose from them)."""
        if grey.dtype != np.uint8:
            grey = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
        grey = np.ascontiguousarray(grey)
        with self._lock:
            found, ids, _, _ = self._detector.detectBoard(grey)
        count = 0 if ids is None else len(ids)
        if count < self.min_corners:
            return Detection(
                None,
                f'{count} ChArUco corners identified, chart.min_corners is {self.min_corners}',
                np.nan,
            )
        ids = np.asarray(ids).ravel()
        points = np.asarray(found, dtype=float).reshape(-1, 2)
        rows_cols = np.column_stack(np.divmod(ids, self.cols)).astype(float)
        if np.linalg.matrix_rank(rows_cols - rows_cols.mean(axis=0), tol=1e-9) < 2:
            return Detection(None, 'the ChArUco corners found lie on one line', np.nan)
        # The smallest square side seen: the nearest pair of corners one id step apart.
        gaps = np.linalg.norm(points[:, None] - points[None], axis=2)
        steps = np.abs(rows_cols[:, None] - rows_cols[None]).sum(axis=2)
        side = float(gaps[steps == 1].min() if np.any(steps == 1) else gaps[steps > 0].min())
        corners = np.full((self.rows * self.cols, 2), np.nan)
        # The saddle fit on a smaller patch than a chessboard's: the markers' black
        # borders sit point-symmetrically about a corner out to ~0.23 side (markers 0.75),
        # their bits beyond do not. Measured on rig_generator charts (seeds 24, 3; noise 1
        # grey level): CharucoDetector's corners 0.05-0.12 px RMS, refined 0.011-0.035 px
        # (at the chessboard's patch, 0.5 of this scale and up, 0.02-0.16 px).
        corners[ids] = saddle_points(grey, points, CHARUCO_SADDLE_SCALE * side)
        return Detection(corners, '', np.nan)
