"""View selection and coverage progress for a handheld chart, as camera_calibration's
calibrator does it (x, y, size, skew of the board in the image). No rclpy.

A view's parameters, from its (rows * cols, 2) corners in an image of (width, height):
``x``, ``y`` the board's mean position within the room its size leaves; ``size`` the
square root of its outline's area over the image area; ``skew`` how far the angle at its
first corner is from a right angle (0 fronto-parallel, 1 at 45 degrees of shear). A view
is kept only when its parameters differ from every kept view's by ``min_distance`` (sum
of absolute differences); progress per parameter is the spread of the kept views over
``RANGES`` (camera_calibration's x 0.7, y 0.7, size 0.4, skew 0.5), capped at 100 %.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from vgm_common.geometry import FloatArray

PARAMETERS = ('x', 'y', 'size', 'skew')
RANGES = (0.7, 0.7, 0.4, 0.5)
HINTS = {
    'x': 'move the chart left and right',
    'y': 'move the chart up and down',
    'size': 'move the chart nearer and farther',
    'skew': 'tilt the chart',
}


def view_parameters(
    corners: npt.ArrayLike, rows: int, cols: int, image_size: tuple[int, int]
) -> FloatArray:
    """(4,) x, y, size, skew in [0, 1] of a board's corners (rows * cols, 2) [px]; NaN
    rows (corners not seen) are filled by the homography of the others."""
    width, height = image_size
    points = np.asarray(corners, dtype=float).reshape(-1, 2)
    seen = np.isfinite(points[:, 0])
    if not np.all(seen):  # a partial ChArUco view: its board's outline by homography
        r, c = np.divmod(np.arange(rows * cols), cols)
        H, _ = cv2.findHomography(np.column_stack([c, r])[seen].astype(np.float32), points[seen])
        if H is None:
            raise ValueError('the corners seen give no homography')
        grid_cr = np.column_stack([c, r, np.ones(rows * cols)]) @ H.T
        points = grid_cr[:, :2] / grid_cr[:, 2:]
    grid = points.reshape(rows, cols, 2)
    outline = np.array([grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]])
    x, y = outline[:, 0], outline[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    border = np.sqrt(area)
    mean = grid.reshape(-1, 2).mean(axis=0)
    px = np.clip((mean[0] - border / 2) / max(width - border, 1.0), 0.0, 1.0)
    py = np.clip((mean[1] - border / 2) / max(height - border, 1.0), 0.0, 1.0)
    size = np.sqrt(area / (width * height))
    a, b = grid[0, -1] - grid[0, 0], grid[-1, 0] - grid[0, 0]
    angle = np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))
    skew = min(1.0, 2.0 * abs(np.pi / 2 - angle))
    return np.array([px, py, size, skew])


class Coverage:
    """The kept views' parameters and the progress per parameter."""

    def __init__(self, min_distance: float = 0.2) -> None:
        self.min_distance = float(min_distance)
        self.kept: list[FloatArray] = []

    def is_new(self, parameters: npt.ArrayLike) -> bool:
        """Whether a view with ``parameters`` (4,) adds to the kept ones."""
        return all(
            np.sum(np.abs(np.asarray(parameters) - p)) > self.min_distance for p in self.kept
        )

    def add(self, parameters: npt.ArrayLike) -> None:
        """Keep a view's ``parameters`` (4,) (a copy); :meth:`is_new` is not checked."""
        self.kept.append(np.asarray(parameters, dtype=float).copy())

    def clear(self) -> None:
        """Forget every kept view (progress back to 0)."""
        self.kept.clear()

    def progress(self) -> dict[str, float]:
        """{parameter: fraction in [0, 1]} of the ranges covered."""
        if not self.kept:
            return dict.fromkeys(PARAMETERS, 0.0)
        kept = np.array(self.kept)
        spread = kept.max(axis=0) - kept.min(axis=0)
        spread[2] = kept[:, 2].max() - min(kept[:, 2].min(), 0.2)  # a far board counts
        spread[3] = kept[:, 3].max()  # skew from fronto-parallel (0) up
        return {name: float(min(s / r, 1.0)) for name, s, r in zip(PARAMETERS, spread, RANGES)}

    def summary(self) -> str:
        """'x 80 %, y 60 %, size 40 %, skew 30 %'."""
        return ', '.join(f'{name} {100 * value:.0f} %' for name, value in self.progress().items())

    def missing(self, required: float = 1.0) -> str:
        """What to do to reach ``required`` in every parameter ('' when covered)."""
        return '; '.join(
            f'{name} {100 * value:.0f} %: {HINTS[name]}'
            for name, value in self.progress().items()
            if value < required
        )
