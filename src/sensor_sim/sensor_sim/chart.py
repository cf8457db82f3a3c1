"""Chessboard calibration chart geometry (INTERFACES.md, "The calibration chart").

Chart frame, for ``rows`` x ``cols`` inner corners and square size ``spacing`` [m]:
origin at inner corner (row 0, col 0); corner (r, c) at (c * spacing, r * spacing, 0);
x along increasing col, y along increasing row, z = x cross y pointing into the board (away
from a camera that sees the printed face).

The print: (rows + 1) x (cols + 1) squares, the square diagonally outside corner (0, 0)
(negative x and y) black, alternating; a white margin one square wide all round. The
chart is a finite plate exactly as large as the print.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from vgm_common.geometry import FloatArray

BLACK_ALBEDO = 0.05
WHITE_ALBEDO = 0.9
MARGIN_SQUARES = 1  # white border around the squares [squares]


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
