"""How well a calibration determines its cameras: the covariance of the solution
propagated to the projection of points at the working range, and to the baseline. No
rclpy.

As mrcal does it: the parameters' covariance is (J^T J)^-1 scaled by the residual variance
s^2 = RSS / (n - p) of the final adjustment (the corners' noise as the fit itself
measures it). A point is fixed in the reference frame (base_link on the stage, the left
camera handheld) at the working range (the median depth of the chart corners the camera
saw) on the ray of each pixel of a grid over the whole image; its projection moves with
the camera's intrinsics and pose by J_q, so its covariance is J_q C J_q^T. The figure per
pixel is sqrt(trace) of that 2 x 2 covariance: the expected length of the projection
error [px] (the RMS over many calibrations of the same rig).

Parameters are addressed in ``cv2.projectPoints``' Jacobian order: rvec (3), tvec (3) of
T_camera_ref, fx, fy, cx, cy, then D of the camera's model (plumb_bob k1, k2, p1, p2, k3).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from vgm_common.camera_model import PinholeCamera, project_points
from vgm_common.geometry import FloatArray, invert_transform

GRID = (16, 12)  # grid pixels across and down the image
IndexArray = npt.NDArray[np.int_]


class RigCamera(NamedTuple):
    """A calibrated camera of a rig, for the propagation: the camera (its
    ``T_base_camera`` the pose in the rig's reference frame: base_link on the stage, the
    left camera handheld), its working range [m] and the rows of its 10 + len(D)
    parameters (rvec, tvec, fx, fy, cx, cy, D) in the rig's covariance (-1: held
    fixed)."""

    camera: PinholeCamera
    range_m: float
    rows: IndexArray


class Uncertainty(NamedTuple):
    """Per camera the worst and median projection standard deviation over the image grid
    [px], the working range it is taken at [m] and the grid itself ((rows, cols) [px]);
    the baseline's standard deviation [m] (nan without left and right)."""

    worst_px: dict[str, float]
    median_px: dict[str, float]
    range_m: dict[str, float]
    grid_px: dict[str, FloatArray]
    baseline_std_m: float

    def worst(self) -> tuple[str, float]:
        """(camera, px) of the largest projection standard deviation of the rig."""
        name = max(self.worst_px, key=lambda n: self.worst_px[n])
        return name, self.worst_px[name]


def parameter_covariance(
    jacobian: npt.ArrayLike, residuals: npt.ArrayLike, groups: npt.ArrayLike | None = None
) -> FloatArray:
    """(p, p) covariance of the (unweighted) least-squares solution.

    One noise level (``groups`` None): s^2 (J^T J)^+ with s^2 = RSS / (n - p). With
    ``groups`` (a label per residual, e.g. its camera and view) each group's noise is its
    own, s_g^2 = RSS_g / (n_g (n - p) / n), and the covariance the sandwich
    (J^T J)^+ J^T S J (J^T J)^+ with S = diag(s_g^2): corners of a far or steep view are
    noisier than a near frontal one's, and one pooled s^2 would lend the informative views
    the noise of the others. Pseudo-inverse: a direction the data do not fix gets no
    finite variance claimed from a rounding-level pivot.
    """
    J = np.asarray(jacobian, dtype=float)
    r = np.asarray(residuals, dtype=float)
    share = max(r.size - J.shape[1], 1) / r.size  # degrees of freedom per residual
    # Columns scaled to unit norm first: fx (1000s of px) and k3 share one J^T J.
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    Js = J / scale
    inverse = np.linalg.pinv(Js.T @ Js, rcond=1e-13, hermitian=True)
    if groups is None:
        return float(r @ r) / (share * r.size) * inverse / np.outer(scale, scale)
    labels, group = np.unique(np.asarray(groups), return_inverse=True)
    variance = np.bincount(group, weights=r**2) / (share * np.bincount(group))
    weighted = Js * np.sqrt(variance[group])[:, None]
    return inverse @ (weighted.T @ weighted) @ inverse / np.outer(scale, scale)


def canonical_rotations(x: FloatArray, starts: Sequence[int]) -> FloatArray:
    """``x`` with the Rodrigues vectors at ``starts`` as cv2.Rodrigues gives them for their
    rotation (angle at most pi). LM may step past pi to the equivalent vector on the
    other side; a covariance taken there is in other coordinates than the pose the
    propagation reads back from the rotation matrix (measured: a camera turned 174 deg
    had its projection uncertainty overstated 17x)."""
    x = np.array(x, dtype=float)
    for start in starts:
        R = cv2.Rodrigues(x[start : start + 3])[0]
        x[start : start + 3] = cv2.Rodrigues(R)[0].ravel()
    return x


def image_grid(size: tuple[int, int], grid: tuple[int, int] = GRID) -> FloatArray:
    """(rows * cols, 2) pixels of a grid spanning the whole image, row by row."""
    width, height = size
    u, v = np.meshgrid(np.linspace(0, width - 1, grid[0]), np.linspace(0, height - 1, grid[1]))
    return np.column_stack([u.ravel(), v.ravel()])


def points_at_range(camera: PinholeCamera, pixels: FloatArray, depth: float) -> FloatArray:
    """(M, 3) points at ``depth`` [m] along ``camera``'s rays of ``pixels``, in the frame
    its ``T_base_camera`` is given in."""
    xy = camera.undistort_pixels(pixels)
    points_camera = np.column_stack([xy * depth, np.full(len(xy), depth)])
    T = camera.T_base_camera
    return points_camera @ T[:3, :3].T + T[:3, 3]


def _rt(T: FloatArray) -> tuple[FloatArray, FloatArray]:
    rvec = np.asarray(cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0], dtype=float)
    return rvec.ravel(), T[:3, 3].copy()


def _block(covariance: FloatArray, index: IndexArray) -> FloatArray:
    """The covariance of the parameters ``index`` (-1: fixed, zero rows)."""
    out = np.zeros((len(index), len(index)))
    held = index >= 0
    out[np.ix_(held, held)] = covariance[np.ix_(index[held], index[held])]
    return out


def projection_std(
    rig_camera: RigCamera, covariance: FloatArray, pixels: FloatArray
) -> FloatArray:
    """(M,) sqrt(trace) of the projection covariance [px] of the points at the working
    range on the rays of ``pixels``."""
    camera = rig_camera.camera
    points = points_at_range(camera, pixels, rig_camera.range_m)
    rvec, tvec = _rt(camera.T_camera_base)
    _, J = project_points(points, rvec, tvec, camera.K, camera.D, camera.distortion_model)
    C = _block(covariance, rig_camera.rows)
    J = J[:, : len(rig_camera.rows)]
    per_row = np.einsum('ij,jk,ik->i', J, C, J)  # diagonal of J C J^T
    return np.sqrt(np.maximum(per_row.reshape(-1, 2).sum(axis=1), 0.0))


def _pose(rt: FloatArray) -> FloatArray:
    """(4, 4) transform of a (6,) Rodrigues vector and translation."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rt[:3])[0]
    T[:3, 3] = rt[3:]
    return T


def projection_std_chart_fixed(
    rig_camera: RigCamera,
    covariance: FloatArray,
    pixels: FloatArray,
    T_ref_chart: Sequence[FloatArray],
    chart_rows: Sequence[IndexArray],
    step: float = 1e-6,
) -> FloatArray:
    """(M,) sqrt(trace) of the projection covariance [px] of the points at the working
    range on the rays of ``pixels``, each point held fixed to the charts rather than to
    the reference frame: mrcal's 'mean-pcam'. Each chart pose i maps the point into its
    chart frame once (p_i = T_ref_chart_i^-1 p); a perturbed solution places it at the
    mean over the charts of T_ref_chart_i' p_i and projects that with the perturbed
    camera. Without an estimated chart pose (``chart_rows`` all -1: the stage's known
    poses) this is :func:`projection_std`.

    Why: handheld, the reference frame is the left camera's own optical frame, which
    floats with its intrinsics (a principal point error comes with a rotation of every
    chart pose the other way); no projection of a point of the observed scene sees that
    float, but a point fixed in the floating frame does (measured: OpenCV's 13 sample
    pairs, 0.82 px flat over the image from cx, cy alone; generated rigs: the prediction
    held against the true error in both gauges, README "Uncertainty").

    Args:
        rig_camera: the camera in the reference frame, its 10 + len(D) parameters'
            ``rows``.
        covariance: the adjustment's covariance.
        pixels: (M, 2) [px].
        T_ref_chart: (4, 4) chart pose of every view in the reference frame.
        chart_rows: (6,) rows of each chart pose (Rodrigues vector, translation) in
            ``covariance`` (-1: held fixed).
    """
    camera = rig_camera.camera
    points = points_at_range(camera, pixels, rig_camera.range_m)
    charts = [invert_transform(T) for T in T_ref_chart]
    points_chart = np.stack([points @ T[:3, :3].T + T[:3, 3] for T in charts])  # (V, M, 3)
    rvec, tvec = _rt(camera.T_camera_base)
    K, D = camera.K, camera.D
    x0 = np.concatenate(
        [
            rvec,
            tvec,
            [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
            D,
            *[np.concatenate(_rt(T)) for T in T_ref_chart],
        ]
    )
    index = np.concatenate([rig_camera.rows, *chart_rows])
    own = 10 + len(D)  # the camera's parameters, then the charts'

    def project(x: FloatArray) -> FloatArray:
        poses = x[own:].reshape(-1, 6)
        mean = np.mean(
            [p @ _pose(rt)[:3, :3].T + rt[3:] for p, rt in zip(points_chart, poses)], axis=0
        )
        Kx = np.array([[x[6], 0, x[8]], [0, x[7], x[9]], [0, 0, 1.0]])
        uv = project_points(mean, x[:3], x[3:6], Kx, x[10:own], camera.distortion_model)[0]
        return uv.ravel()

    held = np.flatnonzero(index >= 0)
    J = np.zeros((2 * len(pixels), len(held)))
    for k, column in enumerate(held):
        dx = np.zeros(len(x0))
        dx[column] = step * max(1.0, abs(x0[column]))
        J[:, k] = (project(x0 + dx) - project(x0 - dx)) / (2 * dx[column])
    C = covariance[np.ix_(index[held], index[held])]
    per_row = np.einsum('ij,jk,ik->i', J, C, J)
    return np.sqrt(np.maximum(per_row.reshape(-1, 2).sum(axis=1), 0.0))


def _centre_jacobian(T_camera_ref: FloatArray, step: float = 1e-7) -> FloatArray:
    """(3, 6) derivative of the camera centre -R^T t in the reference frame by its
    (rvec, tvec) (central differences)."""
    x = np.concatenate(_rt(T_camera_ref))

    def centre(p: FloatArray) -> FloatArray:
        R = cv2.Rodrigues(p[:3])[0]
        return np.asarray(-R.T @ p[3:], dtype=float)

    J = np.empty((3, 6))
    for k in range(6):
        dx = np.zeros(6)
        dx[k] = step
        J[:, k] = (centre(x + dx) - centre(x - dx)) / (2 * step)
    return J


def baseline_std(left: RigCamera, right: RigCamera, covariance: FloatArray) -> float:
    """Standard deviation [m] of |centre_left - centre_right| (the poses' joint covariance)."""
    index = np.concatenate([left.rows[:6], right.rows[:6]])
    C = _block(covariance, index)
    c_left, c_right = left.camera.centre_base, right.camera.centre_base
    direction = (c_right - c_left) / np.linalg.norm(c_right - c_left)
    g = np.concatenate(
        [
            -direction @ _centre_jacobian(left.camera.T_camera_base),
            direction @ _centre_jacobian(right.camera.T_camera_base),
        ]
    )
    return float(np.sqrt(max(g @ C @ g, 0.0)))


class ChartPoses(NamedTuple):
    """The estimated chart poses of a handheld adjustment: (4, 4) T_ref_chart per view and
    the rows of its (Rodrigues vector, translation) in the covariance."""

    T_ref_chart: Sequence[FloatArray]
    rows: Sequence[IndexArray]


def rig_uncertainty(
    cameras: Mapping[str, RigCamera],
    covariance: FloatArray,
    grid: tuple[int, int] = GRID,
    charts: ChartPoses | None = None,
) -> Uncertainty:
    """:class:`Uncertainty` of a rig from its parameters' ``covariance``; with ``charts``
    the points are held fixed to the charts (:func:`projection_std_chart_fixed`), else
    to the reference frame."""
    worst, median, ranges, grids = {}, {}, {}, {}
    for name, camera in cameras.items():
        pixels = image_grid((camera.camera.width, camera.camera.height), grid)
        if charts is None:
            std = projection_std(camera, covariance, pixels)
        else:
            std = projection_std_chart_fixed(
                camera, covariance, pixels, charts.T_ref_chart, charts.rows
            )
        # A pixel without a ray in front of the camera (a fisheye's image corners past 90
        # deg, or past the fold of a lens extrapolated beyond the charts) has no point to
        # project: left out (NaN in the grid); none with a ray: nothing is determined.
        rays = np.isfinite(std)
        worst[name] = float(std[rays].max()) if rays.any() else float('inf')
        median[name] = float(np.median(std[rays])) if rays.any() else float('inf')
        ranges[name] = camera.range_m
        grids[name] = std.reshape(grid[1], grid[0])
    baseline = (
        baseline_std(cameras['left'], cameras['right'], covariance)
        if 'left' in cameras and 'right' in cameras
        else float('nan')
    )
    return Uncertainty(worst, median, ranges, grids, baseline)


def working_range(points_camera: FloatArray) -> float:
    """The median depth [m] of chart corners (M, 3) in a camera's frame."""
    return float(np.median(np.asarray(points_camera)[:, 2]))
