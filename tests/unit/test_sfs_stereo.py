"""Chapter 5 cores (stereo, SFS, fusion) against synthetic ground truth, all seeded."""

import numpy as np
import pytest

from sfs_stereo_node.fusion import depth_error_stats, fuse_least_squares
from sfs_stereo_node.sfs import reflectance, sfs_depth
from sfs_stereo_node.stereo import (
    depth_from_disparity,
    histogram_line_fit,
    normalized_ssd_volume,
    sparse_disparity,
)
from sfs_stereo_node.thesis import fuse_mlp_rows, train_row_networks
from vgm_common.errors import InvalidInput


def brute_force_ssd(I_left, I_right, max_disparity, window):
    """Per-pixel normalised SSD, zeros outside the images, +inf where x + d >= W."""
    H, W = I_right.shape
    r = window // 2
    L, R = np.pad(I_left, r + max_disparity), np.pad(I_right, r + max_disparity)
    o = r + max_disparity
    cost = np.full((max_disparity + 1, H, W), np.inf)
    for d in range(max_disparity + 1):
        for y in range(H):
            for x in range(W - d):
                wr = R[o + y - r : o + y + r + 1, o + x - r : o + x + r + 1]
                wl = L[o + y - r : o + y + r + 1, o + x + d - r : o + x + d + r + 1]
                cost[d, y, x] = np.sum((wr - wl) ** 2) / np.sqrt(np.sum(wr**2) * np.sum(wl**2))
    return cost


@pytest.mark.parametrize('window', [3, 5])
def test_ssd_volume_matches_brute_force(window):
    rng = np.random.default_rng(0)
    I_left, I_right = rng.random((9, 13)), rng.random((9, 13))
    fast = normalized_ssd_volume(I_left, I_right, 4, window)
    slow = brute_force_ssd(I_left, I_right, 4, window)
    assert fast.shape == (5, 9, 13)
    np.testing.assert_array_equal(np.isinf(fast), np.isinf(slow))
    finite = np.isfinite(slow)
    np.testing.assert_allclose(fast[finite], slow[finite], rtol=0, atol=1e-9)


def make_pair(rng, H=48, W=64):
    """Random-dot right image; left image with I_l(x + d) = I_r(x), d = 3 in the top half
    and 6 in the bottom half (a step along y, so no occlusions); fresh dots elsewhere."""
    true_d = np.where(np.arange(H)[:, None] < H // 2, 3, 6) * np.ones((1, W), dtype=int)
    I_right = rng.uniform(0.1, 1.0, (H, W))
    I_left = rng.uniform(0.1, 1.0, (H, W))
    for y in range(H):
        d = true_d[y, 0]
        I_left[y, d:] = I_right[y, : W - d]
    return I_left, I_right, true_d


@pytest.mark.parametrize('lr_check', [False, True])
def test_sparse_disparity_recovers_step(lr_check):
    I_left, I_right, true_d = make_pair(np.random.default_rng(1))
    cost = normalized_ssd_volume(I_left, I_right, max_disparity=10)
    disparity = sparse_disparity(cost, threshold=0.05, left_right_check=lr_check)
    confident = np.isfinite(disparity)
    exact = np.mean(disparity[confident] == true_d[confident])
    assert confident.mean() > 0.8  # measured 0.873 with and without the check
    assert exact > 0.95  # measured 0.9996 (one pixel on the step's row is off)
    depth = depth_from_disparity(disparity, f_px=500.0, baseline_m=0.1)
    np.testing.assert_allclose(depth[confident], 500.0 * 0.1 / disparity[confident])
    assert np.all(np.isnan(depth[~confident]))


def test_histogram_line_fit_recovers_affine_change():
    rng = np.random.default_rng(2)
    I_right = rng.beta(2, 5, (60, 80))
    I_left = 1.3 * rng.permuted(I_right) + 0.1 + rng.normal(0, 0.002, I_right.shape)
    alpha, beta = histogram_line_fit(I_left, I_right)
    assert alpha == pytest.approx(1.3, abs=0.01)
    assert beta == pytest.approx(0.1, abs=0.005)


def test_bad_shapes_raise():
    with pytest.raises(InvalidInput):
        normalized_ssd_volume(np.zeros((4, 5)), np.zeros((4, 6)), 2)
    with pytest.raises(InvalidInput):
        fuse_least_squares(np.zeros((4, 5)), np.full((4, 5), np.nan))


def sphere(H=64, W=64, radius=24.0):
    y, x = np.mgrid[:H, :W] - (np.array([H, W])[:, None, None] - 1) / 2
    rho2 = x**2 + y**2
    inside = rho2 < radius**2
    G = np.sqrt(np.maximum(radius**2 - rho2, 0.0))
    with np.errstate(divide='ignore', invalid='ignore'):
        p, q = np.where(inside, -x / G, 0.0), np.where(inside, -y / G, 0.0)
    return G, p, q, rho2 < (0.9 * radius) ** 2


def test_reflectance_reduces_to_lambert():
    p, q = np.random.default_rng(3).normal(0, 0.5, (2, 50))
    lambert = reflectance(p, q, 0.2, -0.1, 0.7, 0.0)
    cos_i = (1 + 0.2 * p - 0.1 * q) / np.sqrt((1 + p**2 + q**2) * (1 + 0.05))
    np.testing.assert_allclose(lambert, 0.7 * np.maximum(cos_i, 0))
    for variant in ('thesis', 'oren_nayar'):
        rough = reflectance(p, q, 0.2, -0.1, 0.7, 0.3, variant)
        assert np.all(rough >= 0) and np.all(rough <= 0.7 * 1.5)


def test_sfs_sphere_correlates_with_truth():
    G, p, q, mask = sphere()
    light = (0.1, 0.1)  # slightly oblique, along the image diagonal
    E = reflectance(p, q, *light, albedo=1.0, roughness=0.0)
    Z = sfs_depth(E, light, albedo=1.0, roughness=0.0, iterations=200, tol=1e-6)
    errors = depth_error_stats(Z, G, mask)
    corr = np.corrcoef(Z[mask], G[mask])[0, 1]
    assert corr > 0.9  # measured 0.954 on the inner 90 % of the sphere's radius
    assert errors.rms < 0.3 * np.ptp(G[mask])  # measured 3.22 on a range of 13.43


def test_row_network_training_lowers_loss():
    rng = np.random.default_rng(4)
    x = np.linspace(0, 1, 40)[None, :]
    t = (x**2 + 0.2 * x) / 1.2  # monotonic map, scaled to [0, 1]
    mask = rng.random(x.shape) < 0.5
    _, loss0, loss1 = train_row_networks(x, t, mask, rng)
    assert loss1[0] < 0.1 * loss0[0]  # measured 0.123 -> 0.0030


def smooth_surface(H=48, W=64):
    y, x = np.mgrid[:H, :W] / np.array([H, W])[:, None, None]
    return 2.0 + np.exp(-((x - 0.4) ** 2 + (y - 0.5) ** 2) / 0.05) + 0.5 * x * y


def test_mlp_rows_fusion_improves_on_sfs():
    rng = np.random.default_rng(5)
    G = smooth_surface()
    Z_sfs = np.sqrt(G) + 0.03 * np.sin(np.arange(G.shape[1]) / 5.0)  # monotonic distortion
    Z_stereo = np.where(rng.random(G.shape) < 0.1, G, np.nan)
    Z_stereo[10:14] = np.nan  # four rows borrow a neighbour's network
    fused = fuse_mlp_rows(Z_sfs, Z_stereo, np.random.default_rng(6))
    assert not fused.trained_rows[10:14].any()
    trained = fused.trained_rows
    assert np.all(fused.loss_final[trained] < fused.loss_initial[trained])  # mean 0.72 -> 0.028
    rms_fused = np.sqrt(np.mean((fused.depth - G) ** 2))
    rms_sfs = depth_error_stats(Z_sfs, G, np.ones(G.shape, bool)).rms
    assert rms_fused < rms_sfs  # measured 0.076 vs 0.125


def test_least_squares_fusion_beats_sfs():
    rng = np.random.default_rng(7)
    G = smooth_surface()
    H, W = G.shape
    y, x = np.mgrid[:H, :W] / np.array([H, W])[:, None, None]
    Z_sfs = 0.6 * G + 3.0 + 0.15 * np.sin(3 * x + 2 * y)  # affine + smooth error
    Z_stereo = np.where(rng.random(G.shape) < 0.05, G, np.nan)
    Z = fuse_least_squares(Z_sfs, Z_stereo, weight=0.1)
    rms_sfs = depth_error_stats(Z_sfs, G, np.ones(G.shape, bool)).rms  # 0.140 (§4.5 map)
    rms_fused = np.sqrt(np.mean((Z - G) ** 2))  # 0.0126, already in G's unit
    assert rms_fused < rms_sfs / 5  # measured factor 11
    assert depth_error_stats(Z, G, np.ones(G.shape, bool)).rms < rms_sfs / 2.5  # 0.045
