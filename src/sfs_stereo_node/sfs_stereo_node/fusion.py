"""Fusion of dense SFS depth with sparse stereo depth (ALGORITHMS.md §4.4, A5.8) and the
chapter's error metrics (§4.5): ours (``fuse_local_affine``) and the global least-squares
alternative; the thesis's per-row networks (``mlp_rows``) are in ``thesis``.

Depth maps are (H, W) float arrays; sparse stereo depth is NaN where absent.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

BoolArray = npt.NDArray[np.bool_]


class DepthErrors(NamedTuple):
    """§4.5 errors of a depth estimate against ground truth G (:func:`depth_error_stats`,
    after the estimate's range is mapped onto G's), in G's unit."""

    mean: float  # mean |Z' - G| (Table 5.1)
    std: float  # std of |Z' - G| (Table 5.2)
    rms: float  # sqrt(mean (Z' - G)^2)


def check_pair(
    Z_sfs: npt.ArrayLike, Z_stereo: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Both maps as float (H, W) arrays and the (H, W) mask of finite stereo depth; raises
    ``InvalidInput`` if they are not two maps of one shape or no stereo depth is finite."""
    Z_sfs, Z_stereo = np.asarray(Z_sfs, dtype=float), np.asarray(Z_stereo, dtype=float)
    if Z_sfs.ndim != 2 or Z_sfs.shape != Z_stereo.shape:
        raise InvalidInput(
            f'Z_sfs {Z_sfs.shape} and Z_stereo {Z_stereo.shape}: expected '
            'two (H, W) maps of one shape',
            key='Z_sfs',
            value=Z_sfs.shape,
        )
    mask = np.isfinite(Z_stereo)
    if not mask.any():
        raise InvalidInput('Z_stereo has no finite point', key='Z_stereo')
    return Z_sfs, Z_stereo, mask


def _difference_operators(H: int, W: int) -> tuple[sp.spmatrix, sp.spmatrix]:
    """Sparse forward differences along x (columns) and y (rows) of a row-major (H, W)."""

    def diff(n: int) -> sp.spmatrix:
        return sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))

    return sp.kron(sp.eye(H), diff(W)), sp.kron(diff(H), sp.eye(W))


def fuse_least_squares(
    Z_sfs: npt.ArrayLike, Z_stereo: npt.ArrayLike, weight: float = 1.0
) -> FloatArray:
    """Dense depth Z minimising sum_stereo (Z - Z_s)^2 + weight ||grad Z - grad(a Z_sfs + b)||^2.

    (a, b) is the least-squares affine fit of Z_sfs to the stereo points, made first;
    gradients are forward differences. ``weight`` > 0 [dimensionless]. Solves the sparse
    normal equations. Returns (H, W) depth in the stereo depth's unit.
    """
    Z_sfs, Z_stereo, mask = check_pair(Z_sfs, Z_stereo)
    if not weight > 0:
        raise InvalidInput(f'weight must be > 0, got {weight}', key='weight', value=weight)
    a, b = np.polyfit(Z_sfs[mask], Z_stereo[mask], 1) if mask.sum() > 1 else (1.0, 0.0)
    guide = (a * Z_sfs + b).ravel()
    Dx, Dy = _difference_operators(*Z_sfs.shape)
    S = sp.diags(mask.ravel().astype(float))
    lhs = S + weight * (Dx.T @ Dx + Dy.T @ Dy)
    rhs = np.where(mask, Z_stereo, 0.0).ravel() + weight * (Dx.T @ Dx + Dy.T @ Dy) @ guide
    return spsolve(lhs.tocsc(), rhs).reshape(Z_sfs.shape)


def depth_error_stats(
    Z: npt.ArrayLike, G: npt.ArrayLike, mask: BoolArray | None = None
) -> DepthErrors:
    """§4.5 errors of an estimate ``Z`` against ground truth ``G``, both (H, W), over the
    bool ``mask`` (default: where both are finite). Z is first mapped linearly so that its
    range over the mask becomes G's. Returns ``DepthErrors``."""
    Z, G = np.asarray(Z, dtype=float), np.asarray(G, dtype=float)
    if mask is None:
        mask = np.isfinite(Z) & np.isfinite(G)
    z, g = Z[mask], G[mask]
    if z.size == 0 or np.ptp(z) == 0:
        raise InvalidInput('depth_error_stats: empty mask or constant estimate', key='mask')
    mapped = g.min() + (z - z.min()) * np.ptp(g) / np.ptp(z)
    err = mapped - g
    return DepthErrors(
        float(np.mean(np.abs(err))), float(np.std(np.abs(err))), float(np.sqrt(np.mean(err**2)))
    )


def _normalized_blur(
    values: np.ndarray, weights: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-weighted local mean of ``values`` where ``weights`` > 0 (normalised
    convolution); also returns the local weight (the blurred weights)."""
    ksize = int(2 * np.ceil(3 * sigma) + 1)

    def blur(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (ksize, ksize), sigma, borderType=cv2.BORDER_CONSTANT)

    w = blur(weights)
    with np.errstate(invalid='ignore', divide='ignore'):
        return blur(values * weights) / w, w


def fuse_local_affine(
    Z_sfs: npt.ArrayLike,
    Z_stereo: npt.ArrayLike,
    sigma: float = 12.0,
    prior: float = 0.5,
    residual_sigma: float = 4.0,
) -> FloatArray:
    """Our fusion: SFS shape mapped onto the stereo points by a spatially varying affine
    map, then the remaining residual interpolated (all by Gaussian normalised
    convolution, O(HW), no solver).

    1. Global least-squares line Z_stereo ~ a0 Z_sfs + b0 over all stereo points.
    2. Local line (a(x), b(x)): weighted least squares over the stereo points with
       Gaussian weights of ``sigma`` [px] around x, shrunk toward (a0, b0) with
       ``prior`` [points] of pseudo-weight, so sparse neighbourhoods fall back to the
       global map (the SFS scale drifts across the image: Tsai-Shah's height errors
       accumulate along the light direction).
    3. Z = a Z_sfs + b + r, r the residual at the stereo points interpolated with
       ``residual_sigma`` [px] and faded out away from stereo points.
    Returns (H, W) depth in the stereo depth's unit; NaN where Z_sfs is NaN.
    """
    Z_sfs, Z_stereo, mask = check_pair(Z_sfs, Z_stereo)
    valid_sfs = np.isfinite(Z_sfs)
    mask = mask & valid_sfs
    if mask.sum() < 2:
        raise InvalidInput('fewer than 2 stereo points on the SFS surface', key='Z_stereo')
    x, t = Z_sfs[mask], Z_stereo[mask]
    a0, b0 = np.polyfit(x, t, 1) if np.ptp(x) > 0 else (0.0, float(np.mean(t)))
    w = mask.astype(np.float32)
    xs = np.where(mask, Z_sfs, 0.0).astype(np.float32)
    ts = np.where(mask, Z_stereo, 0.0).astype(np.float32)
    ksize = int(2 * np.ceil(3 * sigma) + 1)

    def blur(a: np.ndarray) -> FloatArray:
        return cv2.GaussianBlur(a, (ksize, ksize), sigma, borderType=cv2.BORDER_CONSTANT).astype(
            float
        )

    # Gaussian-weighted sums, scaled so that one point at the centre weighs 1.
    scale = 2 * np.pi * sigma**2
    S, Sx, St = blur(w) * scale, blur(xs) * scale, blur(ts) * scale
    Sxx, Sxt = blur(xs * xs) * scale, blur(xs * ts) * scale
    # Centred moments plus the prior: prior points lying on the global line.
    mean_x = np.where(S > 0, Sx / np.maximum(S, 1e-12), 0.0)
    var_x = np.maximum(Sxx - Sx * mean_x, 0.0)
    cov_xt = Sxt - St * mean_x
    spread = np.var(x) if np.ptp(x) > 0 else 1.0
    a = (cov_xt + prior * spread * a0) / (var_x + prior * spread)
    b = np.where(S > 0, (St - a * Sx) / np.maximum(S, 1e-12), b0)
    b = (S * b + prior * (b0 + (a0 - a) * mean_x)) / (S + prior)
    guide = a * np.where(valid_sfs, Z_sfs, 0.0) + b
    residual = np.where(mask, Z_stereo - guide, 0.0)
    smooth, weight = _normalized_blur(residual.astype(np.float32), w, residual_sigma)
    fade = weight / (weight + 0.05 / (2 * np.pi * residual_sigma**2))
    fused = guide + np.nan_to_num(smooth) * fade
    return np.where(valid_sfs, fused, np.nan)


def fill_from_stereo(
    Z_stereo: npt.ArrayLike, surface: npt.ArrayLike, smooth_sigma: float = 1.0
) -> FloatArray:
    """Dense depth from stereo alone, for surfaces the shading model does not explain
    (texture, varying albedo): the matches denoised by a normalised convolution of
    ``smooth_sigma`` [px] over the matches only, and each hole filled from the matches
    around it by normalised convolutions of doubling width (pull-push), the narrowest
    that reaches it. O(H W log size), no solver. ``Z_stereo`` (H, W) [m], NaN where no
    match; ``surface`` (H, W) bool. Returns (H, W) [m], NaN off the surface (and
    everywhere when there is no match)."""
    Z_stereo = np.asarray(Z_stereo, dtype=np.float32)
    surface = np.asarray(surface, dtype=bool)
    known = np.isfinite(Z_stereo) & surface
    values = np.where(known, Z_stereo, 0.0).astype(np.float32)
    weights = known.astype(np.float32)
    smooth, _ = _normalized_blur(values, weights, smooth_sigma)
    fused = np.where(known, smooth, np.nan)
    sigma = 2.0 * smooth_sigma
    while np.isnan(fused[surface]).any() and known.any() and sigma < 2 * max(Z_stereo.shape):
        estimate, reach = _normalized_blur(values, weights, sigma)
        fused = np.where(np.isnan(fused) & (reach > 1e-3), estimate, fused)
        sigma *= 2.0
    return np.where(surface, fused, np.nan)
