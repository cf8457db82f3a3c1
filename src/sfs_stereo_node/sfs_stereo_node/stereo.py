"""Sparse stereo branch of chapter 5 (ALGORITHMS.md §4.2, A5.5-A5.7).

Images are (H, W) float arrays of a rectified pair, x = column, y = row. The right image
is the reference (A5.5): right pixel x matches left pixel x + d, d >= 0 [px].
"""
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


def _box_sum(volume, window):
    """Sums over every full window x window patch of the last two axes ('valid' mode: each
    axis shrinks by window - 1), by cumulative sums."""
    for axis in (-2, -1):
        pad = [(0, 0)] * volume.ndim
        pad[axis] = (1, 0)
        c = np.cumsum(np.pad(volume, pad), axis=axis)
        n = c.shape[axis]
        volume = (np.take(c, np.arange(window, n), axis=axis)
                  - np.take(c, np.arange(n - window), axis=axis))
    return volume


def normalized_ssd_volume(I_left, I_right, max_disparity, window=3):
    """Normalised SSD cost (5.2.3 with A5.5, A5.6) for d = 0..max_disparity.

    C(x, y, d) = sum_w (I_r(x+i, y+j) - I_l(x+d+i, y+j))^2
                 / sqrt(sum_w I_r(x+i, y+j)^2 * sum_w I_l(x+d+i, y+j)^2)
    over the window x window neighbourhood; pixels outside the images count as 0.
    Returns (max_disparity + 1, H, W) float, +inf where x + d >= W or a window is all zero.
    """
    I_left, I_right = _check_image(I_left, 'I_left'), _check_image(I_right, 'I_right')
    if I_left.shape != I_right.shape:
        raise InvalidInput(f'I_left {I_left.shape} and I_right {I_right.shape} differ',
                           key='I_left', value=I_left.shape)
    if window < 1 or window % 2 == 0 or max_disparity < 0:
        raise InvalidInput(f'window must be odd >= 1 and max_disparity >= 0, got '
                           f'{window}, {max_disparity}', key='window', value=window)
    H, W = I_right.shape
    r, D = window // 2, max_disparity
    left = np.pad(I_left, ((r, r), (r, r + D)))
    right = np.pad(I_right, r)
    # shifted[d, y, x] = I_l(x + d, y) on the padded grid
    shifted = np.stack([left[:, d:d + W + 2 * r] for d in range(D + 1)])
    ssd = _box_sum((right - shifted) ** 2, window)
    energy = _box_sum(right**2, window) * _box_sum(shifted**2, window)
    with np.errstate(divide='ignore', invalid='ignore'):
        cost = ssd / np.sqrt(energy)
    cost[~(energy > 0)] = np.inf
    outside = np.arange(W)[None, None, :] + np.arange(max_disparity + 1)[:, None, None] >= W
    return np.where(outside, np.inf, cost)


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
