"""The thesis's chapter 4 camera model (ALGORITHMS.md §3.2), vectorised over a population
of parameter vectors, with the ground truth and bounds of Tables 4.1 / 4.2 and the
synthetic control points of §3.6.

A camera is 12 parameters in the thesis's order (4.3.1):
``(u0, v0, Nx, Ny, f, k, alpha, beta, gamma, Tx, Ty, Tz)``: principal point [px], pixels
per unit length [px/unit], focal length [unit], division distortion k [1/unit^2],
yaw, pitch, roll [rad] with R = Rz(alpha) Ry(beta) Rx(gamma) [C], and the translation T
[unit], where R, T map world to camera: X = R x + T. Units are the thesis's (1 unit = 1 mm
in the ch4_calibration scenario). Images are non-inverted: Xu = f X / Z.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray, rpy_to_matrix

PARAM_NAMES = ('u0', 'v0', 'Nx', 'Ny', 'f', 'k', 'alpha', 'beta', 'gamma', 'Tx', 'Ty', 'Tz')
DISTORTIONS = ('implicit', 'explicit')

# Tables 4.1 / 4.2 [T]. Right gamma = k = 0.15152 looks like a copy error; used as
# printed (A4.8).
LEFT_TRUTH = np.array([20.0, 19.0, 200.0, 200.0, 10.0, 0.15152, 0.0, 0.0, 0.0, 60.0, 35.0, 1210.0])
RIGHT_TRUTH = np.array(
    [256.0, 192.0, 144.0, 144.0, 25.0, 0.15152, -1.90, 0.20916, 0.15152, -38.0, 35.0, 1210.0]
)
# (12, 2) rows of [lower, upper], same order as the parameters.
LEFT_BOUNDS = np.array(
    [
        [0, 50],
        [0, 50],
        [0, 300],
        [0, 300],
        [0, 50],
        [0, 1],
        [-np.pi, np.pi],
        [-np.pi, np.pi],
        [-np.pi, np.pi],
        [0, 100],
        [0, 100],
        [0, 1600],
    ],
    dtype=float,
)
RIGHT_BOUNDS = np.array(
    [
        [0, 300],
        [0, 300],
        [0, 300],
        [0, 300],
        [0, 50],
        [0, 1],
        [-np.pi, np.pi],
        [-np.pi, np.pi],
        [-np.pi, np.pi],
        [-100, 100],
        [0, 100],
        [0, 1600],
    ],
    dtype=float,
)
for _array in (LEFT_TRUTH, RIGHT_TRUTH, LEFT_BOUNDS, RIGHT_BOUNDS):
    _array.setflags(write=False)


class Identifiable(NamedTuple):
    """What the images determine (A4.1); leading shape of the input parameters."""

    fx: np.ndarray  # f Nx [px]
    fy: np.ndarray  # f Ny [px]
    kappa: np.ndarray  # k f^2, normalised division coefficient
    u0: np.ndarray  # [px]
    v0: np.ndarray  # [px]
    R: np.ndarray  # (..., 3, 3) world -> camera
    T: np.ndarray  # (..., 3) [unit]


def seed_control_points(spacing: float = 10.0) -> FloatArray:
    """The §3.6 control points: x_w, y_w, z_w each in {0, s, ..., 7 s}, (512, 3) [unit].

    Ordered z slowest, then y, then x (x fastest), one 8 x 8 chart per depth. The grid
    origin at the world origin matches the ch4_calibration scenario (chart columns 1..8)
    and puts the left ground-truth pixels in about u in [104, 208], v in [67, 174].
    """
    steps = spacing * np.arange(8.0)
    z, y, x = np.meshgrid(steps, steps, steps, indexing='ij')
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def seed_stereo_observations() -> tuple[FloatArray, FloatArray]:
    """The thesis's calibration experiment: the 512 control points (N, 3) [unit] and their
    noise-free pixels in the Table 4.1 left and right cameras, (2, N, 2)."""
    points = seed_control_points()
    return points, project_seed(np.stack([LEFT_TRUTH, RIGHT_TRUTH]), points)


def distorted_radius(r_u: npt.ArrayLike, k: npt.ArrayLike) -> FloatArray:
    """Root r >= 0 of k r^3 + r - r_u = 0 for k >= 0 (unique), elementwise by broadcasting.

    Closed form r = 2/s sinh(asinh(1.5 s r_u)/3) with s = sqrt(3k), r = r_u where k = 0,
    then one Newton step to remove rounding.
    """
    r_u, k = np.broadcast_arrays(np.asarray(r_u, dtype=float), np.asarray(k, dtype=float))
    positive = k > 0
    s = np.sqrt(3 * np.where(positive, k, 1.0))
    r = np.where(positive, 2 / s * np.sinh(np.arcsinh(1.5 * s * r_u) / 3), r_u)
    return r - (k * r**3 + r - r_u) / (3 * k * r**2 + 1)


def camera_points(params: FloatArray, points_world: FloatArray) -> FloatArray:
    """World points (N, 3) into each camera of a population (P, 12) -> (P, N, 3)."""
    # R = Rz(alpha) Ry(beta) Rx(gamma): roll gamma, pitch beta, yaw alpha.
    R = rpy_to_matrix(params[:, 8], params[:, 7], params[:, 6])
    # Batched matmul (BLAS), several times faster than the equivalent einsum.
    X = np.matmul(points_world, R.transpose(0, 2, 1))
    X += params[:, None, 9:12]
    return X


def _check(
    params: npt.ArrayLike, points_world: npt.ArrayLike, distortion: str
) -> tuple[FloatArray, FloatArray]:
    params = np.asarray(params, dtype=float)
    points_world = np.asarray(points_world, dtype=float)
    if params.ndim != 2 or params.shape[1] != 12:
        raise InvalidInput(f'params: expected shape (P, 12), got {params.shape}', key='params')
    if points_world.ndim != 2 or points_world.shape[1] != 3:
        raise InvalidInput(
            f'points_world: expected shape (N, 3), got {points_world.shape}', key='points_world'
        )
    if distortion not in DISTORTIONS:
        raise InvalidInput(
            f'distortion: expected one of {DISTORTIONS}, got {distortion!r}', key='distortion'
        )
    if np.any(params[:, 5] < 0):
        raise InvalidInput('params: the division model needs k >= 0 (column 5)', key='params')
    return params, points_world


def project_with_depth(
    params: npt.ArrayLike, points_world: npt.ArrayLike, distortion: str = 'implicit'
) -> tuple[FloatArray, FloatArray]:
    """Like :func:`project_seed`, also returning the camera depths Z (P, N) [unit]."""
    params, points_world = _check(params, points_world, distortion)
    X = camera_points(params, points_world)
    Z = X[..., 2].copy()
    f, k = params[:, 4:5], params[:, 5:6]
    with np.errstate(divide='ignore', invalid='ignore'):
        scale = f / Z  # (P, N)
        x_u, y_u = X[..., 0] * scale, X[..., 1] * scale
        r_u = np.hypot(x_u, y_u)
        r = distorted_radius(r_u, k) if distortion == 'implicit' else r_u
        shrink = 1 / (1 + k * r * r)
    uv = np.empty(X.shape[:2] + (2,))
    uv[..., 0] = x_u * shrink * params[:, 2:3] + params[:, 0:1]
    uv[..., 1] = y_u * shrink * params[:, 3:4] + params[:, 1:2]
    return uv, Z


def project_seed(
    params: npt.ArrayLike, points_world: npt.ArrayLike, distortion: str = 'implicit'
) -> FloatArray:
    """Pixels of N world points in each of P cameras (§3.2, 4.2.1-4.2.4).

    Args:
        params: (P, 12) cameras, ``PARAM_NAMES`` order, k >= 0.
        points_world: (N, 3) points [unit].
        distortion: ``'implicit'`` (r is the distorted radius, the thesis's model, A4.2)
            or ``'explicit'`` (r = r_u).

    Returns:
        (P, N, 2) pixels (u, v). Points with Z <= 0 are not masked (inf/nan at Z = 0).

    Raises:
        ValueError: on bad shapes, an unknown ``distortion`` or a negative k.
    """
    return project_with_depth(params, points_world, distortion)[0]


def identifiable(params: npt.ArrayLike) -> Identifiable:
    """The combinations the images fix (A4.1) of (12,) or (P, 12) params."""
    params = np.asarray(params, dtype=float)
    if params.shape[-1] != 12:
        raise InvalidInput(f'params: expected shape (..., 12), got {params.shape}', key='params')
    f = params[..., 4]
    return Identifiable(
        fx=f * params[..., 2],
        fy=f * params[..., 3],
        kappa=params[..., 5] * f**2,
        u0=params[..., 0].copy(),
        v0=params[..., 1].copy(),
        R=rpy_to_matrix(params[..., 8], params[..., 7], params[..., 6]),
        T=params[..., 9:12].copy(),
    )


class PopulationCost:
    """Fast (4.3.2) cost of one camera for a whole population: (P, 12) -> (P,) [px^2].

    The implicit model (§3.2) simplified for speed, same values as :func:`project_seed`
    (to rounding): k r^3 + r = r_u gives 1 / (1 + k r^2) = r / r_u, and r_u = f rho / Z
    with rho = |(X, Y)|, so u - u0 = Nx X r / rho (f and Z cancel), with the closed-form
    root r = (2 / s) sinh(asinh(1.5 s r_u) / 3), s = sqrt(3 k) (k = 0 is the limit s -> 0,
    taken by a tiny floor on s). Camera coordinates are (P, N) rows of one batched matmul;
    the per-camera factors are folded into (P, 1) columns, so each step is one pass over
    (P, N) float64 with in-place operations. Individuals that put a point at Z <= 0 cost
    +inf. ``distortion='explicit'`` (r = r_u) falls back to :func:`project_with_depth`.
    """

    def __init__(
        self, points_world: npt.ArrayLike, pixels: npt.ArrayLike, distortion: str = 'implicit'
    ) -> None:
        self.points_t = np.ascontiguousarray(np.asarray(points_world, dtype=float).T)  # 3 N
        pixels = np.asarray(pixels, dtype=float)
        if self.points_t.shape[0] != 3 or pixels.shape != (self.points_t.shape[1], 2):
            raise InvalidInput(
                f'points_world (N, 3) and pixels (N, 2) expected, got '
                f'{self.points_t.T.shape} and {pixels.shape}'
            )
        if distortion not in DISTORTIONS:
            raise InvalidInput(
                f'distortion: expected one of {DISTORTIONS}, got {distortion!r}', key='distortion'
            )
        self.points_world = self.points_t.T
        self.u_obs = np.ascontiguousarray(pixels[:, 0])
        self.v_obs = np.ascontiguousarray(pixels[:, 1])
        self.pixels = pixels
        self.distortion = distortion

    def __call__(self, params: npt.ArrayLike) -> FloatArray:
        """(P,) sums of squared reprojection errors [px^2] of (P, 12) params; +inf for an
        individual that puts a point at Z <= 0."""
        params = np.asarray(params, dtype=float)
        if self.distortion != 'implicit':
            uv, Z = project_with_depth(params, self.points_world, self.distortion)
            with np.errstate(invalid='ignore', over='ignore'):
                cost = np.sum((uv - self.pixels) ** 2, axis=(1, 2))
            return np.where(np.all(Z > 0, axis=1), cost, np.inf)
        R = rpy_to_matrix(params[:, 8], params[:, 7], params[:, 6])
        # One GEMM (3 P, 3) @ (3, N): several times faster than P batched 3x3 products.
        camera = (R.reshape(-1, 3) @ self.points_t).reshape(len(params), 3, -1)
        camera += params[:, 9:12, None]
        X, Y, Z = camera[:, 0], camera[:, 1], camera[:, 2]
        in_front = Z.min(axis=1) > 0
        s = np.sqrt(np.maximum(3 * params[:, 5:6], 1e-200))
        with np.errstate(all='ignore'):
            rho = X * X
            a = Y * Y
            rho += a
            np.sqrt(rho, out=rho)  # |(X, Y)|; np.hypot is 3x slower here
            np.divide(rho, Z, out=a)
            a *= 1.5 * s * params[:, 4:5]  # 1.5 s r_u
            np.arcsinh(a, out=a)
            a *= 1 / 3
            np.sinh(a, out=a)
            a /= rho  # r / rho without 2 / s
            a *= 2 / s
            X *= a
            X *= params[:, 2:3]
            X += params[:, 0:1]
            X -= self.u_obs
            Y *= a
            Y *= params[:, 3:4]
            Y += params[:, 1:2]
            Y -= self.v_obs
            cost = np.einsum('ij,ij->i', X, X) + np.einsum('ij,ij->i', Y, Y)
        return np.where(in_front & ~np.isnan(cost), cost, np.inf)
