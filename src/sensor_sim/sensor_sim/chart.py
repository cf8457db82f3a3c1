"""Calibration chart geometry and print (INTERFACES.md, "The calibration chart"):
a chessboard, or a ChArUco board (``cv2.aruco.CharucoBoard``) of the same squares.

Chart frame, for ``rows`` x ``cols`` inner corners and square size ``spacing`` [m]:
origin at inner corner (row 0, col 0); corner (r, c) at (c * spacing, r * spacing, 0);
x along increasing col, y along increasing row, z = x cross y pointing into the board (away
from a camera that sees the printed face).

The print: (rows + 1) x (cols + 1) squares, the square diagonally outside corner (0, 0)
(negative x and y) black, alternating; a white margin one square wide all round. The
chart is a finite plate exactly as large as the print.

A ChArUco print is OpenCV's own ``CharucoBoard.generateImage`` of (cols + 1) x (rows + 1)
squares, used as the texture of the same squares: its top-left square is black and its
chessboard corner id ``r * cols + c`` is inner corner (r, c), so the chart frame, the
corner order and the white margin are the chessboard's; ArUco markers of ``marker_size``
[m] fill the white squares.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from vgm_common.charuco import DEFAULT_DICTIONARY, charuco_board
from vgm_common.geometry import FloatArray

BLACK_ALBEDO = 0.05
WHITE_ALBEDO = 0.9
MARGIN_SQUARES = 1  # white border around the squares [squares]
# ChArUco texture resolution: 0.75-square markers of 4x4 and 5x5 bits fall on whole texels
TEXTURE_PX_PER_SQUARE = 112


@lru_cache(maxsize=8)
def charuco_texture(
    rows: int, cols: int, spacing: float, marker_size: float, dictionary: str
) -> npt.NDArray[np.bool_]:
    """The board's print, ``generateImage`` at ``TEXTURE_PX_PER_SQUARE`` (square edges on
    texel edges), as a read-only white mask ((rows + 1) * P, (cols + 1) * P)."""
    board = charuco_board(rows, cols, spacing, marker_size, dictionary)
    size = ((cols + 1) * TEXTURE_PX_PER_SQUARE, (rows + 1) * TEXTURE_PX_PER_SQUARE)
    white = board.generateImage(size, marginSize=0, borderBits=1) > 127
    white.setflags(write=False)
    return white


def chart_corners_chart(rows: int, cols: int, spacing: float) -> FloatArray:
    """Inner corners (rows * cols, 3) in the chart frame [m], row-major: index r * cols + c
    is corner (r, c) at (c * spacing, r * spacing, 0)."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    return np.column_stack([c * spacing, r * spacing, np.zeros(rows * cols)])


def chart_plate_extent(
    rows: int, cols: int, spacing: float
) -> tuple[tuple[float, float], tuple[float, float]]:
    """The plate ((x_min, x_max), (y_min, y_max)) in the chart frame [m]."""
    border = (1 + MARGIN_SQUARES) * spacing
    return ((-border, (cols - 1) * spacing + border), (-border, (rows - 1) * spacing + border))


def chart_albedo(xy_chart: npt.ArrayLike, rows: int, cols: int, spacing: float) -> FloatArray:
    """Albedo of the printed face at (N, 2) chart-frame points [m]; NaN off the plate.

    Square (i, j) spans x in [i, i+1) * spacing and y in [j, j+1) * spacing, for
    i = -1..cols-1 and j = -1..rows-1; it is black when i + j is even, so the square
    (-1, -1) outside corner (0, 0) is black. Everything else on the plate is white.
    """
    xy = np.asarray(xy_chart, dtype=float).reshape(-1, 2)
    (x0, x1), (y0, y1) = chart_plate_extent(rows, cols, spacing)
    x, y = xy[:, 0], xy[:, 1]
    i, j = np.floor(x / spacing), np.floor(y / spacing)
    on_squares = (i >= -1) & (i <= cols - 1) & (j >= -1) & (j <= rows - 1)
    with np.errstate(invalid='ignore'):  # NaN points are off the squares anyway
        even = ((i + j).astype(np.int64) & 1) == 0
    albedo = np.where(on_squares & even, BLACK_ALBEDO, WHITE_ALBEDO)
    albedo[~((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))] = np.nan
    return albedo


def charuco_albedo(
    xy_chart: npt.ArrayLike,
    rows: int,
    cols: int,
    spacing: float,
    marker_size: float = 0.0,
    dictionary: str = DEFAULT_DICTIONARY,
) -> FloatArray:
    """Albedo of a ChArUco print at (N, 2) chart-frame points [m]; NaN off the plate. The
    squares are where :func:`chart_albedo` has them; the texel under each point decides."""
    white = charuco_texture(rows, cols, spacing, marker_size, dictionary)
    xy = np.asarray(xy_chart, dtype=float).reshape(-1, 2)
    (x0, x1), (y0, y1) = chart_plate_extent(rows, cols, spacing)
    with np.errstate(invalid='ignore'):
        texel = np.floor((xy / spacing + 1.0) * TEXTURE_PX_PER_SQUARE)
    height, width = white.shape
    valid = np.all(np.isfinite(texel), axis=1)
    i = np.where(valid, texel[:, 0], -1).astype(np.int64)
    j = np.where(valid, texel[:, 1], -1).astype(np.int64)
    on_squares = (i >= 0) & (i < width) & (j >= 0) & (j < height)
    printed_white = np.ones(len(xy), bool)
    printed_white[on_squares] = white[j[on_squares], i[on_squares]]
    albedo = np.where(printed_white, WHITE_ALBEDO, BLACK_ALBEDO)
    x, y = xy[:, 0], xy[:, 1]
    albedo[~((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))] = np.nan
    return albedo


def print_albedo(
    pattern: str,
    rows: int,
    cols: int,
    spacing: float,
    marker_size: float = 0.0,
    dictionary: str = DEFAULT_DICTIONARY,
) -> Callable[[npt.ArrayLike], FloatArray]:
    """The albedo function (N, 2) chart-frame points [m] -> (N,) of a chart print:
    ``pattern`` 'chessboard' (:func:`chart_albedo`) or 'charuco' (:func:`charuco_albedo`).
    Raises ValueError for another pattern or a bad ChArUco board."""
    if pattern == 'chessboard':
        return lambda xy: chart_albedo(xy, rows, cols, spacing)
    if pattern == 'charuco':
        charuco_texture(rows, cols, spacing, marker_size, dictionary)  # fail here, not later
        return lambda xy: charuco_albedo(xy, rows, cols, spacing, marker_size, dictionary)
    raise ValueError(f'unknown chart pattern {pattern!r}')
