"""Cross-validation of a calibration, as mrcal validates one: calibrate two halves of the
views apart and compare where the two solutions project the same points. Where the
halves agree, the data pin the cameras down; where they disagree (image corners no chart
reached, a lens model that does not fit), the full calibration is no better known than
that. No rclpy.

The halves are drawn so both cover the image alike: the views are paired with their
nearest neighbour in camera_calibration's view parameters (x, y, size, skew) and each pair
split between the halves. The comparison is taken, like the projection uncertainty, at
each camera's working range on a grid over the whole image: the points on the rays of
half A's camera are projected by half B's, in one frame for the whole rig:

- base_link when the chart poses are known (the stage): both halves are solved in it;
- handheld, each half's frame is its own left camera's, which floats with that half's
  intrinsics; the transform between the two frames is fitted to the projections
  themselves (one rigid transform for the rig, weighted by the halves' predicted
  uncertainty, as mrcal's ``projection_diff`` fits its implied transform per camera).

With independent halves the difference is the sum of two calibration errors each about
sqrt(2) times the full calibration's, so about twice the full calibration's true error
(tests/unit/test_calib_cross_validation.py measures it against the truth).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
import scipy.optimize

from calib_node.coverage import view_parameters
from calib_node.uncertainty import GRID, Uncertainty, image_grid, points_at_range
from vgm_common.camera_model import PinholeCamera
from vgm_common.geometry import FloatArray, make_transform

MIN_HALF_VIEWS = 3  # Zhang's minimum per camera, in each half


class CrossValidation(NamedTuple):
    """Per camera the worst and median projection difference between the two halves'
    solutions over the image grid [px], the working range it is taken at [m] and the grid
    ((rows, cols) [px]); the views in each half; whether the halves' frames were aligned
    by a fitted transform (handheld) rather than shared (base_link)."""

    worst_px: dict[str, float]
    median_px: dict[str, float]
    range_m: dict[str, float]
    grid_px: dict[str, FloatArray]
    halves: tuple[int, int]
    aligned: bool


def split_views(parameters: Sequence[npt.ArrayLike]) -> tuple[list[int], list[int]]:
    """Indices of two halves of views that cover the image alike: each view, in order, is
    paired with its nearest unpaired neighbour by ``parameters`` (x, y, size, skew per
    view, ``coverage.view_parameters``) and the pair split, the first view going to the
    half with fewer so far (an odd view out as well)."""
    points = np.asarray(parameters, dtype=float).reshape(len(parameters), -1)
    free = list(range(len(points)))
    halves: tuple[list[int], list[int]] = ([], [])
    while free:
        first = free.pop(0)
        smaller = 0 if len(halves[0]) <= len(halves[1]) else 1
        halves[smaller].append(first)
        if free:
            distances = np.linalg.norm(points[free] - points[first], axis=1)
            halves[1 - smaller].append(free.pop(int(np.argmin(distances))))
    return sorted(halves[0]), sorted(halves[1])


def split_chart_views(
    views: Sequence[Mapping[str, FloatArray]],
    names: Sequence[str],
    rows: int,
    cols: int,
    image_sizes: Mapping[str, tuple[int, int]],
) -> tuple[list[int], list[int]]:
    """:func:`split_views` of chart views ([{name: corners (rows * cols, 2)}]), each view
    placed by where the chart was in the first camera of ``names`` that saw it."""
    parameters = []
    for corners in views:
        name = next(n for n in names if n in corners)
        parameters.append(view_parameters(corners[name], rows, cols, image_sizes[name]))
    return split_views(parameters)


def rigid_fit(source: FloatArray, target: FloatArray, weights: FloatArray) -> FloatArray:
    """(4, 4) rigid transform T minimising sum w |T source - target|^2 over points (M, 3)
    (weighted Kabsch)."""
    w = np.asarray(weights, dtype=float) / np.sum(weights)
    source_mean, target_mean = w @ source, w @ target
    H = (source - source_mean).T @ ((target - target_mean) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ flip @ U.T
    return make_transform(R, target_mean - R @ source_mean)


def _refine_in_pixels(
    start: FloatArray,
    cameras: Mapping[str, PinholeCamera],
    points: Mapping[str, FloatArray],
    pixels: Mapping[str, FloatArray],
    weights: Sequence[FloatArray],
) -> FloatArray:
    """The rigid transform from ``start`` that minimises the weighted squared pixel
    differences of ``cameras`` projecting the moved ``points`` (what is compared). The 3D
    fit alone cannot trade a focal length difference between the halves against a shift
    along the optical axis, which the projections at one range do not tell apart
    (measured, left / right median: OpenCV's 13 sample pairs 0.63 / 0.81 px after the 3D
    fit alone, 0.43 / 0.82 px after this one; generated rig 1 0.16 / 0.18 -> 0.04 / 0.07)."""
    root_weights = [np.sqrt(w / np.max(w))[:, None] for w in weights]

    def residuals(x: FloatArray) -> FloatArray:
        T = make_transform(cv2.Rodrigues(x[:3])[0], x[3:]) @ start
        return np.concatenate(
            [
                (w * (cameras[n].project(p @ T[:3, :3].T + T[:3, 3])[0] - pixels[n])).ravel()
                for (n, p), w in zip(points.items(), root_weights)
            ]
        )

    step = scipy.optimize.least_squares(residuals, np.zeros(6), method='lm').x
    return make_transform(cv2.Rodrigues(step[:3])[0], step[3:]) @ start


def compare_halves(
    half_a: Mapping[str, PinholeCamera],
    half_b: Mapping[str, PinholeCamera],
    ranges_m: Mapping[str, float],
    halves: tuple[int, int],
    align: bool,
    uncertainty: tuple[Uncertainty | None, Uncertainty | None] = (None, None),
    grid: tuple[int, int] = GRID,
) -> CrossValidation:
    """:class:`CrossValidation` of two solutions of one rig.

    Args:
        half_a, half_b: {name: camera} with poses in a frame shared by the halves
            (``align`` False) or each in its own (``align`` True: the rigid transform
            between them is fitted to every camera's points, each weighted by
            1 / (std_a^2 + std_b^2) of the halves' ``uncertainty`` grids when given).
        ranges_m: {name: working range [m]}.
        halves: the views in each half (reported).
    """
    pixels = {n: image_grid((c.width, c.height), grid) for n, c in half_a.items()}
    points_a = {n: points_at_range(c, pixels[n], ranges_m[n]) for n, c in half_a.items()}
    T_b_a = np.eye(4)
    if align:
        points_b = {n: points_at_range(half_b[n], pixels[n], ranges_m[n]) for n in half_a}
        known = [u for u in uncertainty if u is not None]
        weights = []
        for name in half_a:
            variance = np.full(len(pixels[name]), 1e-12)
            for u in known:
                variance += u.grid_px[name].ravel() ** 2
            weights.append(1.0 / variance if known else np.ones(len(variance)))
        start = rigid_fit(
            np.concatenate(list(points_a.values())),
            np.concatenate([points_b[n] for n in half_a]),
            np.concatenate(weights),
        )
        T_b_a = _refine_in_pixels(start, half_b, points_a, pixels, weights)
    worst, median, grids = {}, {}, {}
    for name, points in points_a.items():
        moved = points @ T_b_a[:3, :3].T + T_b_a[:3, 3]
        difference = np.linalg.norm(half_b[name].project(moved)[0] - pixels[name], axis=1)
        grids[name] = difference.reshape(grid[1], grid[0])
        worst[name] = float(difference.max())
        median[name] = float(np.median(difference))
    return CrossValidation(worst, median, dict(ranges_m), grids, halves, align)
