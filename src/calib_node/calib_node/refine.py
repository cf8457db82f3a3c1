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

    def jacobian(x):
        # Central differences, every perturbed camera projected in one population call
        # (the block of each camera; the two cameras share no parameter).
        J = np.zeros((4 * len(points_world), 22))
        for c in range(2):
            z = x[11 * c:11 * c + 11]
            step = np.finfo(float).eps ** (1 / 3) * np.maximum(1.0, np.abs(z))
            population = np.array([_from_identifiable(z + sign * step[j] * np.eye(11)[j],
                                                      focal[c])
                                   for j in range(11) for sign in (1.0, -1.0)])
            population[:, 5] = np.maximum(population[:, 5], 0.0)  # kappa at its bound
            uv = project_seed(population, points_world).reshape(11, 2, -1)
            rows = slice(2 * len(points_world) * c, 2 * len(points_world) * (c + 1))
            J[rows, 11 * c:11 * c + 11] = ((uv[:, 0] - uv[:, 1]) / (2 * step[:, None])).T
        return J

    x0 = np.concatenate([_to_identifiable(p) for p in start])
    lower = np.full(22, -np.inf)
    lower[[4, 15]] = 0.0  # kappa >= 0
    result = least_squares(residuals, x0, bounds=(lower, np.inf), method='trf',
                           x_scale='jac', jac=jacobian, ftol=1e-15, xtol=1e-15,
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
    P = np.linalg.inv(T2) @ np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 4) @ T3
    return decompose_projection(P)


def decompose_projection(P):
    """3x4 projection P ~ K [R | t] (any scale and sign) -> K (3, 3) upper triangular with
    a positive diagonal and K[2, 2] = 1, R (3, 3) with det +1, t (3,), by RQ."""
    P = np.asarray(P, dtype=float)
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


class NetworkInfo(NamedTuple):
    rms_before: float  # reprojection RMS [px] of the start camera (full seed model)
    rms_after: float  # and of the refined camera
    loss: np.ndarray  # (epochs,) mean network error 1/2 |d - O|^2 in normalised units


def undistort_seed_pixels(params, pixels):
    """Remove the seed's division distortion from (N, 2) pixels of camera ``params`` (12,):
    X_u = X_d (1 + k |X_d|^2) with X_d = ((u - u0) / Nx, (v - v0) / Ny) (4.2.3, explicit
    in this direction)."""
    u0, v0, Nx, Ny, k = params[0], params[1], params[2], params[3], params[5]
    xy_d = (np.asarray(pixels, dtype=float) - [u0, v0]) / [Nx, Ny]
    xy_u = xy_d * (1 + k * np.sum(xy_d ** 2, axis=1, keepdims=True))
    return xy_u * [Nx, Ny] + [u0, v0]


def network_refine(params, points_world, pixels, epochs=3000, rate_D=0.05, rate_B=0.05,
                   rate_gamma=0.5):
    """The seed's neural refinement of one camera (ALGORITHMS.md §3.5, 4.5.1-4.5.7).

    A linear network: hidden h_i = B W_i (B 4x4, the extrinsics [R T; 0 1]), output
    O_i = gamma_i D h_i (D 3x4, the intrinsics [A | 0]), target d_i = (u_i, v_i, 1) with the
    GA's distortion removed first (the network cannot model k; f and k keep their start
    values). Full-batch gradient descent on E = 1/2 sum |d_i - O_i|^2 with the thesis's
    updates (dD = eta_D gamma e h^T, dB = eta_B gamma D^T e W^T, dgamma = eta_g e^T D h),
    averaged over the points, on Hartley-normalised inputs and targets [C].

    Choices where the thesis is silent [C]: D is scaled so that the mean start depth is 1,
    which makes gamma_i = 1 (the thesis's start) a consistent start; the rates and epochs
    are the arguments; the read-out decomposes the trained projection D B by RQ (the
    product is all the data fix) into K, R, T, and takes fx, fy, u0, v0 from K (skew
    dropped), Nx = fx / f, Ny = fy / f.

    Args:
        params: (12,) start camera in ``PARAM_NAMES`` order (the GA result).
        points_world: (N, 3) [unit]; pixels: (N, 2) [px].

    Returns:
        (refined params (12,), :class:`NetworkInfo`).
    """
    from scipy.spatial.transform import Rotation

    params = np.asarray(params, dtype=float)
    if params.shape != (12,) or params[4] <= 0:
        raise ValueError('params: expected shape (12,) with f > 0')
    points_world, (pixels,) = _check_points(points_world, pixels)
    start = identifiable(params)
    targets = undistort_seed_pixels(params, pixels)
    T3, T2 = _normalise(points_world), _normalise(targets)
    W = np.column_stack([points_world, np.ones(len(points_world))]) @ T3.T  # (N, 4)
    d = np.column_stack([targets, np.ones(len(targets))]) @ T2.T  # (N, 3)
    B = np.eye(4)
    B[:3, :3], B[:3, 3] = start.R, start.T
    D = np.array([[start.fx, 0, start.u0, 0], [0, start.fy, start.v0, 0], [0, 0, 1, 0]])
    B = B @ np.linalg.inv(T3)
    D = T2 @ D
    # Gauge [C]: D B is all the data fix, so balance the two factors (hidden units of
    # order 1, mean output depth 1) for a well-conditioned descent.
    depth = np.mean((W @ B.T)[:, 2])
    B[:3] /= depth
    D[:, :3] *= depth
    D /= np.mean((W @ B.T @ D.T)[:, 2])
    gamma = np.ones(len(W))
    count = len(W)
    loss = np.empty(epochs)
    rate = 1.0  # backtracking factor on the three rates [C]: halve when a step raises E

    def error(D, B, gamma):
        h = W @ B.T
        Dh = h @ D.T
        e = d - gamma[:, None] * Dh
        return 0.5 * np.mean(np.sum(e ** 2, axis=1)), h, Dh, e

    current, h, Dh, e = error(D, B, gamma)
    for epoch in range(epochs):
        ge = gamma[:, None] * e
        steps = (rate * rate_D * ge.T @ h / count, rate * rate_B * D.T @ ge.T @ W / count,
                 rate * rate_gamma * np.sum(e * Dh, axis=1))
        trial = error(D + steps[0], B + steps[1], gamma + steps[2])
        if trial[0] <= current:
            D, B, gamma = D + steps[0], B + steps[1], gamma + steps[2]
            current, h, Dh, e = trial
            rate = min(1.0, 1.5 * rate)
        else:
            rate *= 0.5
        loss[epoch] = current
    P = np.linalg.inv(T2) @ D @ B @ T3
    K, R, t = decompose_projection(P)
    refined = params.copy()
    refined[0:2] = K[0, 2], K[1, 2]
    refined[2:4] = K[0, 0] / params[4], K[1, 1] / params[4]
    refined[6:9] = Rotation.from_matrix(R).as_euler('ZYX')  # alpha, beta, gamma
    refined[9:12] = t
    rms = [float(np.sqrt(np.mean(np.sum((project_seed(p[None], points_world)[0] - pixels)
                                        ** 2, axis=1)))) for p in (params, refined)]
    return refined, NetworkInfo(rms[0], rms[1], loss)


