"""The conventional peer of the curve reconstruction, for benches and tests: epipolar
matching of view-1 chain points along view 2's chain polyline, cv2.triangulatePoints,
and view 3 to choose among several crossings (and to reject points off its chain), on
the same extracted chains and calibration the node uses; and the thesis's measure of a
planar curve's reconstruction, the angle between the planes (§2.5).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from curve_recon_node.algebraic_curves import IntArray
from vgm_common.camera_model import PinholeCamera
from vgm_common.geometry import FloatArray

if TYPE_CHECKING:
    from curve_recon_node.piecewise import View


def _closed_polyline(xy: FloatArray, closed: bool) -> FloatArray:
    return np.vstack([xy, xy[:1]]) if closed else xy


def densify_polyline(
    xy: FloatArray, breaks: Iterable[int] | None = None, per: int = 20
) -> FloatArray:
    """``per`` points per segment of a polyline (N, 2); no segment ends at an index in
    ``breaks`` (the polyline jumps there)."""
    breaks = set() if breaks is None else set(int(b) for b in breaks)
    keep = np.array([k + 1 not in breaks for k in range(len(xy) - 1)], dtype=bool)
    fractions = np.linspace(0, 1, per, endpoint=False)
    a, b = xy[:-1][keep], xy[1:][keep]
    dense = a[:, None, :] + fractions[None, :, None] * (b - a)[:, None, :]
    return np.vstack([dense.reshape(-1, 2), xy[-1:]])


def triangulate_chains(
    xy_views: Sequence[npt.ArrayLike],
    cameras: Sequence[PinholeCamera],
    closed: Sequence[bool],
    focal_px: float,
    tol3_px: float = 2.0,
    breaks: Sequence[int] | np.ndarray | None = None,
) -> tuple[FloatArray, IntArray]:
    """Point-based reconstruction of a curve from its chains in two or three views.

    Args:
        xy_views: per view, the ordered chain (N_i, 2) in undistorted normalised image
            coordinates, view 1 first.
        cameras: per view, the camera (its pose; the chains are already normalised).
        closed: per view, whether its chain is a loop.
        focal_px: [px] per normalised unit, for the view-3 tolerance.
        tol3_px: [px] largest distance of a point's view-3 projection to view 3's chain.
        breaks: indices where the chains of views 2 and 3 jump (no segment there; the
            thesis's line pair has its two pieces in one array).

    Returns (points (K, 3) in base [m] in view-1 order, view-1 indices (K,)). With two
    views, view-1 points whose epipolar line crosses view 2's chain more than once are
    dropped (ambiguous).
    """
    R_camera_base = [camera.R_camera_base for camera in cameras]
    centre_base = [camera.centre_base for camera in cameras]
    # the thesis's 3 x 4 camera matrices [R | -R c] (f = 1), at cv2's boundary only
    P = [np.hstack([R, (-R @ c)[:, None]]) for R, c in zip(R_camera_base, centre_base)]
    xy1 = np.asarray(xy_views[0], float)
    xy2 = _closed_polyline(np.asarray(xy_views[1], float), closed[1])
    R1, R2 = R_camera_base[0], R_camera_base[1]
    c1, c2 = centre_base[0], centre_base[1]
    # epipolar line in view 2 of each view-1 point: through the epipole and the image of
    # a point one unit along the ray
    c1_in_2 = R2 @ (c1 - c2)
    rays = np.column_stack([xy1, np.ones(len(xy1))]) @ R1  # base directions
    far = (c1 + rays - c2) @ R2.T
    lines = np.cross(c1_in_2[None], far)
    side = np.column_stack([xy2, np.ones(len(xy2))]) @ lines.T  # (N2, N1)
    valid_segment = np.ones(len(xy2) - 1, bool)
    if breaks is not None:
        valid_segment[np.asarray(breaks, int) - 1] = False
    crossing = (side[:-1] * side[1:] <= 0) & valid_segment[:, None] & (side[:-1] != side[1:])
    segment, point = np.nonzero(crossing)
    w = side[segment, point] / (side[segment, point] - side[segment + 1, point])
    matches = xy2[segment] + w[:, None] * (xy2[segment + 1] - xy2[segment])
    if not len(point):
        return np.zeros((0, 3)), np.zeros(0, int)
    X = cv2.triangulatePoints(P[0], P[1], xy1[point].T, matches.T)
    X = (X[:3] / X[3]).T
    if len(xy_views) > 2:
        R3, c3 = R_camera_base[2], centre_base[2]
        x3 = (X - c3) @ R3.T
        with np.errstate(divide='ignore', invalid='ignore'):
            proj3 = x3[:, :2] / x3[:, 2:]
        dense3 = cKDTree(
            densify_polyline(_closed_polyline(np.asarray(xy_views[2], float), closed[2]), breaks)
        )
        d3 = dense3.query(np.nan_to_num(proj3, nan=1e9))[0] * focal_px
        d3[~(x3[:, 2] > 0)] = np.inf
    else:
        d3 = np.zeros(len(X))
    order = np.lexsort((d3, point))  # per view-1 point, the best crossing first
    point, X, d3 = point[order], X[order], d3[order]
    first = np.concatenate([[True], point[1:] != point[:-1]])
    counts = np.bincount(point, minlength=len(xy1))
    keep = first & (d3 <= tol3_px)
    if len(xy_views) == 2:
        keep &= counts[point] == 1
    return X[keep], point[keep]


def triangulate_views(views: Sequence[View], tol3_px: float = 2.0) -> tuple[FloatArray, IntArray]:
    """``triangulate_chains`` on the node's ``piecewise.View`` objects (their chains as
    extracted and undistorted)."""
    return triangulate_chains(
        [v.curve.xy for v in views],
        [v.camera for v in views],
        [v.curve.closed for v in views],
        views[-1].curve.focal_px,
        tol3_px,
    )


def fit_plane(points: npt.ArrayLike) -> tuple[FloatArray, float]:
    """Unit normal (3,) and offset d of the SVD plane n.x + d = 0 through (N, 3) points."""
    points = np.asarray(points, dtype=float)
    centroid = points.mean(axis=0)
    normal = np.linalg.svd(points - centroid, full_matrices=False)[2][-1]
    return normal, -normal @ centroid


def plane_angle_error_deg(true_points: npt.ArrayLike, reconstructed: npt.ArrayLike) -> float:
    """Angle [deg] between the SVD planes of (N, 3) true and (K, 3) reconstructed points
    (§2.5, |cos delta|, computed as atan2(|n1 x n2|, |n1 . n2|) for accuracy near 0)."""
    n1, _ = fit_plane(true_points)
    n2, _ = fit_plane(reconstructed)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(n1, n2)), abs(n1 @ n2))))
