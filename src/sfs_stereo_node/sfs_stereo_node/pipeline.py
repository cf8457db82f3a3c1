"""One stereo pair -> disparity, sparse stereo depth, SFS depth, fused depth (chapter 5
pipeline, ALGORITHMS.md §4.6), shared by the node, the tests and the bench. No rclpy.

Everything lives in the rectified LEFT frame (ROS convention; the thesis's choice of the
right image as reference is internal to it), at the processing resolution: the rectified
full-resolution images averaged over ``downsample`` x ``downsample`` blocks.
"""
import time
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from sfs_stereo_node import fusion as fusion_cores
from sfs_stereo_node.rectify import (
    light_in_rectified_frame,
    rectified_valid_mask,
    rectify,
    scaled_pair,
)
from sfs_stereo_node.refine import ShadingModel, refine_depth
from sfs_stereo_node.sfs import light_gradient, sfs_depth
from sfs_stereo_node.stereo import (
    confident_disparity,
    depth_from_disparity,
    histogram_line_fit,
    left_reference_volume,
    sgbm_disparity,
    window_std,
)
from vgm_common.errors import InvalidInput

FUSIONS = ('shading_refine', 'local_affine', 'least_squares', 'mlp_rows')
STEREOS = ('ssd', 'sgbm')


@dataclass
class DepthConfig:
    """Processing settings (the node's parameters; README has the table)."""

    window: int = 3
    max_disparity: int = 160  # [px at full resolution]
    min_disparity: int = 0  # [px at full resolution]
    min_depth: float = 0.35  # [m] nearest surface the rig sees; 0 = no limit
    max_depth: float = 1.5  # [m] farthest; 0 = no limit
    match_threshold: float = 0.02
    min_texture: float = 2.0  # [grey levels] window std
    uniqueness: float = 0.02
    left_right_check: bool = True
    light_direction: tuple = (-0.23, -0.70, -0.67)  # left optical frame, surface -> light
    albedo: float = 0.8
    ambient: float = 0.08
    roughness: float = 0.3
    fusion: str = 'shading_refine'
    stereo: str = 'ssd'
    seed: int = 0
    sfs_iterations: int = 150
    sfs_downsample: int = 2  # SFS grid = processing grid / this
    sfs_max_step: float = 0.5
    downsample: int = 2
    min_intensity: float = 30.0  # [grey levels] darker = no surface (background, shadow)
    mlp_epochs: int = 500
    fusion_sigma: float = 12.0  # [px] local_affine neighbourhood
    fusion_weight: float = 1.0  # least_squares gradient weight
    refine_shading_sigma: float = 2.0  # [grey levels] shading_refine image noise
    refine_stereo_sigma: float = 0.002  # [m] shading_refine stereo depth noise
    refine_curvature_sigma: float = 1e-4  # [m/px^2] shading_refine thin-plate prior
    refine_finest_steps: int = 1  # shading_refine Gauss-Newton steps on the full grid


class DepthResult(NamedTuple):
    disparity: np.ndarray  # (h, w) float32 [px at processing resolution], NaN = no match
    depth_stereo: np.ndarray  # (h, w) float32 [m], NaN where no confident match
    depth_sfs: np.ndarray  # (h, w) float32 [m], SFS mapped affinely onto the stereo depths
    depth_fused: np.ndarray  # (h, w) float32 [m], NaN where no surface
    surface: np.ndarray  # (h, w) bool, where the surface is seen
    focal_px: float  # at processing resolution
    baseline_m: float
    P: np.ndarray  # (3, 4) rectified left projection at processing resolution
    valid_window: tuple  # (x, y, w, h) of fully valid rectified pixels
    density: float  # confident matches / surface pixels
    timings: dict  # stage -> seconds


def to_grey(image):
    """(H, W) or (H, W, 3) image -> float32 grey levels scaled to 0..255."""
    image = np.asarray(image)
    scale = 255.0 / 65535.0 if image.dtype == np.uint16 else 1.0
    if image.ndim == 3:
        image = cv2.cvtColor(image.astype(np.float32), cv2.COLOR_RGB2GRAY)
    return image.astype(np.float32) * scale


def _valid_window(mask):
    rows, cols = np.flatnonzero(mask.all(axis=1)), np.flatnonzero(mask.all(axis=0))
    if not len(rows) or not len(cols):
        return (0, 0, 0, 0)
    return (int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1),
            int(rows[-1] - rows[0] + 1))


def process_pair(left_raw, right_raw, pair, raw_size, config, rng=None):
    """Run the pipeline on one raw pair of grey images (2-D arrays, 0..255).

    ``pair`` a full-resolution ``RectifiedPair``; ``raw_size`` (width, height) of the raw
    images. Raises InvalidInput when the pair gives nothing usable (no surface, no
    confident match), so the caller reports it instead of publishing.
    """
    timings = {}
    started = time.perf_counter()
    factor = int(config.downsample)
    small = scaled_pair(pair, factor)
    w, h = small.size
    images = []
    for raw, maps in ((left_raw, pair.maps_left), (right_raw, pair.maps_right)):
        rect = rectify(to_grey(raw), maps)
        if factor > 1:
            rect = cv2.resize(rect[:h * factor, :w * factor], (w, h),
                              interpolation=cv2.INTER_AREA)
        images.append(rect.astype(float))
    left, right = images
    valid = rectified_valid_mask(small.maps_left, raw_size) & \
        rectified_valid_mask(small.maps_right, raw_size)
    surface = cv2.morphologyEx((left > config.min_intensity).astype(np.uint8),
                               cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)).astype(bool)
    surface &= cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if surface.sum() < 16:
        raise InvalidInput(f'no surface seen: fewer than 16 pixels brighter than '
                           f'min_intensity {config.min_intensity:g}', key='image')
    timings['rectify'] = time.perf_counter() - started

    t = time.perf_counter()
    d_max = max(1, int(np.ceil(config.max_disparity / factor)))
    d_min = min(int(config.min_disparity // factor), d_max)
    # The rig sees the surface within [min_depth, max_depth]: only d = f b / Z there is
    # searched (fewer cost layers), and a best match on the band's edge is rejected (the
    # true minimum may lie outside it).
    fb = small.focal_px * small.baseline_m
    if config.min_depth > 0:
        d_max = max(1, min(d_max, int(np.ceil(fb / config.min_depth)) + 1))
    if config.max_depth > 0:
        d_min = min(max(d_min, int(np.floor(fb / config.max_depth)) - 1), d_max - 1)
    if config.stereo == 'sgbm':
        disparity = sgbm_disparity(left, right, d_max, window=max(config.window, 3),
                                   min_disparity=d_min)
    else:
        # The thesis normalises the other image onto the reference's histogram (5.2.2).
        alpha, beta = histogram_line_fit(left, right)
        cost = left_reference_volume(left, alpha * right + beta, d_max, config.window, d_min)
        disparity = confident_disparity(
            cost, config.match_threshold, window_std(left, config.window),
            config.min_texture, config.uniqueness, config.left_right_check)
    disparity = np.where(surface, disparity, np.nan)
    with np.errstate(invalid='ignore'):
        on_edge = (disparity >= d_max - 0.5) | ((disparity <= d_min + 0.5) & (d_min > 0))
    disparity[on_edge] = np.nan
    depth_stereo = depth_from_disparity(disparity, small.focal_px, small.baseline_m)
    matched = np.isfinite(depth_stereo)
    density = float(matched.sum() / surface.sum())
    timings['stereo'] = time.perf_counter() - t
    if matched.sum() < 8:
        raise InvalidInput(f'only {int(matched.sum())} confident stereo matches: nothing '
                           'to fix the depth scale', key='image')

    t = time.perf_counter()
    light = light_in_rectified_frame(config.light_direction, pair.R_left)
    E = np.clip(left / 255.0 - config.albedo * config.ambient, 0.0, None)
    k = int(config.sfs_downsample)
    if k > 1:  # Tsai-Shah needs ~image-width iterations: a coarser grid is k^3 cheaper
        hs, ws = h // k, w // k
        E_small = cv2.resize(E[:hs * k, :ws * k], (ws, hs), interpolation=cv2.INTER_AREA)
        mask_small = cv2.resize(surface[:hs * k, :ws * k].astype(np.float32), (ws, hs),
                                interpolation=cv2.INTER_AREA) > 0.5
        height = sfs_depth(E_small, light_gradient(light), config.albedo, config.roughness,
                           config.sfs_iterations, tol=1e-4, max_step=config.sfs_max_step,
                           mask=mask_small)
        height = k * cv2.resize(height, (w, h), interpolation=cv2.INTER_LINEAR)
    else:
        height = sfs_depth(E, light_gradient(light), config.albedo, config.roughness,
                           config.sfs_iterations, tol=1e-4, max_step=config.sfs_max_step,
                           mask=surface)
    # Height toward the viewer, in pixel units: depth grows as height falls.
    relief = np.where(surface, -height, np.nan)
    on = matched & surface
    a, b = np.polyfit(relief[on], depth_stereo[on], 1)
    depth_sfs = a * relief + b
    timings['sfs'] = time.perf_counter() - t

    t = time.perf_counter()
    stereo_on_surface = np.where(on, depth_stereo, np.nan)
    filled = np.where(surface, depth_sfs, np.nanmean(depth_sfs))
    if config.fusion == 'shading_refine':
        model = ShadingModel(light, config.albedo, config.ambient, config.roughness)
        fused = refine_depth(left, stereo_on_surface, surface, small.P_left[:3, :3], model,
                             sigma_i=config.refine_shading_sigma,
                             sigma_z=config.refine_stereo_sigma,
                             curvature_sigma=config.refine_curvature_sigma,
                             finest_steps=config.refine_finest_steps).depth
    elif config.fusion == 'mlp_rows':
        rng = rng if rng is not None else np.random.default_rng(config.seed)
        fused = fusion_cores.fuse_mlp_rows(filled, stereo_on_surface, rng,
                                           epochs=config.mlp_epochs).depth
    elif config.fusion == 'least_squares':
        fused = fusion_cores.fuse_least_squares(filled, stereo_on_surface,
                                                config.fusion_weight)
    else:
        fused = fusion_cores.fuse_local_affine(depth_sfs, stereo_on_surface,
                                               config.fusion_sigma)
    fused = np.where(surface, fused, np.nan)
    timings['fusion'] = time.perf_counter() - t
    timings['total'] = time.perf_counter() - started
    return DepthResult(disparity.astype(np.float32), depth_stereo.astype(np.float32),
                       depth_sfs.astype(np.float32), fused.astype(np.float32), surface,
                       small.focal_px, small.baseline_m, small.P_left, _valid_window(valid),
                       density, timings)
