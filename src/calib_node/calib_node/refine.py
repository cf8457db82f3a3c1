"""Chapter 4 "better" (ALGORITHMS.md §8): Levenberg-Marquardt refinement of a stereo
calibration in the identifiable parameters (A4.1) of the full seed model (§3.2, A4.3),
and an OpenCV reference (DLT initial guess, ``calibrateCamera``, ``stereoCalibrate``).

Both cameras use the seed conventions: X = R x + T maps world to camera, pixels in
[px], lengths in the thesis's unit. The DLT is the standard 3x4 projection estimate with
Hartley normalisation and an RQ decomposition.
"""
from typing import NamedTuple

import cv2
import numpy as np
from scipy.linalg import rq
from scipy.optimize import least_squares

from calib_node.seed_camera import Identifiable, identifiable, project_seed

IDENTIFIABLE_NAMES = ('u0', 'v0', 'fx', 'fy', 'kappa', 'alpha', 'beta', 'gamma', 'Tx', 'Ty',
                      'Tz')


class RefineInfo(NamedTuple):
    rms_left: float  # sqrt(mean |reprojection error|^2) over the points [px]
    rms_right: float
    iterations: int  # Jacobian evaluations of the solver
    status: int  # scipy.optimize.least_squares status (> 0: converged)
    std: np.ndarray  # (2, 11) standard errors of IDENTIFIABLE_NAMES, s^2 (J^T J)^-1
    left: Identifiable
    right: Identifiable


class OpenCVReference(NamedTuple):
    K_left: np.ndarray  # (3, 3) [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] [px]
    K_right: np.ndarray
    dist_left: np.ndarray  # (5,) (k1, k2, p1, p2, k3), tangential fixed at 0
    dist_right: np.ndarray
    R_left: np.ndarray  # (3, 3) world -> left camera
    T_left: np.ndarray  # (3,) [unit]
    R_right: np.ndarray
    T_right: np.ndarray
    R: np.ndarray  # (3, 3) left camera -> right camera (stereoCalibrate)
    T: np.ndarray  # (3,) [unit]
    rms_left: float  # calibrateCamera RMS per point [px]
    rms_right: float
    rms_stereo: float  # stereoCalibrate RMS over both images [px]


def _to_identifiable(params):
    """(12,) seed params -> (11,) z = (u0, v0, fx, fy, kappa, alpha, beta, gamma, T)."""
    f = params[4]
    return np.concatenate([params[0:2], params[2:4] * f, [params[5] * f ** 2], params[6:12]])


def _from_identifiable(z, f):
    """Inverse of :func:`_to_identifiable` with the focal length f held fixed."""
    return np.concatenate([z[0:2], z[2:4] / f, [f], [z[4] / f ** 2], z[5:11]])


def _check_points(points_world, *pixels):
    points_world = np.asarray(points_world, dtype=float)
    if points_world.ndim != 2 or points_world.shape[1] != 3:
        raise ValueError(f'points_world: expected shape (N, 3), got {points_world.shape}')
    out = [np.asarray(p, dtype=float) for p in pixels]
    for p in out:
        if p.shape != (points_world.shape[0], 2):
            raise ValueError(f'pixels: expected shape ({points_world.shape[0]}, 2), '
                             f'got {p.shape}')
    return points_world, out


def refine_seed_lm(params_left, params_right, points_world, pixels_left, pixels_right):
    """Minimise the stereo reprojection error (4.3.2, full model) from a starting guess.

    The 11 identifiable parameters per camera (u0, v0, fx = f Nx, fy = f Ny, kappa = k f^2,
    alpha, beta, gamma, Tx, Ty, Tz; A4.1) are refined by a trust-region Gauss-Newton /
    LM solver (scipy ``trf``, ``x_scale='jac'``, kappa >= 0). f stays at its start value
    and Nx, Ny, k are re-derived from the products.

    Args:
        params_left, params_right: (12,) start cameras in ``PARAM_NAMES`` order, e.g. the
            GA result.
        points_world: (N, 3) control points [unit].
        pixels_left, pixels_right: (N, 2) observed pixels (u, v) [px].

    Returns:
        (left (12,), right (12,), :class:`RefineInfo`).

    Raises:
        ValueError: on bad shapes, f <= 0 or k < 0.
    """
    start = [np.asarray(p, dtype=float) for p in (params_left, params_right)]
    if any(p.shape != (12,) for p in start):
        raise ValueError('params_left, params_right: expected shape (12,)')
    if any(p[4] <= 0 or p[5] < 0 for p in start):
        raise ValueError('params: need f > 0 and k >= 0')
    points_world, observed = _check_points(points_world, pixels_left, pixels_right)
    focal = [p[4] for p in start]

    def cameras(x):
        return [_from_identifiable(x[11 * c:11 * c + 11], focal[c]) for c in range(2)]

    def residuals(x):
        return np.concatenate([(project_seed(p[None], points_world)[0] - obs).ravel()
                               for p, obs in zip(cameras(x), observed)])

    x0 = np.concatenate([_to_identifiable(p) for p in start])
    lower = np.full(22, -np.inf)
    lower[[4, 15]] = 0.0  # kappa >= 0
    result = least_squares(residuals, x0, bounds=(lower, np.inf), method='trf',
                           x_scale='jac', jac='3-point', ftol=1e-15, xtol=1e-15,
                           gtol=1e-15, max_nfev=200)
    left, right = cameras(result.x)
    dof = max(result.fun.size - result.x.size, 1)
    covariance = np.sum(result.fun ** 2) / dof * np.linalg.pinv(result.jac.T @ result.jac)
    rms = np.sqrt(np.mean(result.fun.reshape(2, -1, 2) ** 2, axis=(1, 2)) * 2)
    info = RefineInfo(rms_left=float(rms[0]), rms_right=float(rms[1]),
                      iterations=int(result.njev), status=int(result.status),
                      std=np.sqrt(np.diag(covariance)).reshape(2, 11),
                      left=identifiable(left), right=identifiable(right))
    return left, right, info


def _normalise(points):
    """Similarity T (d+1, d+1) moving (N, d) points to centroid 0, mean distance sqrt(d)."""
    d = points.shape[1]
    centre = points.mean(axis=0)
    scale = np.sqrt(d) / np.mean(np.linalg.norm(points - centre, axis=1))
    T = np.diag(np.append(np.full(d, scale), 1.0))
    T[:d, d] = -scale * centre
    return T


def dlt_camera(points_world, pixels):
    """Pinhole camera (K, R, t) with pixels ~ K (R x + t), from >= 6 non-coplanar points.

    Normalised DLT of the 3x4 P (SVD null vector), then P[:, :3] = K R by RQ, with the
    diagonal of K made positive, det R = +1 and K[2, 2] = 1. Distortion is ignored.

    Args:
        points_world: (N, 3) [unit]; pixels: (N, 2) [px].

    Returns:
        K (3, 3) upper triangular [px], R (3, 3) world -> camera, t (3,) [unit].
    """
    points_world, (pixels,) = _check_points(points_world, pixels)
    if points_world.shape[0] < 6:
        raise ValueError('dlt_camera: needs at least 6 points')
    T3, T2 = _normalise(points_world), _normalise(pixels)
    X = np.column_stack([points_world, np.ones(len(points_world))]) @ T3.T
    x = np.column_stack([pixels, np.ones(len(pixels))]) @ T2.T
    zero = np.zeros_like(X)
    A = np.concatenate([np.hstack([X, zero, -x[:, :1] * X]),
                        np.hstack([zero, X, -x[:, 1:2] * X])])
    P = np.linalg.inv(T2) @ np.linalg.svd(A)[2][-1].reshape(3, 4) @ T3
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    K, R = rq(P[:, :3])
    signs = np.diag(np.sign(np.diag(K)))  # K R = (K S)(S R), S^2 = I
    K, R = K @ signs, signs @ R
    t = np.linalg.solve(K, P[:, 3])
    return K / K[2, 2], R, t


def opencv_reference(points_world, pixels_left, pixels_right, image_size_left,
                     image_size_right):
    """OpenCV calibration of the same single non-planar view, as a reference.

    Each camera: DLT intrinsic guess, then ``calibrateCamera`` with
    ``CALIB_USE_INTRINSIC_GUESS`` and radial k1, k2, k3 (tangential fixed at 0); then
    ``stereoCalibrate`` with ``CALIB_FIX_INTRINSIC``. OpenCV's radial model is a forward
    polynomial, the seed's an implicit division model: compare RMS, not coefficients.

    Args:
        points_world: (N, 3) [unit]; pixels_left, pixels_right: (N, 2) [px];
        image_size_left, image_size_right: (width, height) [px].

    Returns:
        :class:`OpenCVReference`.
    """
    points_world, pixels = _check_points(points_world, pixels_left, pixels_right)
    objects = [points_world.astype(np.float32).reshape(-1, 1, 3)]
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    images, fits = [], []
    for uv, size in zip(pixels, (image_size_left, image_size_right)):
        images.append([uv.astype(np.float32).reshape(-1, 1, 2)])
        K0 = dlt_camera(points_world, uv)[0]
        K0[0, 1] = 0.0  # OpenCV has no skew; it needs the principal point in the image
        K0[:2, 2] = np.clip(K0[:2, 2], 0.0, np.asarray(size, dtype=float) - 1.0)
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            objects, images[-1], tuple(int(s) for s in size), K0, np.zeros(5), flags=flags,
            criteria=criteria)
        fits.append((rms, K, dist.ravel(), cv2.Rodrigues(rvecs[0])[0], tvecs[0].ravel()))
    (rms_l, K_l, d_l, R_l, t_l), (rms_r, K_r, d_r, R_r, t_r) = fits
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        objects, images[0], images[1], K_l, d_l, K_r, d_r,
        tuple(int(s) for s in image_size_left), flags=cv2.CALIB_FIX_INTRINSIC, criteria=criteria)
    return OpenCVReference(K_l, K_r, d_l, d_r, R_l, t_l, R_r, t_r, R, T.ravel(),
                           float(rms_l), float(rms_r), float(rms))
