"""Chapter 4 "better" (ALGORITHMS.md §8): Levenberg-Marquardt refinement of a stereo
calibration in the identifiable parameters (A4.1) of the full seed model (§3.2, A4.3),
its closed-form starts (DLT, division model) and an OpenCV reference (``calibrateCamera``,
``stereoCalibrate``). The thesis's network refinement is in ``thesis``.

Both cameras use the seed conventions: X = R x + T maps world to camera, pixels in
[px], lengths in the thesis's unit. The DLT is the standard 3x4 projection estimate with
Hartley normalisation and an RQ decomposition.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
from scipy.linalg import rq
from scipy.optimize import least_squares

from calib_node.seed_camera import Identifiable, PopulationCost, identifiable, project_seed
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

IDENTIFIABLE_NAMES = ('u0', 'v0', 'fx', 'fy', 'kappa', 'alpha', 'beta', 'gamma', 'Tx', 'Ty', 'Tz')


class RefineInfo(NamedTuple):
    """How :func:`refine_seed_lm` ended: each camera's RMS [px], the solver's iterations
    and status, the standard errors and the refined cameras' identifiable parameters."""

    rms_left: float  # sqrt(mean |reprojection error|^2) over the points [px]
    rms_right: float
    iterations: int  # Jacobian evaluations of the solver
    status: int  # scipy.optimize.least_squares status (> 0: converged)
    std: np.ndarray  # (2, 11) standard errors of IDENTIFIABLE_NAMES, s^2 (J^T J)^-1
    left: Identifiable
    right: Identifiable


class OpenCVReference(NamedTuple):
    """OpenCV's stereo calibration (:func:`opencv_reference`): each camera's intrinsics,
    distortion and world pose, the left-to-right transform and the RMS figures [px]."""

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


def _to_identifiable(params: FloatArray) -> FloatArray:
    """(12,) seed params -> (11,) z = (u0, v0, fx, fy, kappa, alpha, beta, gamma, T)."""
    f = params[4]
    return np.concatenate([params[0:2], params[2:4] * f, [params[5] * f**2], params[6:12]])


def _from_identifiable(z: FloatArray, f: float) -> FloatArray:
    """Inverse of :func:`_to_identifiable` with the focal length f held fixed."""
    return np.concatenate([z[0:2], z[2:4] / f, [f], [z[4] / f**2], z[5:11]])


def check_points(
    points_world: npt.ArrayLike, *pixels: npt.ArrayLike
) -> tuple[FloatArray, list[FloatArray]]:
    """(N, 3) control points and each (N, 2) pixel array as float arrays.

    Raises:
        ValueError: points_world is not (N, 3) or a pixel array is not (N, 2).
    """
    points_world = np.asarray(points_world, dtype=float)
    if points_world.ndim != 2 or points_world.shape[1] != 3:
        raise InvalidInput(
            f'points_world: expected shape (N, 3), got {points_world.shape}', key='points_world'
        )
    out = [np.asarray(p, dtype=float) for p in pixels]
    for p in out:
        if p.shape != (points_world.shape[0], 2):
            raise InvalidInput(
                f'pixels: expected shape ({points_world.shape[0]}, 2), got {p.shape}', key='pixels'
            )
    return points_world, out


def refine_seed_lm(
    params_left: npt.ArrayLike,
    params_right: npt.ArrayLike,
    points_world: npt.ArrayLike,
    pixels_left: npt.ArrayLike,
    pixels_right: npt.ArrayLike,
) -> tuple[FloatArray, FloatArray, RefineInfo]:
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
        raise InvalidInput('params_left, params_right: expected shape (12,)')
    if any(p[4] <= 0 or p[5] < 0 for p in start):
        raise InvalidInput('params: need f > 0 and k >= 0', key='params')
    points_world, observed = check_points(points_world, pixels_left, pixels_right)
    focal = [p[4] for p in start]

    def cameras(x: FloatArray) -> list[FloatArray]:
        return [_from_identifiable(x[11 * c : 11 * c + 11], focal[c]) for c in range(2)]

    def residuals(x: FloatArray) -> FloatArray:
        return np.concatenate(
            [
                (project_seed(p[None], points_world)[0] - obs).ravel()
                for p, obs in zip(cameras(x), observed)
            ]
        )

    def jacobian(x: FloatArray) -> FloatArray:
        # Central differences, every perturbed camera projected in one population call
        # (the block of each camera; the two cameras share no parameter).
        J = np.zeros((4 * len(points_world), 22))
        for c in range(2):
            z = x[11 * c : 11 * c + 11]
            step = np.finfo(float).eps ** (1 / 3) * np.maximum(1.0, np.abs(z))
            population = np.array(
                [
                    _from_identifiable(z + sign * step[j] * np.eye(11)[j], focal[c])
                    for j in range(11)
                    for sign in (1.0, -1.0)
                ]
            )
            population[:, 5] = np.maximum(population[:, 5], 0.0)  # kappa at its bound
            uv = project_seed(population, points_world).reshape(11, 2, -1)
            rows = slice(2 * len(points_world) * c, 2 * len(points_world) * (c + 1))
            J[rows, 11 * c : 11 * c + 11] = ((uv[:, 0] - uv[:, 1]) / (2 * step[:, None])).T
        return J

    x0 = np.concatenate([_to_identifiable(p) for p in start])
    lower = np.full(22, -np.inf)
    lower[[4, 15]] = 0.0  # kappa >= 0
    result = least_squares(
        residuals,
        x0,
        bounds=(lower, np.inf),
        method='trf',
        x_scale='jac',
        jac=jacobian,
        ftol=1e-15,
        xtol=1e-15,
        gtol=1e-15,
        max_nfev=200,
    )
    left, right = cameras(result.x)
    dof = max(result.fun.size - result.x.size, 1)
    covariance = np.sum(result.fun**2) / dof * np.linalg.pinv(result.jac.T @ result.jac)
    rms = np.sqrt(np.mean(result.fun.reshape(2, -1, 2) ** 2, axis=(1, 2)) * 2)
    info = RefineInfo(
        rms_left=float(rms[0]),
        rms_right=float(rms[1]),
        iterations=int(result.njev),
        status=int(result.status),
        std=np.sqrt(np.diag(covariance)).reshape(2, 11),
        left=identifiable(left),
        right=identifiable(right),
    )
    return left, right, info


def hartley_normalise(points: FloatArray) -> FloatArray:
    """Similarity T (d+1, d+1) moving (N, d) points to centroid 0, mean distance sqrt(d)."""
    d = points.shape[1]
    centre = points.mean(axis=0)
    scale = np.sqrt(d) / np.mean(np.linalg.norm(points - centre, axis=1))
    T = np.diag(np.append(np.full(d, scale), 1.0))
    T[:d, d] = -scale * centre
    return T


def dlt_camera(
    points_world: npt.ArrayLike, pixels: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Pinhole camera (K, R, t) with pixels ~ K (R x + t), from >= 6 non-coplanar points.

    Normalised DLT of the 3x4 P (SVD null vector), then P[:, :3] = K R by RQ, with the
    diagonal of K made positive, det R = +1 and K[2, 2] = 1. Distortion is ignored.

    Args:
        points_world: (N, 3) [unit]; pixels: (N, 2) [px].

    Returns:
        K (3, 3) upper triangular [px], R (3, 3) world -> camera, t (3,) [unit].
    """
    points_world, (pixels,) = check_points(points_world, pixels)
    if points_world.shape[0] < 6:
        raise InvalidInput('dlt_camera: needs at least 6 points')
    T3, T2 = hartley_normalise(points_world), hartley_normalise(pixels)
    X = np.column_stack([points_world, np.ones(len(points_world))]) @ T3.T
    x = np.column_stack([pixels, np.ones(len(pixels))]) @ T2.T
    zero = np.zeros_like(X)
    A = np.concatenate([np.hstack([X, zero, -x[:, :1] * X]), np.hstack([zero, X, -x[:, 1:2] * X])])
    P = np.linalg.inv(T2) @ np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 4) @ T3
    return decompose_projection(P)


def decompose_projection(P: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
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


def opencv_reference(
    points_world: npt.ArrayLike,
    pixels_left: npt.ArrayLike,
    pixels_right: npt.ArrayLike,
    image_size_left: tuple[int, int],
    image_size_right: tuple[int, int],
) -> OpenCVReference:
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
    points_world, pixels = check_points(points_world, pixels_left, pixels_right)
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
            objects,
            images[-1],
            tuple(int(s) for s in size),
            K0,
            np.zeros(5),
            flags=flags,
            criteria=criteria,
        )
        fits.append((rms, K, dist.ravel(), cv2.Rodrigues(rvecs[0])[0], tvecs[0].ravel()))
    (rms_l, K_l, d_l, R_l, t_l), (rms_r, K_r, d_r, R_r, t_r) = fits
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        objects,
        images[0],
        images[1],
        K_l,
        d_l,
        K_r,
        d_r,
        tuple(int(s) for s in image_size_left),
        flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=criteria,
    )
    return OpenCVReference(
        K_l,
        K_r,
        d_l,
        d_r,
        R_l,
        t_l,
        R_r,
        t_r,
        R,
        T.ravel(),
        float(rms_l),
        float(rms_r),
        float(rms),
    )


def _null_vector(rows: FloatArray) -> FloatArray:
    """Unit vector minimising |rows @ x| (last right singular vector)."""
    return np.linalg.svd(rows, full_matrices=False)[2][-1]


def _orthonormal_rows(rows: FloatArray) -> FloatArray:
    """Nearest (in Frobenius norm) matrix with orthonormal rows to (2, 3) ``rows``."""
    U, _, Vt = np.linalg.svd(rows, full_matrices=False)
    return U @ Vt


def radial_division_init(points_world: npt.ArrayLike, pixels: npt.ArrayLike) -> FloatArray:
    """Closed-form seed camera (12,) with f = 1 for the division model (§3.2), no start.

    Radial distortion about the principal point c keeps each image point on the line
    through c and its undistorted image (Tsai's radial alignment constraint), whatever the
    distortion coefficient; with Nx != Ny this holds in pixels too, because the distortion
    scales the pixel offset m = (u - u0, v - v0) by one scalar. Three linear steps, exact
    on noise-free data [O: Tsai 1987; Thirthala & Pollefeys' radial 1D camera]:

    1. The line through c and the undistorted projection is l = M X~ with M (3x4) of rank
       2 and c its left null vector, so every point gives m~^T M X~ = 0, linear in the 12
       entries of M (Hartley-normalised, SVD null vector); c = left null vector of M.
    2. With c fixed, the 8 entries of A ~ fx [r1 t1], B ~ fy [r2 t2] from
       m_x (B X~) - m_y (A X~) = 0 (SVD null vector): r1, r2 (orthonormalised), t1, t2 and
       the aspect fy / fx = |B[:3]| / |A[:3]|.
    3. r3 = r1 x r2; the model m (1 + lambda rho)(r3 x + t3) = (fx, fy) (r1 x + t1, r2 x + t2)
       with rho = m_x^2 + (m_y fx / fy)^2 and lambda = kappa / fx^2 is linear in
       (t3, lambda, lambda t3, fx): least squares over both image axes. The overall sign
       of A, B is chosen so that fx > 0.

    Needs non-coplanar points and some distortion or perspective (without distortion
    step 1's null space is 3-dimensional: then use :func:`dlt_camera`).

    Args:
        points_world: (N, 3) [unit], N >= 12; pixels: (N, 2) [px].

    Returns:
        (12,) seed parameters (u0, v0, Nx = fx, Ny = fy, f = 1, k = kappa >= 0, alpha,
        beta, gamma, Tx, Ty, Tz), the start for :func:`refine_seed_lm`.
    """
    from scipy.spatial.transform import Rotation

    points_world, (pixels,) = check_points(points_world, pixels)
    if points_world.shape[0] < 12:
        raise InvalidInput(
            'radial_division_init: needs at least 12 points', key='radial_division_init'
        )
    T3, T2 = hartley_normalise(points_world), hartley_normalise(pixels)
    X = np.column_stack([points_world, np.ones(len(points_world))]) @ T3.T  # (N, 4)
    m = np.column_stack([pixels, np.ones(len(pixels))]) @ T2.T  # (N, 3)
    # Step 1: m~^T M X~ = 0 in normalised coordinates; back: M = T2^T M_n T3.
    M = T2.T @ _null_vector((m[:, :, None] * X[:, None, :]).reshape(len(X), 12)).reshape(3, 4) @ T3
    c = np.linalg.svd(M.T)[2][-1]
    u0, v0 = c[:2] / c[2]
    # Step 2: (u - u0) B X~ - (v - v0) A X~ = 0, world normalised (X~_n = T3 X~).
    offsets = pixels - [u0, v0]
    scale = 1.0 / np.mean(np.linalg.norm(offsets, axis=1))
    mx, my = offsets[:, 0] * scale, offsets[:, 1] * scale
    AB = _null_vector(np.hstack([-my[:, None] * X, mx[:, None] * X])).reshape(2, 4) @ T3
    norms = np.linalg.norm(AB[:, :3], axis=1)
    aspect = norms[1] / norms[0]
    translation_xy = AB[:, 3] / norms
    rows = _orthonormal_rows(AB[:, :3] / norms[:, None])
    # Step 3: linear in theta = (t3, lambda, lambda t3, fx), pixel offsets in px.
    mx, my = offsets[:, 0], offsets[:, 1]
    rho = mx**2 + (my / aspect) ** 2
    for sign in (1.0, -1.0):
        r12 = sign * rows
        t12 = sign * translation_xy
        R = np.vstack([r12, np.cross(r12[0], r12[1])])
        cam = points_world @ R.T  # without t3
        x1, y1 = cam[:, 0] + t12[0], cam[:, 1] + t12[1]
        z = cam[:, 2]
        system = np.concatenate(
            [
                np.column_stack([mx, rho * mx * z, rho * mx, -x1]),
                np.column_stack([my, rho * my * z, rho * my, -aspect * y1]),
            ]
        )
        rhs = -np.concatenate([mx * z, my * z])
        column_scale = 1.0 / np.maximum(np.linalg.norm(system, axis=0), 1e-300)
        theta = np.linalg.lstsq(system * column_scale, rhs, rcond=None)[0] * column_scale
        t3, lam, _, fx = theta
        if fx > 0:
            break
    kappa = max(float(lam) * fx**2, 0.0)
    angles = Rotation.from_matrix(R).as_euler('ZYX')  # R = Rz(alpha) Ry(beta) Rx(gamma)
    return np.r_[u0, v0, fx, aspect * fx, 1.0, kappa, angles, t12, t3]


def _rac_pose(
    points_world: FloatArray, pixels: FloatArray, centre: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """Tsai's radial alignment constraint with the centre known: (r1, r2) orthonormal rows
    (2, 3), (t1, t2) and the aspect fy / fx from m_x (B X~) - m_y (A X~) = 0 with
    A ~ fx [r1 t1], B ~ fy [r2 t2] (8 unknowns, SVD null vector; exact without noise
    whatever the radial distortion)."""
    T3 = hartley_normalise(points_world)
    X = np.column_stack([points_world, np.ones(len(points_world))]) @ T3.T
    offsets = pixels - centre
    offsets = offsets / np.mean(np.linalg.norm(offsets, axis=1))
    AB = _null_vector(np.hstack([-offsets[:, 1:2] * X, offsets[:, 0:1] * X])).reshape(2, 4)
    AB = AB @ T3
    norms = np.linalg.norm(AB[:, :3], axis=1)
    return _orthonormal_rows(AB[:, :3] / norms[:, None]), AB[:, 3] / norms, norms[1] / norms[0]


def division_init(
    points_world: npt.ArrayLike,
    pixels: npt.ArrayLike,
    grid: int = 9,
    depths: int = 48,
    keep: int = 3,
) -> list[FloatArray]:
    """Closed-form start candidates (seed params (12,) with f = 1) for the division model
    (§3.2), best first by their full-model reprojection RMS.

    The centre (u0, v0) is searched on a ``grid`` x ``grid`` lattice over the pixels'
    bounding box enlarged by its own size on each side (plus the centre of
    :func:`radial_division_init`). For each centre: the radial alignment constraint gives
    r1, r2, t1, t2 and the aspect linearly (:func:`_rac_pose`); r3 = r1 x r2 (both signs of
    (r1, r2) tried); then for each of ``depths`` values of t3 (log-spaced over 0.1 .. 1000
    times the points' extent) the model m (1 + lambda rho) = (fx x1, fy y1) / (r3 x + t3)
    is linear in (fx, lambda), lambda = kappa / fx^2, rho = m_x^2 + (m_y fx / fy)^2.
    Every (centre, sign, t3) candidate is scored by its full-model RMS; the best ``keep``
    with distinct centres are returned. In the thesis's nearly affine view (a 70-unit cube
    at 1210 units) fx and t3 are weakly separated, so several starts go to LM.
    """
    from scipy.spatial.transform import Rotation

    points_world, (pixels,) = check_points(points_world, pixels)
    low, high = pixels.min(axis=0), pixels.max(axis=0)
    size = np.maximum(high - low, 1.0)
    us = np.linspace(low[0] - size[0], high[0] + size[0], grid)
    vs = np.linspace(low[1] - size[1], high[1] + size[1], grid)
    centres = [np.array([u, v]) for u in us for v in vs]
    try:
        centres.append(radial_division_init(points_world, pixels)[:2])
    except (ValueError, np.linalg.LinAlgError):
        pass
    extent = np.max(np.linalg.norm(points_world - points_world.mean(axis=0), axis=1))
    score = PopulationCost(points_world, pixels)
    candidates = []
    for centre in centres:
        offsets = pixels - centre
        rows, t12, aspect = _rac_pose(points_world, pixels, centre)
        rho = offsets[:, 0] ** 2 + (offsets[:, 1] / aspect) ** 2
        for sign in (1.0, -1.0):
            R = np.vstack([sign * rows, np.cross(rows[0], rows[1])])
            cam = points_world @ R.T
            t3 = -cam[:, 2].min() + extent * np.geomspace(0.1, 1000, depths)  # Z > 0
            depth = cam[None, :, 2] + t3[:, None]  # (depths, N)
            # per t3: m = fx a - lambda b, a = (x1, aspect y1) / Z, b = rho m
            a = np.concatenate(
                [
                    (cam[:, 0] + sign * t12[0]) / depth,
                    aspect * (cam[:, 1] + sign * t12[1]) / depth,
                ],
                axis=1,
            )
            m = offsets.T.ravel()
            b = np.concatenate([rho, rho]) * m
            saa, sab, sbb = np.sum(a * a, axis=1), a @ b, b @ b
            sam, sbm = a @ m, b @ m
            det = saa * sbb - sab**2
            with np.errstate(all='ignore'):
                fx = (sbb * sam - sab * sbm) / det
                lam = -(saa * sbm - sab * sam) / det
            good = np.isfinite(fx) & (fx > 0)
            if not np.any(good):
                continue
            angles = Rotation.from_matrix(R).as_euler('ZYX')
            population = np.column_stack(
                [
                    np.full(good.sum(), centre[0]),
                    np.full(good.sum(), centre[1]),
                    fx[good],
                    aspect * fx[good],
                    np.ones(good.sum()),
                    np.maximum(lam[good], 0.0) * fx[good] ** 2,
                    np.tile(angles, (good.sum(), 1)),
                    np.tile(sign * t12, (good.sum(), 1)),
                    t3[good],
                ]
            )
            error = np.sqrt(score(population) / len(pixels))
            best = (
                int(np.nanargmin(np.where(np.isfinite(error), error, np.nan)))
                if np.any(np.isfinite(error))
                else None
            )
            if best is not None:
                candidates.append((float(error[best]), population[best]))
    if not candidates:
        raise InvalidInput('division_init: no candidate centre gave a camera')
    candidates.sort(key=lambda c: c[0])
    return [params for _, params in candidates[:keep]]


def calibrate_seed_stereo(
    points_world: npt.ArrayLike, pixels_left: npt.ArrayLike, pixels_right: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, RefineInfo]:
    """Ours on the thesis's setting: :func:`division_init` per camera, then
    :func:`refine_seed_lm` over both cameras (full implicit division model).

    Returns:
        (left (12,), right (12,), :class:`RefineInfo`) as :func:`refine_seed_lm`.
    """
    start_left, start_right = [
        division_init(points_world, uv)[0] for uv in (pixels_left, pixels_right)
    ]
    return refine_seed_lm(start_left, start_right, points_world, pixels_left, pixels_right)
