"""Pinhole camera with plumb_bob distortion (the model of sensor_msgs/CameraInfo and of
cv2.projectPoints), as plain numpy.

Frames: ``T_base_camera`` maps camera optical-frame coordinates (z forward, x right,
y down) to ``base_link``. Pixels are (u, v) = (column, row) with the centre of the
top-left pixel at (0, 0), as in OpenCV and CameraInfo.
"""
from dataclasses import dataclass

import cv2
import numpy as np

from vgm_common.geometry import invert_transform, transform_points


def distort_normalized(xy, D):
    """Apply plumb_bob distortion D = (k1, k2, p1, p2, k3) to (N, 2) normalised points.

    Same formula as OpenCV's projectPoints, so the two agree to rounding error.
    """
    k1, k2, p1, p2, k3 = (list(D) + [0.0] * 5)[:5]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    x_d = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    y_d = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([x_d, y_d])


@dataclass(frozen=True)
class PinholeCamera:
    """A calibrated camera: image size [px], intrinsics K (3x3), plumb_bob D (5,), pose."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    T_base_camera: np.ndarray

    def __post_init__(self):
        for name in ('K', 'D', 'T_base_camera'):
            array = np.array(getattr(self, name), dtype=float)
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def T_camera_base(self):
        return invert_transform(self.T_base_camera)

    @property
    def centre_base(self):
        """Optical centre in base_link [m]."""
        return self.T_base_camera[:3, 3].copy()

    def to_camera(self, points_base):
        """(N, 3) base_link points -> (N, 3) optical-frame points."""
        return transform_points(self.T_camera_base, points_base)

    def project(self, points_base):
        """Project (N, 3) base_link points.

        Returns (pixels (N, 2) [px], depth (N,) [m] along the optical axis). Points with
        depth <= 0 get NaN pixels.
        """
        points_camera = self.to_camera(np.atleast_2d(points_base))
        depth = points_camera[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = points_camera[:, :2] / depth[:, None]
        xy[depth <= 0] = np.nan
        xy_d = distort_normalized(xy, self.D)
        K = self.K
        pixels = np.column_stack([K[0, 0] * xy_d[:, 0] + K[0, 1] * xy_d[:, 1] + K[0, 2],
                                  K[1, 1] * xy_d[:, 1] + K[1, 2]])
        return pixels, depth

    def undistort_pixels(self, pixels):
        """(N, 2) pixels -> (N, 2) normalised undistorted coordinates (x/z, y/z)."""
        pts = np.ascontiguousarray(np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2))
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        return cv2.undistortPointsIter(pts, self.K, self.D, None, None, criteria).reshape(-1, 2)

    def pixel_rays_base(self, pixels):
        """Unit ray directions in base_link (N, 3) through the given (N, 2) pixels."""
        xy = self.undistort_pixels(pixels)
        rays_camera = np.column_stack([xy, np.ones(len(xy))])
        rays_camera /= np.linalg.norm(rays_camera, axis=1, keepdims=True)
        return rays_camera @ self.T_base_camera[:3, :3].T
