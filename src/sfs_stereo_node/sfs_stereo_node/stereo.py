"""Sparse stereo branch of chapter 5 (ALGORITHMS.md §4.2, A5.5-A5.7).

Images are (H, W) float arrays of a rectified pair, x = column, y = row. The right image
is the reference (A5.5): right pixel x matches left pixel x + d, d >= 0 [px].
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

Float32Array = npt.NDArray[np.float32]  # the matcher's working images and cost layers


def _check_image(image: npt.ArrayLike, name: str) -> FloatArray:
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        raise InvalidInput(
            f'{name}: expected an (H, W) image, got shape {image.shape}',
            key=name,
            value=image.shape,
        )
    return image


def histogram_line_fit(
    I_ref: npt.ArrayLike, I_other: npt.ArrayLike, quantiles: int = 256
) -> tuple[float, float]:
    """Line alpha, beta with alpha * I_other + beta ~ I_ref in distribution (5.2.2, A5.7).

    Grey levels of equal cumulative-histogram value (``quantiles`` levels at (k + 1/2) / n)
    are paired and fitted by least squares. For the thesis's normalisation pass
    I_ref = I_left, I_other = I_right and apply the line to I_right. Returns floats.
    """
    levels = (np.arange(quantiles) + 0.5) / quantiles
    g_ref = np.quantile(_check_image(I_ref, 'I_ref'), levels)
    g_other = np.quantile(_check_image(I_other, 'I_other'), levels)
    alpha, beta = np.polyfit(g_other, g_ref, 1)
    return float(alpha), float(beta)


def _box_sum(image: FloatArray, window: int) -> np.ndarray:
    """Sums over the window x window patch centred on every pixel of a 2-D float64 image,
    zeros outside (cv2.boxFilter, unnormalised, constant border)."""
    return cv2.boxFilter(
        image, cv2.CV_64F, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT
    )


def normalized_ssd_volume(
    I_left: npt.ArrayLike,
    I_right: npt.ArrayLike,
    max_disparity: int,
    window: int = 3,
    min_disparity: int = 0,
) -> FloatArray:
    """Normalised SSD cost (5.2.3 with A5.5, A5.6) for d = 0..max_disparity.

    C(x, y, d) = sum_w (I_r(x+i, y+j) - I_l(x+d+i, y+j))^2
                 / sqrt(sum_w I_r(x+i, y+j)^2 * sum_w I_l(x+d+i, y+j)^2)
    over the window x window neighbourhood; pixels outside the images count as 0.
    Returns (max_disparity + 1, H, W) float, +inf where x + d >= W, where a window is all
    zero, and for d < ``min_disparity`` (not searched: saves time when the scene's depth
    range is known). One box filter per disparity: no per-pixel Python loop.
    """
    I_left, I_right = _check_image(I_left, 'I_left'), _check_image(I_right, 'I_right')
    if I_left.shape != I_right.shape:
        raise InvalidInput(
            f'I_left {I_left.shape} and I_right {I_right.shape} differ',
            key='I_left',
            value=I_left.shape,
        )
    if (
        window < 1
        or window % 2 == 0
        or max_disparity < 0
        or not 0 <= min_disparity <= max_disparity
    ):
        raise InvalidInput(
            f'window must be odd >= 1 and 0 <= min_disparity <= '
            f'max_disparity, got {window}, {min_disparity}, {max_disparity}',
            key='window',
            value=window,
        )
    H, W = I_right.shape
    r = window // 2
    cost = np.full((max_disparity + 1, H, W), np.inf)
    # Columns -r..W+r-1, so windows at the image's sides see I_l(x + d + i) where it exists.
    left = np.pad(I_left, ((0, 0), (r, r + max_disparity)))
    right = np.pad(I_right, ((0, 0), (r, r)))
    energy_right = _box_sum(right**2, window)[:, r : r + W]
    # Window energies of the shifted left image are columns of ONE box sum over the
    # padded left image (the kept columns' windows lie inside every shifted view).
    energy_left = _box_sum(left**2, window)
    for d in range(min_disparity, min(max_disparity + 1, W)):
        shifted = left[:, d : d + W + 2 * r]  # shifted(x) = I_l(x + d), 0 beyond the image
        ssd = _box_sum((right - shifted) ** 2, window)[:, r : r + W]
        energy = energy_right * energy_left[:, d + r : d + r + W]
        with np.errstate(divide='ignore', invalid='ignore'):
            layer = ssd / np.sqrt(energy)
        layer[~(energy > 0)] = np.inf
        layer[:, W - d :] = np.inf
        cost[d] = layer
    return cost


def left_reference_volume(
    I_left: npt.ArrayLike,
    I_right: npt.ArrayLike,
    max_disparity: int,
    window: int = 3,
    min_disparity: int = 0,
) -> FloatArray:
    """The same normalised SSD with the LEFT image as reference (ROS convention):
    C_L(x, y, d) compares left pixel x with right pixel x - d. Mirroring both images
    swaps their roles, so this is ``normalized_ssd_volume`` on the mirrored pair."""
    I_left, I_right = _check_image(I_left, 'I_left'), _check_image(I_right, 'I_right')
    cost = normalized_ssd_volume(
        I_right[:, ::-1], I_left[:, ::-1], max_disparity, window, min_disparity
    )
    return np.ascontiguousarray(cost[:, :, ::-1])


def window_std(image: npt.ArrayLike, window: int) -> np.ndarray:
    """Standard deviation of the grey levels in the window x window patch around each
    pixel (edge-replicated), a texture measure [grey levels]."""
    image = _check_image(image, 'image')
    mean = cv2.blur(image, (window, window), borderType=cv2.BORDER_REPLICATE)
    mean_sq = cv2.blur(image**2, (window, window), borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(np.maximum(mean_sq - mean**2, 0.0))


def confident_disparity(
    cost: npt.ArrayLike,
    threshold: float,
    texture: npt.ArrayLike | None = None,
    min_texture: float = 0.0,
    uniqueness: float = 0.0,
    left_right_check: bool = True,
    lr_tolerance: float = 1,
    subpixel: bool = True,
) -> FloatArray:
    """Left-reference disparity from a left-reference cost volume (``left_reference_volume``):
    the thesis's selection (C(d0) < threshold, d0 > 0) made confident.

    Also required, each optional: window texture >= ``min_texture`` (``texture`` (H, W),
    e.g. ``window_std``; a flat window's normalised SSD is low at every disparity);
    uniqueness: the best cost at least ``uniqueness`` (fraction) below the best cost
    more than one disparity away; left-right check: the right pixel x - d0 picks back d0
    within ``lr_tolerance`` [px]. ``subpixel`` refines d0 by the parabola through the
    costs at d0 - 1, d0, d0 + 1. Returns (H, W) float disparity [px], NaN where rejected.
    """
    cost = np.asarray(cost, dtype=float)
    if cost.ndim != 3:
        raise InvalidInput(
            f'cost: expected (D+1, H, W), got {cost.shape}', key='cost', value=cost.shape
        )
    n_disp, H, W = cost.shape
    # Layers below min_disparity are all +inf (not searched): leave them out of every
    # reduction below (same result; a pixel whose costs are all inf is rejected anyway).
    searched = np.flatnonzero(np.isfinite(cost).any(axis=(1, 2)))
    first = int(searched[0]) if len(searched) else 0
    if first > 0:
        cost = cost[first:]
    d0 = np.argmin(cost, axis=0)
    c0 = np.take_along_axis(cost, d0[None], axis=0)[0]
    d0 = d0 + first
    keep = (c0 < threshold) & (d0 > 0)
    if texture is not None and min_texture > 0:
        keep &= np.asarray(texture) >= min_texture
    if uniqueness > 0:
        disparities = np.arange(first, n_disp)[:, None, None]
        far = np.abs(disparities - d0[None]) > 1
        second = np.min(np.where(far, cost, np.inf), axis=0)
        keep &= c0 < (1 - uniqueness) * second
    if left_right_check:
        # cost_right[d, y, xr] = C_L(xr + d, y, d): the right image's own costs
        cost_right = np.full_like(cost, np.inf)
        for d in range(first, min(n_disp, W)):
            cost_right[d - first, :, : W - d] = cost[d - first, :, d:]
        d_right = np.argmin(cost_right, axis=0) + first
        x_right = np.maximum(np.arange(W)[None, :] - d0, 0)
        d_back = np.take_along_axis(d_right, x_right, axis=1)
        keep &= np.abs(d_back - d0) <= lr_tolerance
    disparity = d0.astype(float)
    if subpixel:
        inner = (d0 > 0) & (d0 < n_disp - 1)
        # d0 - 1 below the searched layers reads +inf there, as in the full volume
        lo = np.take_along_axis(cost, np.clip(d0 - 1 - first, 0, None)[None], axis=0)[0]
        lo = np.where(d0 - 1 < first, np.inf, lo)
        hi = np.take_along_axis(
            cost, np.clip(d0 + 1 - first, 0, n_disp - 1 - first)[None], axis=0
        )[0]
        with np.errstate(invalid='ignore', divide='ignore'):
            curvature = lo - 2 * c0 + hi
            offset = np.where(
                inner & np.isfinite(curvature) & (curvature > 0), 0.5 * (lo - hi) / curvature, 0.0
            )
        disparity += np.clip(np.nan_to_num(offset), -0.5, 0.5)
    return np.where(keep, disparity, np.nan)


def sgbm_disparity(
    I_left: npt.ArrayLike,
    I_right: npt.ArrayLike,
    max_disparity: int,
    window: int = 5,
    min_disparity: int = 0,
    mode: int = cv2.STEREO_SGBM_MODE_SGBM,
    pad_left: bool = False,
) -> FloatArray:
    """Semi-global matching: OpenCV's StereoSGBM on the rectified pair (left reference),
    P1 = 8 w^2, P2 = 32 w^2 as OpenCV's sample suggests, left-right check within 1 px,
    uniqueness 10 %, speckles smaller than 1/3000 of the image removed (100 px at
    640x480: relative, so the filter means the same at any resolution). Inputs are grey
    levels (any range; stretched to uint8). ``mode``: cv2.STEREO_SGBM_MODE_SGBM (the
    reference the bench compares with) or _SGBM_3WAY (the node's: the same disparities
    within 0.1 % bad pixels on Aloe, 2.4x faster). ``pad_left``: match the first
    min_disparity + band columns too (see below; the node's). Returns (H, W) float [px,
    1/16 px steps], NaN where invalid."""
    I_left, I_right = _check_image(I_left, 'I_left'), _check_image(I_right, 'I_right')
    lo, hi = min(I_left.min(), I_right.min()), max(I_left.max(), I_right.max())
    scale = 255.0 / max(hi - lo, 1e-12)
    left8 = np.clip((I_left - lo) * scale, 0, 255).astype(np.uint8)
    right8 = np.clip((I_right - lo) * scale, 0, 255).astype(np.uint8)
    count = max_disparity - min_disparity + 1
    count = int(np.ceil(count / 16) * 16)  # SGBM wants a multiple of 16
    matcher = cv2.StereoSGBM.create(
        minDisparity=int(min_disparity),
        numDisparities=count,
        blockSize=int(window),
        P1=8 * window**2,
        P2=32 * window**2,
        uniquenessRatio=10,
        speckleWindowSize=max(4, I_left.size // 3000),
        speckleRange=2,
        disp12MaxDiff=1,
        mode=mode,
    )
    # SGBM leaves the first min_disparity + count columns unmatched (their whole band is
    # not inside the right image); padding both images on the left lets those pixels
    # match what the right image does see, the left-right check refusing the rest.
    pad = max(int(min_disparity) + count, 0) if pad_left else 0
    left8, right8 = (
        cv2.copyMakeBorder(image, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
        for image in (left8, right8)
    )
    disparity = matcher.compute(left8, right8)[:, pad:].astype(float) / 16.0
    # SGBM marks invalid pixels with min_disparity - 1
    return np.where(disparity > min_disparity - 1, disparity, np.nan)


def refine_subpixel(
    I_left: npt.ArrayLike,
    I_right: npt.ArrayLike,
    disparity: npt.ArrayLike,
    window: int,
    iterations: int = 2,
) -> FloatArray:
    """``disparity`` [px, NaN = none] re-estimated to sub-pixel by Lucas-Kanade along the
    rows: a few Gauss-Newton steps of the window SSD between the left image and the
    right one sampled bilinearly at x - d, each step bounded to half a pixel. SGBM's own
    sub-pixel step fits a parabola to its aggregated, smoothed cost and pulls
    disparities toward integers in correlated bands, which no fusion averages out."""
    I_left = _check_image(I_left, 'I_left').astype(np.float32)
    I_right = _check_image(I_right, 'I_right').astype(np.float32)
    d = np.nan_to_num(np.asarray(disparity, dtype=np.float32))
    H, W = d.shape
    columns = np.arange(W, dtype=np.float32)[None, :]
    map_y = np.repeat(np.arange(H, dtype=np.float32)[:, None], W, axis=1)
    gradient = np.asarray(cv2.Sobel(I_right, cv2.CV_32F, 1, 0, ksize=3) / 8.0, np.float32)
    size = (window, window)
    for _ in range(iterations):
        map_x = (columns - d).astype(np.float32)
        warped = cv2.remap(
            I_right, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        g = cv2.remap(gradient, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        # I_right(x - d - dd) ~ warped - g dd = I_left  ->  dd = sum g (warped - I_left) / sum g^2
        numerator = cv2.blur(g * (warped - I_left), size, borderType=cv2.BORDER_REPLICATE)
        denominator = cv2.blur(g * g, size, borderType=cv2.BORDER_REPLICATE)
        with np.errstate(invalid='ignore', divide='ignore'):
            step = np.where(denominator > 1e-6, numerator / denominator, 0.0)
        d = d + np.clip(step, -0.5, 0.5)
    return np.where(np.isfinite(np.asarray(disparity, dtype=float)), d, np.nan)


def match_correlation(
    I_left: npt.ArrayLike, I_right: npt.ArrayLike, disparity: npt.ArrayLike, window: int
) -> FloatArray:
    """(H, W) zero-mean normalised cross-correlation of each left window with the right
    window its raw ``disparity`` [px, NaN = none] points at (right x = left x - d, the
    right image sampled bilinearly), in [-1, 1]; NaN where no disparity. A semi-global
    matcher's smoothness can make consistent disparities out of two unrelated images;
    the windows it pairs then do not correlate (about 1 / window for noise)."""
    I_left = _check_image(I_left, 'I_left').astype(np.float32)
    I_right = _check_image(I_right, 'I_right').astype(np.float32)
    disparity = np.asarray(disparity, dtype=np.float32)
    H, W = disparity.shape
    map_x = np.arange(W, dtype=np.float32)[None, :] - np.nan_to_num(disparity)
    map_y = np.repeat(np.arange(H, dtype=np.float32)[:, None], W, axis=1)
    warped = cv2.remap(I_right, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    size = (window, window)

    def blur(image: np.ndarray) -> np.ndarray:
        return cv2.blur(image, size, borderType=cv2.BORDER_REPLICATE)

    mean_l, mean_r = blur(I_left), blur(warped)
    covariance = blur(I_left * warped) - mean_l * mean_r
    var_l = np.maximum(blur(I_left * I_left) - mean_l**2, 0.0)
    var_r = np.maximum(blur(warped * warped) - mean_r**2, 0.0)
    with np.errstate(invalid='ignore', divide='ignore'):
        correlation = covariance / np.sqrt(var_l * var_r)
    return np.where(np.isfinite(disparity), np.nan_to_num(correlation), np.nan)


def reduce_disparity(disparity: npt.ArrayLike, factor: int, tolerance: float = 2.0) -> FloatArray:
    """A disparity map [px] at ``factor`` x coarser resolution, in the coarse grid's
    pixels: each factor x factor block's mean where at least half of it is matched and its
    matches agree within ``tolerance`` [px, fine grid], NaN elsewhere (a block across a
    depth edge mixes two surfaces: no mean of them is true). The rows and columns past
    the last whole block are dropped, as cv2.resize INTER_AREA does for the images."""
    disparity = np.asarray(disparity, dtype=float)
    if factor == 1:
        return disparity
    h, w = disparity.shape[0] // factor, disparity.shape[1] // factor
    # Element-wise over the factor^2 strided sub-images (one per position in the block):
    # numpy's reductions over the axes of a (h, factor, w, factor) view are 5x slower.
    count = np.zeros((h, w))
    total = np.zeros((h, w))
    high = np.full((h, w), -np.inf)
    low = np.full((h, w), np.inf)
    for i in range(factor):
        for j in range(factor):
            sub = disparity[i : h * factor : factor, j : w * factor : factor]
            valid = np.isfinite(sub)
            count += valid
            total += np.where(valid, sub, 0.0)
            high = np.maximum(high, np.where(valid, sub, -np.inf))
            low = np.minimum(low, np.where(valid, sub, np.inf))
    spread = high - low
    agree = (2 * count >= factor * factor) & (spread <= tolerance)
    with np.errstate(invalid='ignore', divide='ignore'):
        return np.where(agree, total / np.maximum(count, 1) / factor, np.nan)


def sparse_disparity(
    cost: npt.ArrayLike, threshold: float, left_right_check: bool = False, lr_tolerance: float = 0
) -> FloatArray:
    """Confident right-image disparity from a (D+1, H, W) cost volume (§4.2 step 5).

    d0 = argmin_d C; a pixel is kept where C(d0) < threshold and d0 > 0. With
    ``left_right_check`` it must also agree within ``lr_tolerance`` [px] with the left
    image's own best match (the same costs read from the left pixel x + d0).
    Returns (H, W) float disparity [px], NaN where not confident.
    """
    cost = np.asarray(cost, dtype=float)
    if cost.ndim != 3:
        raise InvalidInput(
            f'cost: expected (D+1, H, W), got {cost.shape}', key='cost', value=cost.shape
        )
    n_disp, H, W = cost.shape
    d0 = np.argmin(cost, axis=0)
    c0 = np.take_along_axis(cost, d0[None], axis=0)[0]
    keep = (c0 < threshold) & (d0 > 0)
    if left_right_check:
        cost_left = np.full_like(cost, np.inf)  # cost_left[d, y, xl] = C(xl - d, y, d)
        for d in range(min(n_disp, W)):
            cost_left[d, :, d:] = cost[d, :, : W - d]
        d_left = np.argmin(cost_left, axis=0)
        x_left = np.minimum(np.arange(W)[None, :] + d0, W - 1)
        d_back = np.take_along_axis(d_left, x_left, axis=1)
        keep &= np.abs(d_back - d0) <= lr_tolerance
    return np.where(keep, d0.astype(float), np.nan)


def depth_from_disparity(disparity: npt.ArrayLike, f_px: float, baseline_m: float) -> FloatArray:
    """Depth Z = f b / d (5.2.5) in the unit of ``baseline_m`` [m]; NaN where d is NaN or
    d <= 0. ``disparity`` [px] of any shape, ``f_px`` the focal length [px]."""
    disparity = np.asarray(disparity, dtype=float)
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(disparity > 0, f_px * baseline_m / disparity, np.nan)


# --- the fast matcher: band-limited cost volume with OpenCV box filters --------------


def noise_sigma(image: npt.ArrayLike, flat_fraction: float = 0.25) -> float:
    """Robust estimate of the image noise std [grey levels] (Immerkaer 1996: the
    Laplacian-difference mask cancels smooth shading to second order), taken over the
    ``flat_fraction`` of pixels with the weakest smoothed gradient (texture and edges
    would count as noise), floored at the 8-bit quantisation std 1/sqrt(12)."""
    image = np.asarray(image, dtype=np.float32)
    if min(image.shape) < 8:
        return 1.0 / np.sqrt(12.0)
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    response = np.abs(cv2.filter2D(image, cv2.CV_32F, mask))[2:-2, 2:-2]
    smooth = cv2.GaussianBlur(image, (0, 0), 2.0)
    gradient = np.hypot(cv2.Sobel(smooth, cv2.CV_32F, 1, 0), cv2.Sobel(smooth, cv2.CV_32F, 0, 1))
    flat = gradient[2:-2, 2:-2] <= np.quantile(gradient[2:-2, 2:-2], flat_fraction)
    # median |response| of Gaussian noise = 0.6745 * 6 sigma (sum of squared mask = 36)
    sigma = float(np.median(response[flat])) / (0.6745 * 6.0)
    return max(sigma, 1.0 / np.sqrt(12.0))


class Matches(NamedTuple):
    """A matcher's result on the left image: the confident raw disparity, the best cost
    and the distinctiveness of each pixel, all (H, W)."""

    disparity: FloatArray  # (H, W) raw disparity [px], NaN where not confident
    cost: FloatArray  # (H, W) best cost c0 (inf where nothing was searched)
    distinctiveness: FloatArray  # (H, W) 1 - c0 / c1, c1 the best cost > 1 px away


def _inverse_energy(image: Float32Array, size: tuple[int, int]) -> Float32Array:
    energy = cv2.boxFilter(
        image * image, cv2.CV_32F, size, normalize=False, borderType=cv2.BORDER_REFLECT
    )
    with np.errstate(divide='ignore'):
        return np.where(energy > 0, 1.0 / np.sqrt(np.maximum(energy, 1e-30)), np.inf).astype(
            np.float32
        )


def _columns(d: int, W: int) -> tuple[slice, slice]:
    """(left columns, right columns) that disparity d pairs: right x = left x - d."""
    return (slice(d, W), slice(0, W - d)) if d >= 0 else (slice(0, W + d), slice(-d, W))


def cost_layers(
    I_left: npt.ArrayLike, I_right: npt.ArrayLike, d_lo: int, d_hi: int, window: int = 3
) -> Iterator[tuple[int, int, Float32Array]]:
    """Yield (k, d, layer) for the integer raw disparities d = d_lo + k up to d_hi (any
    sign): the left-reference normalised SSD (the thesis's cost, 5.2.3) comparing left
    pixel x with right pixel x - d, float32 (H, W), +inf where x - d leaves the image
    or a window has no energy. Per layer one subtraction, one square and one
    unnormalised box filter on the overlapping columns; window energies once per image."""
    I_left = np.ascontiguousarray(_check_image(I_left, 'I_left'), dtype=np.float32)
    I_right = np.ascontiguousarray(_check_image(I_right, 'I_right'), dtype=np.float32)
    if I_left.shape != I_right.shape:
        raise InvalidInput(
            f'I_left {I_left.shape} and I_right {I_right.shape} differ',
            key='I_left',
            value=I_left.shape,
        )
    if window < 1 or window % 2 == 0 or d_hi < d_lo:
        raise InvalidInput(
            f'window must be odd >= 1 and d_lo <= d_hi, got {window}, {d_lo}, {d_hi}',
            key='window',
            value=window,
        )
    H, W = I_left.shape
    size = (window, window)
    inv_left, inv_right = _inverse_energy(I_left, size), _inverse_energy(I_right, size)
    for k, d in enumerate(range(d_lo, d_hi + 1)):
        layer = np.full((H, W), np.inf, dtype=np.float32)
        if abs(d) < W - window:
            left_cols, right_cols = _columns(d, W)
            diff = I_left[:, left_cols] - I_right[:, right_cols]
            ssd = cv2.boxFilter(
                diff * diff, cv2.CV_32F, size, normalize=False, borderType=cv2.BORDER_REFLECT
            )
            part = ssd * inv_left[:, left_cols] * inv_right[:, right_cols]
            part[np.isnan(part)] = np.inf
            layer[:, left_cols] = part
        yield k, d, layer


def band_cost_volume(
    I_left: npt.ArrayLike, I_right: npt.ArrayLike, d_lo: int, d_hi: int, window: int = 3
) -> Float32Array:
    """The (d_hi - d_lo + 1, H, W) float32 stack of ``cost_layers`` (for tests and
    inspection; the matcher streams the layers instead of storing them)."""
    return np.stack([layer for _, _, layer in cost_layers(I_left, I_right, d_lo, d_hi, window)])


def match_band(
    I_left: npt.ArrayLike,
    I_right: npt.ArrayLike,
    d_lo: int,
    d_hi: int,
    window: int = 3,
    threshold: float = np.inf,
    texture: npt.ArrayLike | None = None,
    min_texture: float = 0.0,
    uniqueness: float = 0.0,
    left_right_check: bool = True,
    lr_tolerance: float = 1,
    subpixel: bool = True,
) -> Matches:
    """Confident left-reference raw disparity over the band d_lo..d_hi: the thesis's
    selection (best normalised SSD cost below ``threshold``) made confident as
    ``confident_disparity`` describes (texture, uniqueness against the best cost more
    than 1 px away, left-right check, parabola subpixel); a best match on either edge
    of the band is rejected (the true minimum may lie outside it).

    The cost layers are streamed, never stored: memory O(H W), whatever the band. The
    best cost more than one layer from the best is exact: when layer k becomes the
    best, the runner-up is the minimum over layers <= k - 2, kept as a running minimum.
    Returns ``Matches``.
    """
    I_left = _check_image(I_left, 'I_left')
    H, W = I_left.shape
    c0 = np.full((H, W), np.inf, np.float32)
    c1 = np.full((H, W), np.inf, np.float32)
    d0 = np.zeros((H, W), np.int32)
    lo = np.full((H, W), np.inf, np.float32)  # cost at d0 - 1
    hi = np.full((H, W), np.inf, np.float32)  # cost at d0 + 1
    min_upto_prev = np.full((H, W), np.inf, np.float32)  # min over layers <= k - 1
    min_before_prev = np.full((H, W), np.inf, np.float32)  # min over layers <= k - 2
    previous = np.full((H, W), np.inf, np.float32)
    best_right = np.full((H, W), np.inf, np.float32)
    d_right = np.zeros((H, W), np.int32)
    for k, d, layer in cost_layers(I_left, I_right, d_lo, d_hi, window):
        better = layer < c0
        adjacent = d0 == k - 1
        np.copyto(hi, layer, where=adjacent & ~better)
        # not the new best: a runner-up candidate unless it neighbours the best
        np.copyto(c1, np.minimum(c1, layer), where=~better & ~adjacent)
        np.copyto(c1, min_before_prev, where=better)
        np.copyto(lo, previous, where=better)
        np.copyto(hi, np.float32(np.inf), where=better)
        np.copyto(c0, layer, where=better)
        np.copyto(d0, np.int32(k), where=better)
        np.copyto(min_before_prev, min_upto_prev)
        np.minimum(min_upto_prev, layer, out=min_upto_prev)
        previous = layer
        if left_right_check and abs(d) < W:
            left_cols, right_cols = _columns(d, W)
            part, best = layer[:, left_cols], best_right[:, right_cols]
            won = part < best
            np.copyto(best, part, where=won)
            np.copyto(d_right[:, right_cols], np.int32(k), where=won)
    n = d_hi - d_lo + 1
    cost0, cost1 = c0.astype(float), c1.astype(float)  # float64 c0, c1
    with np.errstate(invalid='ignore', divide='ignore'):
        distinct = np.where(np.isfinite(cost1) & (cost1 > 0), 1.0 - cost0 / cost1, 0.0)
    keep = np.isfinite(cost0) & (cost0 < threshold) & (d0 > 0) & (d0 < n - 1)
    if texture is not None and min_texture > 0:
        keep &= np.asarray(texture) >= min_texture
    if uniqueness > 0:
        keep &= distinct > uniqueness
    if left_right_check:
        x_right = np.clip(np.arange(W)[None, :] - (d0 + d_lo), 0, W - 1)
        keep &= np.abs(np.take_along_axis(d_right, x_right, axis=1) - d0) <= lr_tolerance
    disparity = (d0 + d_lo).astype(float)
    if subpixel:
        with np.errstate(invalid='ignore', divide='ignore', over='ignore'):
            cost_lo, cost_hi = lo.astype(float), hi.astype(float)
            curvature = cost_lo - 2 * cost0 + cost_hi
            offset = np.where(
                np.isfinite(curvature) & (curvature > 0),
                0.5 * (cost_lo - cost_hi) / curvature,
                0.0,
            )
        disparity += np.clip(np.nan_to_num(offset), -0.5, 0.5)
    return Matches(np.where(keep, disparity, np.nan), cost0, distinct)


def coherent_matches(
    disparity: npt.ArrayLike, radius: int = 2, tolerance: float = 1.0, min_support: int = 2
) -> tuple[FloatArray, float]:
    """``disparity`` with the matches that no neighbour backs removed: a match is kept
    when at least ``min_support`` other matches within ``radius`` px lie within
    ``tolerance`` px of its disparity (false matches are isolated; on a surface,
    neighbours agree). Returns (disparity, support fraction of the input matches)."""
    disparity = np.asarray(disparity, dtype=float)
    valid = np.isfinite(disparity)
    if not valid.any():
        return disparity, 0.0
    side = 2 * radius + 1
    d = np.where(valid, disparity, 0.0).astype(np.float32)
    v = valid.astype(np.float32)
    support = np.zeros(disparity.shape, dtype=np.float32)
    H, W = disparity.shape
    padded_d = cv2.copyMakeBorder(d, radius, radius, radius, radius, cv2.BORDER_CONSTANT)
    padded_v = cv2.copyMakeBorder(v, radius, radius, radius, radius, cv2.BORDER_CONSTANT)
    for dy in range(side):
        for dx in range(side):
            if dy == radius and dx == radius:
                continue
            nd, nv = padded_d[dy : dy + H, dx : dx + W], padded_v[dy : dy + H, dx : dx + W]
            support += nv * (np.abs(nd - d) <= tolerance)
    backed = valid & (support >= min_support)
    return np.where(backed, disparity, np.nan), float(backed.sum() / valid.sum())


def _match_tiles(
    I_left: Float32Array,
    I_right: Float32Array,
    centre: FloatArray,
    have: npt.NDArray[np.bool_],
    window: int,
    threshold: float,
    texture: np.ndarray,
    min_texture: float,
    uniqueness: float,
    left_right_check: bool,
    radius: int,
    tile: int = 64,
) -> Matches:
    """``match_band`` tile by tile, each ``tile`` x ``tile`` block searching only the
    disparities its predicted ``centre`` (where ``have``) spans, +- ``radius``: exact
    constant-disparity windows, left-right check and band-edge rejection as on the
    whole band, at a fraction of its layers. Returns ``Matches``."""
    H, W = I_left.shape
    margin = window // 2 + 1
    disparity = np.full((H, W), np.nan)
    cost = np.full((H, W), np.inf)
    distinct = np.zeros((H, W))
    for r0 in range(0, H, tile):
        for c0 in range(0, W, tile):
            r1, c1 = min(r0 + tile, H), min(c0 + tile, W)
            known = have[r0:r1, c0:c1]
            if not known.any():
                continue
            lo = int(np.min(centre[r0:r1, c0:c1][known])) - radius
            hi = int(np.max(centre[r0:r1, c0:c1][known])) + radius
            rows = slice(max(r0 - margin, 0), min(r1 + margin, H))
            a, b = max(c0 - margin - max(hi, 0), 0), min(c1 + margin - min(lo, 0), W)
            m = match_band(
                I_left[rows, a:b],
                I_right[rows, a:b],
                lo,
                hi,
                window,
                threshold,
                texture[rows, a:b],
                min_texture,
                uniqueness,
                left_right_check,
            )
            inner = (slice(r0 - rows.start, r1 - rows.start), slice(c0 - a, c1 - a))
            disparity[r0:r1, c0:c1] = m.disparity[inner]
            cost[r0:r1, c0:c1] = m.cost[inner]
            distinct[r0:r1, c0:c1] = m.distinctiveness[inner]
    return Matches(disparity, cost, distinct)


def _half(image: np.ndarray) -> np.ndarray:
    H, W = image.shape
    return cv2.resize(
        np.ascontiguousarray(image[: H // 2 * 2, : W // 2 * 2], dtype=np.float32),
        (W // 2, H // 2),
        interpolation=cv2.INTER_AREA,
    )


def match_pyramid(
    I_left: npt.ArrayLike,
    I_right: npt.ArrayLike,
    d_lo: int,
    d_hi: int,
    window: int = 3,
    threshold: float = np.inf,
    texture_snr: float = 0.0,
    min_texture: float = 0.0,
    uniqueness: float = 0.0,
    left_right_check: bool = True,
    max_full_band: int = 24,
    min_width: int = 96,
    radius: int = 2,
) -> tuple[Matches, int]:
    """``match_band`` made fast for wide bands: while the band has more than
    ``max_full_band`` layers (and the half image keeps ``min_width`` px), the whole
    band is searched on the image halved (INTER_AREA; disparities halve), and the
    full resolution only within ``radius`` px around twice the coarse matches, tile by
    tile (``_match_tiles``, with every test of ``match_band``). Texture at every level:
    window std >= max(``min_texture``,
    ``texture_snr`` x the level's noise std (``noise_sigma``)), so the same setting
    holds for any contrast, noise and resolution.
    Returns (``Matches`` at full resolution, levels used)."""
    I_left = np.asarray(_check_image(I_left, 'I_left'), dtype=np.float32)
    I_right = np.asarray(_check_image(I_right, 'I_right'), dtype=np.float32)
    H, W = I_left.shape

    def texture_floor(image: np.ndarray) -> float:
        return max(min_texture, texture_snr * noise_sigma(image))

    texture = window_std(I_left, window)
    if d_hi - d_lo + 1 <= max_full_band or W // 2 < min_width:
        matches = match_band(
            I_left,
            I_right,
            d_lo,
            d_hi,
            window,
            threshold,
            texture,
            texture_floor(I_left),
            uniqueness,
            left_right_check,
        )
        return matches, 1
    coarse, levels = match_pyramid(
        _half(I_left),
        _half(I_right),
        int(np.floor(d_lo / 2)),
        int(np.ceil(d_hi / 2)),
        window,
        threshold,
        texture_snr,
        min_texture,
        uniqueness,
        left_right_check,
        max_full_band,
        min_width,
        radius,
    )
    found = np.isfinite(coarse.disparity)
    # Fill one-pixel holes of the coarse map (its texture test is stricter: averaging
    # halves the shading gradients) from the nearest coarse match.
    filled = np.where(found, coarse.disparity, 0.0).astype(np.float32)
    count = cv2.boxFilter(found.astype(np.float32), -1, (3, 3), normalize=False)
    total = cv2.boxFilter(filled, -1, (3, 3), normalize=False)
    with np.errstate(invalid='ignore', divide='ignore'):
        near = np.where(found, filled, np.where(count > 0, total / count, np.nan))
    up = cv2.resize(
        np.nan_to_num(near, nan=-1e6).astype(np.float32),
        (W // 2 * 2, H // 2 * 2),
        interpolation=cv2.INTER_NEAREST,
    )
    predicted = np.full((H, W), -1e6, np.float32)
    predicted[: up.shape[0], : up.shape[1]] = up
    have = predicted > -1e5
    centre = np.rint(np.where(have, 2 * predicted, 0.0))
    fine = _match_tiles(
        I_left,
        I_right,
        centre,
        have,
        window,
        threshold,
        texture,
        texture_floor(I_left),
        uniqueness,
        left_right_check,
        radius,
    )
    # only where the coarse level found the pixel's match and the fine one agrees
    keep = have & (np.abs(fine.disparity - centre) <= radius)
    disparity, cost = fine.disparity, fine.cost
    distinct = np.maximum(
        fine.distinctiveness,
        cv2.resize(
            coarse.distinctiveness.astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST
        ).astype(float),
    )
    return Matches(np.where(keep, disparity, np.nan), cost, distinct), levels + 1
