"""Sparse stereo branch of chapter 5 (ALGORITHMS.md §4.2, A5.5-A5.7).

Images are (H, W) float arrays of a rectified pair, x = column, y = row. The right image
is the reference (A5.5): right pixel x matches left pixel x + d, d >= 0 [px].
"""
import cv2
import numpy as np

from vgm_common.errors import InvalidInput


def _check_image(image, name):
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        raise InvalidInput(f'{name}: expected an (H, W) image, got shape {image.shape}',
                           key=name, value=image.shape)
    return image


def histogram_line_fit(I_ref, I_other, quantiles=256):
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


def _box_sum(image, window):
    """Sums over the window x window patch centred on every pixel of a 2-D float64 image,
    zeros outside (cv2.boxFilter, unnormalised, constant border)."""
    return cv2.boxFilter(image, cv2.CV_64F, (window, window), normalize=False,
                         borderType=cv2.BORDER_CONSTANT)


def normalized_ssd_volume(I_left, I_right, max_disparity, window=3, min_disparity=0):
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
        raise InvalidInput(f'I_left {I_left.shape} and I_right {I_right.shape} differ',
                           key='I_left', value=I_left.shape)
    if window < 1 or window % 2 == 0 or max_disparity < 0 or \
            not 0 <= min_disparity <= max_disparity:
        raise InvalidInput(f'window must be odd >= 1 and 0 <= min_disparity <= '
                           f'max_disparity, got {window}, {min_disparity}, {max_disparity}',
                           key='window', value=window)
    H, W = I_right.shape
    r = window // 2
    cost = np.full((max_disparity + 1, H, W), np.inf)
    # Columns -r..W+r-1, so windows at the image's sides see I_l(x + d + i) where it exists.
    left = np.pad(I_left, ((0, 0), (r, r + max_disparity)))
    right = np.pad(I_right, ((0, 0), (r, r)))
    energy_right = _box_sum(right**2, window)[:, r:r + W]
    # Window energies of the shifted left image are columns of ONE box sum over the
    # padded left image (the kept columns' windows lie inside every shifted view).
    energy_left = _box_sum(left**2, window)
    for d in range(min_disparity, min(max_disparity + 1, W)):
        shifted = left[:, d:d + W + 2 * r]  # shifted(x) = I_l(x + d), 0 beyond the image
        ssd = _box_sum((right - shifted) ** 2, window)[:, r:r + W]
        energy = energy_right * energy_left[:, d + r:d + r + W]
        with np.errstate(divide='ignore', invalid='ignore'):
            layer = ssd / np.sqrt(energy)
        layer[~(energy > 0)] = np.inf
        layer[:, W - d:] = np.inf
        cost[d] = layer
    return cost


def left_reference_volume(I_left, I_right, max_disparity, window=3, min_disparity=0):
    """The same normalised SSD with the LEFT image as reference (ROS convention):
    C_L(x, y, d) compares left pixel x with right pixel x - d. Mirroring both images
    swaps their roles, so this is ``normalized_ssd_volume`` on the mirrored pair."""
    I_left, I_right = _check_image(I_left, 'I_left'), _check_image(I_right, 'I_right')
    cost = normalized_ssd_volume(I_right[:, ::-1], I_left[:, ::-1], max_disparity, window,
                                 min_disparity)
    return np.ascontiguousarray(cost[:, :, ::-1])


def window_std(image, window):
    """Standard deviation of the grey levels in the window x window patch around each
    pixel (edge-replicated), a texture measure [grey levels]."""
    image = _check_image(image, 'image')
    mean = cv2.blur(image, (window, window), borderType=cv2.BORDER_REPLICATE)
    mean_sq = cv2.blur(image**2, (window, window), borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(np.maximum(mean_sq - mean**2, 0.0))


def confident_disparity(cost, threshold, texture=None, min_texture=0.0, uniqueness=0.0,
                        left_right_check=True, lr_tolerance=1, subpixel=True):
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
        raise InvalidInput(f'cost: expected (D+1, H, W), got {cost.shape}', key='cost',
                           value=cost.shape)
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
            cost_right[d - first, :, :W - d] = cost[d - first, :, d:]
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
        hi = np.take_along_axis(cost, np.clip(d0 + 1 - first, 0, n_disp - 1 - first)[None],
                                axis=0)[0]
        with np.errstate(invalid='ignore', divide='ignore'):
            curvature = lo - 2 * c0 + hi
            offset = np.where(inner & np.isfinite(curvature) & (curvature > 0),
                              0.5 * (lo - hi) / curvature, 0.0)
        disparity += np.clip(np.nan_to_num(offset), -0.5, 0.5)
    return np.where(keep, disparity, np.nan)


def sgbm_disparity(I_left, I_right, max_disparity, window=5, min_disparity=0):
    """Reference dense matcher: OpenCV's StereoSGBM on the rectified pair (left
    reference), P1 = 8 w^2, P2 = 32 w^2 as OpenCV's sample suggests. Inputs are grey
    levels (any range; rescaled to uint8). Returns (H, W) float [px], NaN where invalid."""
    I_left, I_right = _check_image(I_left, 'I_left'), _check_image(I_right, 'I_right')
    lo, hi = min(I_left.min(), I_right.min()), max(I_left.max(), I_right.max())
    scale = 255.0 / max(hi - lo, 1e-12)
    left8 = np.clip((I_left - lo) * scale, 0, 255).astype(np.uint8)
    right8 = np.clip((I_right - lo) * scale, 0, 255).astype(np.uint8)
    count = max_disparity - min_disparity + 1
    count = int(np.ceil(count / 16) * 16)  # SGBM wants a multiple of 16
    matcher = cv2.StereoSGBM_create(minDisparity=int(min_disparity), numDisparities=count,
                                    blockSize=int(window), P1=8 * window**2,
                                    P2=32 * window**2, uniquenessRatio=10,
                                    speckleWindowSize=50, speckleRange=2, disp12MaxDiff=1,
                                    mode=cv2.STEREO_SGBM_MODE_SGBM)
    disparity = matcher.compute(left8, right8).astype(float) / 16.0
    # SGBM marks invalid pixels with min_disparity - 1
    return np.where((disparity > min_disparity - 1) & (disparity > 0), disparity, np.nan)


def sparse_disparity(cost, threshold, left_right_check=False, lr_tolerance=0):
    """Confident right-image disparity from a (D+1, H, W) cost volume (§4.2 step 5).

    d0 = argmin_d C; a pixel is kept where C(d0) < threshold and d0 > 0. With
    ``left_right_check`` it must also agree within ``lr_tolerance`` [px] with the left
    image's own best match (the same costs read from the left pixel x + d0).
    Returns (H, W) float disparity [px], NaN where not confident.
    """
    cost = np.asarray(cost, dtype=float)
    if cost.ndim != 3:
        raise InvalidInput(f'cost: expected (D+1, H, W), got {cost.shape}', key='cost',
                           value=cost.shape)
    n_disp, H, W = cost.shape
    d0 = np.argmin(cost, axis=0)
    c0 = np.take_along_axis(cost, d0[None], axis=0)[0]
    keep = (c0 < threshold) & (d0 > 0)
    if left_right_check:
        cost_left = np.full_like(cost, np.inf)  # cost_left[d, y, xl] = C(xl - d, y, d)
        for d in range(min(n_disp, W)):
            cost_left[d, :, d:] = cost[d, :, :W - d]
        d_left = np.argmin(cost_left, axis=0)
        x_left = np.minimum(np.arange(W)[None, :] + d0, W - 1)
        d_back = np.take_along_axis(d_left, x_left, axis=1)
        keep &= np.abs(d_back - d0) <= lr_tolerance
    return np.where(keep, d0.astype(float), np.nan)


def depth_from_disparity(disparity, f_px, baseline_m):
    """Depth Z = f b / d (5.2.5) in the unit of ``baseline_m`` [m]; NaN where d is NaN or
    d <= 0. ``disparity`` [px] of any shape, ``f_px`` the focal length [px]."""
    disparity = np.asarray(disparity, dtype=float)
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(disparity > 0, f_px * baseline_m / disparity, np.nan)
