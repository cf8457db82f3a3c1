"""Pinhole camera with the distortion models of sensor_msgs/CameraInfo (plumb_bob,
rational_polynomial, equidistant: those of cv2.projectPoints and cv2.fisheye) or the
thesis's one-coefficient division distortion, as plain numpy.

Frames: ``T_base_camera`` maps camera optical-frame coordinates (z forward, x right,
y down) to ``base_link``. Pixels are (u, v) = (column, row) with the centre of the
top-left pixel at (0, 0), as in OpenCV and CameraInfo.

Distortion models (``PinholeCamera.distortion_model``), on normalised coordinates
x = (X/Z, Y/Z):

- ``plumb_bob``: D = (k1, k2, p1, p2, k3), OpenCV's forward polynomial.
- ``rational_polynomial``: D = (k1, k2, p1, p2, k3, k4, k5, k6), OpenCV's
  CALIB_RATIONAL_MODEL: the radial factor is (1 + k1 r^2 + k2 r^4 + k3 r^6) /
  (1 + k4 r^2 + k5 r^4 + k6 r^6), the tangential terms as plumb_bob's.
- ``equidistant``: D = (k1, k2, k3, k4), OpenCV's fisheye (cv2.fisheye): the angle
  theta = atan(r) off the axis is mapped to the radius theta (1 + k1 theta^2 + k2 theta^4
  + k3 theta^6 + k4 theta^8).
- ``division``: D = (kappa,), the thesis's (4.2.3) in normalised form (ALGORITHMS.md
  §3.2): x_d = x_u / (1 + kappa |x_d|^2), with the radius of the *distorted* point, so
  projecting solves a cubic and undistorting is explicit, x_u = x_d (1 + kappa |x_d|^2).
  The thesis's k (focal-plane units) gives kappa = k f^2.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray, invert_transform, make_transform, transform_points

DISTORTION_MODELS = ('plumb_bob', 'rational_polynomial', 'equidistant', 'division')
# len(D) each model takes (a shorter plumb_bob D is zero-padded, as OpenCV does)
DISTORTION_SIZES = {'plumb_bob': 5, 'rational_polynomial': 8, 'equidistant': 4, 'division': 1}
# The models of CameraInfo, cv2.projectPoints and cv2.fisheye (:func:`project_points`)
OPENCV_MODELS = ('plumb_bob', 'rational_polynomial', 'equidistant')
COEFFICIENT_NAMES = {
    'plumb_bob': 'k1, k2, p1, p2, k3',
    'rational_polynomial': 'k1, k2, p1, p2, k3, k4, k5, k6',
    'equidistant': 'k1, k2, k3, k4',
    'division': 'kappa',
}


def distort_normalized(xy: FloatArray, D: Iterable[float]) -> FloatArray:
    """Apply plumb_bob distortion D = (k1, k2, p1, p2, k3) to (N, 2) normalised points,
    or rational_polynomial's with an 8-vector D = (k1, k2, p1, p2, k3, k4, k5, k6).

    Same formula as OpenCV's projectPoints, so the two agree to rounding error.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = (list(D) + [0.0] * 8)[:8]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    x_d = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    y_d = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([x_d, y_d])


def distort_equidistant(xy: npt.ArrayLike, D: Iterable[float]) -> FloatArray:
    """Apply the equidistant (fisheye) model D = (k1, k2, k3, k4) to (N, 2) normalised
    points, as cv2.fisheye.projectPoints does."""
    xy = np.asarray(xy, dtype=float)
    k1, k2, k3, k4 = (list(D) + [0.0] * 4)[:4]
    r = np.hypot(xy[:, 0], xy[:, 1])
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    with np.errstate(divide='ignore', invalid='ignore'):
        scale = np.where(r > 1e-8, theta_d / r, 1.0)
    return xy * scale[:, None]


def undistort_equidistant(xy_d: npt.ArrayLike, D: Iterable[float]) -> FloatArray:
    """Invert :func:`distort_equidistant` on (N, 2) distorted normalised points: Newton on
    theta (from theta = theta_d) to ~1e-15; NaN where it does not converge (past the
    fold of a lens whose theta_d stops growing)."""
    xy_d = np.asarray(xy_d, dtype=float).reshape(-1, 2)
    k = np.array((list(D) + [0.0] * 4)[:4])
    theta_d = np.hypot(xy_d[:, 0], xy_d[:, 1])
    theta = theta_d.copy()
    for _ in range(50):
        t2 = theta * theta
        value = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - theta_d
        slope = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        step = value / slope
        theta = theta - step
        if np.all(np.abs(step) < 1e-15):
            break
    t2 = theta * theta
    residual = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - theta_d
    bad = ~(np.abs(residual) < 1e-9) | (theta < 0) | (theta >= np.pi / 2)
    with np.errstate(divide='ignore', invalid='ignore'):
        scale = np.where(theta_d > 1e-8, np.tan(theta) / theta_d, 1.0)
    scale[bad] = np.nan
    return xy_d * scale[:, None]


def distort(xy: npt.ArrayLike, D: Iterable[float], model: str) -> FloatArray:
    """Apply ``model``'s distortion (``DISTORTION_MODELS``) to (N, 2) normalised points."""
    xy = np.asarray(xy, dtype=float)
    if model == 'division':
        return distort_division(xy, float(next(iter(D))))
    if model == 'equidistant':
        return distort_equidistant(xy, D)
    return distort_normalized(xy, D)


def project_points(
    points: npt.ArrayLike,
    rvec: npt.ArrayLike,
    tvec: npt.ArrayLike,
    K: npt.ArrayLike,
    D: npt.ArrayLike,
    model: str = 'plumb_bob',
) -> tuple[FloatArray, FloatArray]:
    """Pixels (N, 2) of (N, 3) points by the world->camera pose (rvec, tvec), K and D of
    ``model`` (``OPENCV_MODELS``), and the Jacobian (2N, 10 + len(D)) by rvec (3), tvec
    (3), fx, fy, cx, cy, D in that order (cv2.projectPoints' order; cv2.fisheye's
    analytic Jacobian reordered to it, its skew column dropped)."""
    points = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 1, 3))
    rvec = np.asarray(rvec, dtype=float).reshape(3, 1)
    tvec = np.asarray(tvec, dtype=float).reshape(3, 1)
    K = np.asarray(K, dtype=float)
    D = np.asarray(D, dtype=float).ravel()
    if model == 'equidistant':
        uv, J = cv2.fisheye.projectPoints(points, rvec, tvec, K, D.reshape(4, 1))
        # cv2.fisheye's columns (checked against finite differences; its documentation
        # puts the skew fifth): f (2), c (2), k (4), rvec (3), tvec (3), skew
        J = J[:, [8, 9, 10, 11, 12, 13, 0, 1, 2, 3, 4, 5, 6, 7]]
    elif model in ('plumb_bob', 'rational_polynomial'):
        uv, J = cv2.projectPoints(points, rvec, tvec, K, D)
    else:
        raise InvalidInput(
            f'project_points: model {model!r} is not one of {", ".join(OPENCV_MODELS)}',
            key='distortion_model',
            value=model,
        )
    return np.asarray(uv, dtype=float).reshape(-1, 2), np.asarray(J, dtype=float)


def division_distorted_radius(r_u: npt.ArrayLike, kappa: float) -> FloatArray:
    """Distorted radius r >= 0 of the division model: the root of kappa r^3 + r = r_u.

    ``r_u`` (N,) undistorted radii, ``kappa`` the normalised coefficient. For kappa > 0
    the root is unique (closed form with sinh); for kappa < 0 it is the smallest
    positive root, the branch through r = r_u at kappa = 0, and NaN past the fold
    r_u > 2 / (3 sqrt(-3 kappa)) where the model has no real solution.
    """
    r_u = np.asarray(r_u, dtype=float)
    if kappa == 0:
        return r_u.copy()
    s = np.sqrt(3 * abs(kappa))
    with np.errstate(invalid='ignore'):
        if kappa > 0:
            r = 2 / s * np.sinh(np.arcsinh(1.5 * s * r_u) / 3)
        else:
            r = 2 / s * np.cos(np.arccos(-1.5 * s * r_u) / 3 - 2 * np.pi / 3)
    # One Newton step removes the cancellation of the cos form near r = 0 and leaves
    # both forms at rounding error, so project and undistort_pixels invert each other.
    return r - (kappa * r**3 + r - r_u) / (3 * kappa * r**2 + 1)


def distort_division(xy: npt.ArrayLike, kappa: float) -> FloatArray:
    """Apply the division model to (N, 2) undistorted normalised points."""
    xy = np.asarray(xy, dtype=float)
    r_d = division_distorted_radius(np.hypot(xy[:, 0], xy[:, 1]), kappa)
    return xy / (1 + kappa * r_d**2)[:, None]


@dataclass(frozen=True)
class PinholeCamera:
    """A calibrated camera: image size [px], intrinsics K (3x3), distortion D, pose.

    D is (k1, k2, p1, p2, k3) for ``distortion_model='plumb_bob'`` (shorter vectors are
    zero-padded, as OpenCV does), (k1, k2, p1, p2, k3, k4, k5, k6) for
    ``'rational_polynomial'``, (k1, k2, k3, k4) for ``'equidistant'`` and (kappa,) for
    ``'division'``.
    """

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    T_base_camera: np.ndarray
    distortion_model: str = 'plumb_bob'

    def __post_init__(self) -> None:
        for name in ('K', 'D', 'T_base_camera'):
            array = np.array(getattr(self, name), dtype=float)
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        if self.distortion_model not in DISTORTION_MODELS:
            raise InvalidInput(
                f'distortion_model: expected one of '
                f'{", ".join(DISTORTION_MODELS)}, got {self.distortion_model!r}',
                key='distortion_model',
                value=self.distortion_model,
            )
        size = DISTORTION_SIZES[self.distortion_model]
        if self.D.ndim != 1 or (
            len(self.D) != size if self.distortion_model != 'plumb_bob' else len(self.D) > size
        ):
            raise InvalidInput(
                f'D: the {self.distortion_model} model takes {size} coefficients, got {self.D}',
                key='D',
                value=self.D,
            )

    @classmethod
    def at_pose(
        cls,
        R_camera_base: npt.ArrayLike,
        centre_base: npt.ArrayLike,
        K: npt.ArrayLike | None = None,
        width: int = 0,
        height: int = 0,
    ) -> PinholeCamera:
        """A camera without distortion given the rotation base -> optical frame (3, 3)
        and its optical centre in base_link (3,) [m], the thesis's x_cam = R (x - c).

        K defaults to the identity: the thesis's idealised cameras (f = 1, pixels are
        normalised coordinates), whose image has no bounds (width = height = 0).
        ``R_camera_base`` and ``centre_base`` come back exactly from the camera.
        """
        R = np.asarray(R_camera_base, dtype=float)
        return cls(
            width,
            height,
            np.eye(3) if K is None else np.asarray(K, dtype=float),
            np.zeros(5),
            make_transform(R.T, centre_base),
        )

    @property
    def T_camera_base(self) -> FloatArray:
        """Inverse of ``T_base_camera`` (4x4): maps base_link points to the optical frame."""
        return invert_transform(self.T_base_camera)

    @property
    def R_camera_base(self) -> FloatArray:
        """Rotation (3, 3) taking base_link vectors to the optical frame."""
        return self.T_camera_base[:3, :3]

    @property
    def centre_base(self) -> FloatArray:
        """Optical centre in base_link [m]."""
        return self.T_base_camera[:3, 3].copy()

    def to_camera(self, points_base: npt.ArrayLike) -> FloatArray:
        """(N, 3) base_link points -> (N, 3) optical-frame points."""
        return transform_points(self.T_camera_base, points_base)

    def project_normalised(self, points_base: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Undistorted normalised image coordinates (x/z, y/z) (N, 2) and depth z (N,) [m]
        of (N, 3) base_link points, as R_camera_base (x - centre_base); NaN coordinates
        behind the camera (depth <= 0). The thesis's projection (f = 1), before K and D.
        """
        camera = (np.asarray(points_base, dtype=float) - self.centre_base) @ self.R_camera_base.T
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = camera[:, :2] / camera[:, 2:]
        xy[camera[:, 2] <= 0] = np.nan
        return xy, camera[:, 2]

    def project(self, points_base: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Project (N, 3) base_link points.

        Returns (pixels (N, 2) [px], depth (N,) [m] along the optical axis). Points with
        depth <= 0, and past the fold of a division model with kappa < 0, get NaN pixels.
        """
        points_camera = self.to_camera(np.atleast_2d(points_base))
        depth = points_camera[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = points_camera[:, :2] / depth[:, None]
        xy[depth <= 0] = np.nan
        xy_d = distort(xy, self.D, self.distortion_model)
        K = self.K
        pixels = np.column_stack(
            [K[0, 0] * xy_d[:, 0] + K[0, 1] * xy_d[:, 1] + K[0, 2], K[1, 1] * xy_d[:, 1] + K[1, 2]]
        )
        return pixels, depth

    def undistort_pixels(self, pixels: npt.ArrayLike) -> FloatArray:
        """(N, 2) pixels -> (N, 2) normalised undistorted coordinates (x/z, y/z)."""
        if self.distortion_model == 'division':  # explicit in this direction: exact
            pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
            K = self.K
            y_d = (pixels[:, 1] - K[1, 2]) / K[1, 1]
            x_d = (pixels[:, 0] - K[0, 2] - K[0, 1] * y_d) / K[0, 0]
            radial = 1 + self.D[0] * (x_d * x_d + y_d * y_d)
            return np.column_stack([x_d * radial, y_d * radial])
        if self.distortion_model == 'equidistant':
            pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
            K = self.K
            y_d = (pixels[:, 1] - K[1, 2]) / K[1, 1]
            x_d = (pixels[:, 0] - K[0, 2] - K[0, 1] * y_d) / K[0, 0]
            return undistort_equidistant(np.column_stack([x_d, y_d]), self.D)
        pts = np.ascontiguousarray(np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2))
        # OpenCV 5 folded undistortPointsIter into undistortPoints: with these criteria the
        # iteration runs to ~1e-15 instead of its default 5 fixed steps (~1e-5 at k1 = -0.3).
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        undistorted = cv2.undistortPoints(pts, self.K, self.D, None, None, None, criteria)
        return cast(FloatArray, undistorted.reshape(-1, 2))  # float64 in, float64 out

    def pixel_rays_base(self, pixels: npt.ArrayLike) -> FloatArray:
        """Unit ray directions in base_link (N, 3) through the given (N, 2) pixels."""
        xy = self.undistort_pixels(pixels)
        rays_camera = np.column_stack([xy, np.ones(len(xy))])
        rays_camera /= np.linalg.norm(rays_camera, axis=1, keepdims=True)
        return rays_camera @ self.T_base_camera[:3, :3].T
