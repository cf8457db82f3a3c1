"""Fusion of dense SFS depth with sparse stereo depth (ALGORITHMS.md §4.4, A5.8) and the
chapter's error metrics (§4.5).

Depth maps are (H, W) float arrays; sparse stereo depth is NaN where absent.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, cast

import cv2
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

BoolArray = npt.NDArray[np.bool_]


class RowFusion(NamedTuple):
    depth: FloatArray  # (H, W) fused depth, in the stereo depth's unit
    trained_rows: BoolArray  # (H,) rows with at least one stereo point
    loss_initial: FloatArray  # (H,) scaled mean squared error before training, NaN if untrained
    loss_final: FloatArray  # (H,) the same after training


class DepthErrors(NamedTuple):
    mean: float  # mean |Z' - G| (Table 5.1)
    std: float  # std of |Z' - G| (Table 5.2)
    rms: float  # sqrt(mean (Z' - G)^2)


def _check_pair(
    Z_sfs: npt.ArrayLike, Z_stereo: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, BoolArray]:
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


def _sigmoid(a: FloatArray) -> FloatArray:
    return 1.0 / (1.0 + np.exp(-a))


def _forward(
    params: Sequence[FloatArray], x: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Batched 1-6-3-1 network: x (R, N) -> output (R, N) and the hidden activations."""
    W1, b1, W2, b2, W3, b3 = params  # (R,6), (R,6), (R,3,6), (R,3), (R,3), (R,)
    h1 = _sigmoid(x[..., None] * W1[:, None, :] + b1[:, None, :])  # (R, N, 6)
    h2 = _sigmoid(np.einsum('rnj,rkj->rnk', h1, W2) + b2[:, None, :])  # (R, N, 3)
    return np.einsum('rnk,rk->rn', h2, W3) + b3[:, None], h1, h2


def train_row_networks(
    x: FloatArray,
    t: FloatArray,
    mask: BoolArray,
    rng: np.random.Generator,
    hidden: tuple[int, int] = (6, 3),
    learning_rate: float = 0.5,
    epochs: int = 2000,
) -> tuple[list[FloatArray], FloatArray, FloatArray]:
    """Train one network per row at once by full-batch back-propagation (§4.4).

    ``x``, ``t`` (R, N) scaled inputs and targets, ``mask`` (R, N) bool training points
    (each row's loss is the mean squared error over its own points). Weights start from
    N(0, 1/fan_in) drawn from ``rng``. Returns (params, loss_initial (R,), loss_final (R,)).
    """
    R = x.shape[0]
    n1, n2 = hidden
    params = [
        rng.normal(0, 1.0, (R, n1)),
        np.zeros((R, n1)),
        rng.normal(0, n1**-0.5, (R, n2, n1)),
        np.zeros((R, n2)),
        rng.normal(0, n2**-0.5, (R, n2)),
        np.zeros(R),
    ]
    weight = mask / np.maximum(mask.sum(axis=1, keepdims=True), 1)  # per-row mean
    losses: list[FloatArray] = []
    for _ in range(epochs + 1):
        y, h1, h2 = _forward(params, x)
        err = np.where(mask, y - t, 0.0)
        losses.append(np.sum(weight * err**2, axis=1))
        if len(losses) > epochs:
            break
        g_y = 2 * weight * err  # (R, N) dLoss/dy
        g_a2 = g_y[..., None] * params[4][:, None, :] * h2 * (1 - h2)  # (R, N, 3)
        g_a1 = np.einsum('rnk,rkj->rnj', g_a2, params[2]) * h1 * (1 - h1)  # (R, N, 6)
        grads = [
            np.einsum('rnj,rn->rj', g_a1, x),
            g_a1.sum(axis=1),
            np.einsum('rnk,rnj->rkj', g_a2, h1),
            g_a2.sum(axis=1),
            np.einsum('rn,rnk->rk', g_y, h2),
            g_y.sum(axis=1),
        ]
        params = [w - learning_rate * g for w, g in zip(params, grads)]
    return params, losses[0], losses[-1]


def fuse_mlp_rows(
    Z_sfs: npt.ArrayLike,
    Z_stereo: npt.ArrayLike,
    rng: np.random.Generator,
    hidden: tuple[int, int] = (6, 3),
    learning_rate: float = 0.5,
    epochs: int = 2000,
) -> RowFusion:
    """The seed's ``mlp_rows`` fusion: per image row, a network maps Z_sfs to Z_stereo.

    Each row is min-max scaled to [0, 1] (inputs over the whole row of ``Z_sfs``, targets
    over its stereo points), trained on its stereo points and applied to the whole row.
    Rows without stereo points borrow the nearest trained row's network with that row's
    scaling. ``rng`` a numpy Generator (deterministic for a seed). Returns ``RowFusion``.
    """
    Z_sfs, Z_stereo, mask = _check_pair(Z_sfs, Z_stereo)
    trained = cast(BoolArray, mask.any(axis=1))  # (H,); numpy's stubs also allow a scalar
    rows = np.flatnonzero(trained)
    x_lo, x_hi = Z_sfs.min(axis=1), Z_sfs.max(axis=1)
    masked_t = np.where(mask, Z_stereo, np.nan)[rows]
    t_lo, t_hi = np.nanmin(masked_t, axis=1), np.nanmax(masked_t, axis=1)
    x_lo, x_span = x_lo[rows, None], np.maximum(x_hi - x_lo, 1e-12)[rows, None]
    t_span = np.maximum(t_hi - t_lo, 1e-12)[:, None]
    t = np.where(mask[rows], (Z_stereo[rows] - t_lo[:, None]) / t_span, 0.0)
    params, loss0, loss1 = train_row_networks(
        (Z_sfs[rows] - x_lo) / x_span, t, mask[rows], rng, hidden, learning_rate, epochs
    )
    # nearest trained row (index into ``rows``) for every image row
    source = np.argmin(np.abs(np.arange(Z_sfs.shape[0])[:, None] - rows[None, :]), axis=1)
    y, _, _ = _forward([w[source] for w in params], (Z_sfs - x_lo[source]) / x_span[source])
    loss_initial, loss_final = np.full(len(trained), np.nan), np.full(len(trained), np.nan)
    loss_initial[rows], loss_final[rows] = loss0, loss1
    return RowFusion(y * t_span[source] + t_lo[source, None], trained, loss_initial, loss_final)


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
    Z_sfs, Z_stereo, mask = _check_pair(Z_sfs, Z_stereo)
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
    Z_sfs, Z_stereo, mask = _check_pair(Z_sfs, Z_stereo)
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
