"""One stereo pair -> disparity, sparse stereo depth, SFS depth, fused depth (chapter 5
pipeline, ALGORITHMS.md §4.6), shared by the node, the tests and the bench. No rclpy.

Everything lives in the rectified LEFT frame (ROS convention; the thesis's choice of the
right image as reference is internal to it), at the processing resolution: the rectified
full-resolution images averaged over ``downsample`` x ``downsample`` blocks.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from sfs_stereo_node import fusion as fusion_cores
from sfs_stereo_node import thesis
from sfs_stereo_node.rectify import (
    RectifiedPair,
    light_in_rectified_frame,
    rectified_valid_mask,
    rectify,
    scaled_pair,
)
from sfs_stereo_node.sfs import light_gradient, sfs_depth
from sfs_stereo_node.shading_refine import ShadingModel, ShadingModelMismatch, refine_depth
from sfs_stereo_node.stereo import (
    coherent_matches,
    depth_from_disparity,
    histogram_line_fit,
    match_correlation,
    match_pyramid,
    noise_sigma,
    reduce_disparity,
    refine_subpixel,
    sgbm_disparity,
    window_std,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.settings import setting

FUSIONS = ('shading_refine', 'local_affine', 'least_squares', 'mlp_rows')
STEREOS = ('sgbm', 'ssd')
SFS_MAX_WIDTH = 160  # [px] widest grid SFS runs on
# Least correlation of the windows a semi-global match pairs: unrelated windows reach
# about 1 / block side (0.2 for 5 px); true matches under noise and gain differences
# keep above 0.8 where the texture gate lets them through.
MIN_CORRELATION = 0.5
# Least share of the textured pixels whose semi-global match passes the checks on a pair
# of one scene (Aloe 0.71, the default scene 0.24 at 640x480; two noise images 0.002).
SGBM_MIN_SUPPORT = 0.05


def _odd(value: int) -> str | None:
    return None if value % 2 else 'must be odd'


def _check_light(value: tuple[float, ...] | list[float]) -> str | None:
    if len(value) != 3 or not np.all(np.isfinite(value)) or np.linalg.norm(value) == 0:
        return 'expected 3 finite numbers, not all zero'
    if value[2] >= 0:
        return 'z must be < 0 (the light must be on the camera side of the surface)'
    return None


@dataclass(frozen=True)
class DepthConfig:
    """Processing settings: the one source of sfs_stereo_node's parameters of these names
    (the advanced ones grouped by the stage they tune: ``texture_snr`` is
    ``ssd.texture_snr``). Every threshold is relative to the image, so the defaults hold
    across resolutions, contrast and noise."""

    # What a user sets for a scene.
    light_direction: tuple[float, float, float] = setting(
        (-0.23, -0.70, -0.67),
        'Unit vector surface -> light in the LEFT optical frame (x right, y down, z '
        "forward; the default scenario's light); rotated by R_left into the rectified "
        'frame; z must be < 0.',
        check=_check_light,
    )
    albedo: float = setting(
        0.8, 'Surface albedo: grey = 255 albedo (R + ambient).', range=(0.01, 1.0)
    )
    ambient: float = setting(0.08, 'Ambient light as a fraction of the source.', range=(0.0, 1.0))
    roughness: float = setting(0.3, 'Oren-Nayar sigma.', unit='rad', range=(0.0, 1.5))
    min_depth: float = setting(
        0.0,
        'Nearest surface depth the rig sees; unbounded by default: a user who knows the '
        'depth band narrows the search to d = f b / Z (+ offset) inside it (a best match '
        "on the band's edge is rejected); 0 = no limit.",
        unit='m',
        range=(0.0, 100.0),
    )
    max_depth: float = setting(
        0.0, 'Farthest surface depth; 0 = no limit.', unit='m', range=(0.0, 1000.0)
    )
    fusion: str = setting(
        'shading_refine',
        'Fusion of SFS and stereo: shading_refine (ours, variational shading refinement), '
        'mlp_rows (the thesis: per-row networks), local_affine, least_squares.',
        choices=FUSIONS,
    )
    stereo: str = setting(
        'sgbm',
        'Matcher: sgbm (semi-global matching at full resolution: OpenCV StereoSGBM, '
        'left-right checked, texture-gated, see Method) or ssd (the thesis normalised '
        'SSD, our matcher).',
        choices=STEREOS,
    )
    downsample: int = setting(
        2, 'Processing (and output) resolution = rectified image / this.', range=(1, 8)
    )
    min_intensity: float = setting(
        30.0,
        'Darker pixels are no surface (background, shadow): NaN in the depth images '
        '[grey levels 0..255].',
        range=(0.0, 255.0),
    )
    max_pixels: int = setting(
        4_194_304,
        'Images with more pixels are refused before any conversion or allocation (memory '
        'bound; a 4000x3000 pair is refused at once).',
        range=(64, 100_000_000),
    )
    # The matcher's search.
    window: int = setting(
        3, 'SSD window side (3 = thesis); odd.', unit='px', range=(1, 15), check=_odd
    )
    sgbm_block_size: int = setting(
        5,
        "stereo sgbm: the matched block's side, odd.",
        unit='px at full resolution',
        range=(1, 21),
        check=_odd,
        name='sgbm.block_size',
    )
    max_disparity: int = setting(
        0,
        'Largest offset-corrected disparity searched; 0 = a quarter of the image extent '
        'along the baseline (surfaces nearer than 4 f b / width need a larger value).',
        unit='px at full resolution',
        range=(0, 4096),
    )
    min_disparity: int = setting(
        0, 'Smallest disparity searched.', unit='px at full resolution', range=(0, 1023)
    )
    match_threshold: float = setting(
        0.02,
        'Largest normalised SSD cost of a confident match (sigma_thr; the cost is already '
        'normalised by the window energies).',
        range=(1e-6, 10.0),
    )
    # Advanced, grouped by the stage they tune.
    texture_snr: float = setting(
        2.5,
        "(both matchers) Least window std of a match in units of the image's own noise "
        "std (estimated per image over its flattest quarter, Immerkaer's mask): contrast- "
        'and resolution-relative; 0 disables.',
        range=(0.0, 100.0),
        name='ssd.texture_snr',
    )
    min_texture: float = setting(
        0.0,
        'Absolute floor under texture_snr [grey levels]; 0 disables.',
        range=(0.0, 255.0),
        name='ssd.min_texture',
    )
    uniqueness: float = setting(
        0.02,
        'The best cost must be this fraction below the best cost more than 1 px away; 0 disables.',
        range=(0.0, 0.99),
        name='ssd.uniqueness',
    )
    left_right_check: bool = setting(
        True,
        'Keep only matches the right image picks back (within 1 px).',
        name='ssd.left_right_check',
    )
    min_support: float = setting(
        0.3,
        'Fraction of matches backed by their neighbours below which the pair looks '
        'unmatched (a warning).',
        range=(0.0, 1.0),
        name='ssd.min_support',
    )
    sfs_iterations: int = setting(
        150, 'Jacobi-Newton iterations of SFS.', range=(1, 5000), name='sfs.iterations'
    )
    sfs_max_step: float = setting(
        0.5,
        'Largest SFS height step per iteration (damping).',
        unit='px units',
        range=(0.01, 100.0),
        name='sfs.max_step',
    )
    sfs_downsample: int = setting(
        2,
        'SFS runs on the processing grid reduced by this factor (speed).',
        range=(1, 8),
        name='sfs.downsample',
    )
    refine_shading_sigma: float = setting(
        2.0,
        'shading_refine: image noise + model error.',
        unit='grey levels',
        range=(0.01, 100.0),
        name='refine.shading_sigma',
    )
    refine_stereo_sigma: float = setting(
        0.002,
        'shading_refine: stereo depth noise.',
        unit='m',
        range=(1e-5, 1.0),
        name='refine.stereo_sigma',
    )
    refine_curvature_sigma: float = setting(
        1e-4,
        "shading_refine: thin-plate prior, the std of the depth's second differences.",
        unit='m/px^2 at the output resolution',
        range=(1e-7, 1.0),
        name='refine.curvature_sigma',
    )
    refine_finest_steps: int = setting(
        1,
        'shading_refine: Gauss-Newton steps on the full grid (0 = stop at the '
        'half-resolution level: faster, ~1 mm worse).',
        range=(0, 20),
        name='refine.finest_steps',
    )
    mlp_epochs: int = setting(
        500, 'Training epochs of mlp_rows.', range=(1, 100000), name='mlp_rows.epochs'
    )
    seed: int = setting(
        0,
        'Seed of the mlp_rows network initialisation.',
        range=(0, 2**31 - 1),
        name='mlp_rows.seed',
    )
    fusion_sigma: float = setting(
        12.0,
        'local_affine: neighbourhood.',
        unit='px',
        range=(1.0, 500.0),
        name='local_affine.sigma',
    )
    fusion_weight: float = setting(
        1.0, 'least_squares: gradient weight.', range=(1e-6, 1e6), name='least_squares.weight'
    )
    full_band_layers: int = 24  # wider bands are searched on a halved image first


Float32Array = npt.NDArray[np.float32]


class DepthResult(NamedTuple):
    """What :func:`process_pair` made of one pair, in the rectified left frame at
    processing resolution (h, w): disparity, the depth maps [m], the camera, the match
    density, the stage timings and why the result is less than asked for."""

    disparity: Float32Array  # (h, w) [px at processing resolution], NaN = no match;
    # the offset-corrected disparity of /stereo/disparity: Z = focal b / disparity
    depth_stereo: Float32Array  # (h, w) [m], NaN where no confident match
    depth_sfs: Float32Array | None  # (h, w) [m], SFS mapped affinely onto the stereo
    # depths; None when there are too few matches to scale it
    depth_fused: Float32Array | None  # (h, w) [m], NaN where no surface; None: no fusion
    surface: npt.NDArray[np.bool_]  # (h, w), where the surface is seen
    focal_px: float  # at processing resolution
    baseline_m: float
    P: FloatArray  # (3, 4) rectified left projection at processing resolution
    valid_window: tuple[int, int, int, int]  # (x, y, w, h) of fully valid rectified pixels
    density: float  # confident matches / surface pixels
    timings: dict[str, float]  # stage -> seconds
    left_rect: npt.NDArray[np.uint8]  # (h, w), the rectified left image matched
    fusion: str = ''  # the fusion that made depth_fused ('' = none)
    warnings: tuple[str, ...] = ()  # why the result is less than asked for (fallbacks, doubts)
    confidence: dict[str, float] = {}  # per-frame match quality (README: diagnostics)
    # (h, w) in [0, 1], NaN off the surface: how much of depth_fused stereo measured (1 on
    # a confident match, falling off with the distance to the nearest one, 1/e at 2 % of
    # the image width: there shading alone carries the depth); None with depth_fused None
    depth_confidence: Float32Array | None = None
    # the offset-corrected disparities searched [px at processing resolution] and the
    # matcher's disparity step: DisparityImage's min/max_disparity and delta_d
    disparity_range: tuple[float, float] = (0.0, 0.0)
    disparity_step: float = 0.0


def to_grey(image: npt.ArrayLike) -> Float32Array:
    """(H, W) or (H, W, 3) image -> float32 grey levels scaled to 0..255."""
    image = np.asarray(image)
    scale = 255.0 / 65535.0 if image.dtype == np.uint16 else 1.0
    if image.ndim == 3:
        image = cv2.cvtColor(image.astype(np.float32), cv2.COLOR_RGB2GRAY)
    return image.astype(np.float32) * scale


def _coarser(image: np.ndarray, k: int) -> np.ndarray:
    """``image`` averaged over k x k blocks (the rows and columns past the last whole
    block dropped); itself for k = 1."""
    if k == 1:
        return image
    h, w = image.shape[0] // k, image.shape[1] // k
    return cv2.resize(image[: h * k, : w * k], (w, h), interpolation=cv2.INTER_AREA)


def _valid_window(mask: npt.NDArray[np.bool_]) -> tuple[int, int, int, int]:
    rows, cols = np.flatnonzero(mask.all(axis=1)), np.flatnonzero(mask.all(axis=0))
    if not len(rows) or not len(cols):
        return (0, 0, 0, 0)
    return (int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1))


def _oriented(image: np.ndarray, pair: RectifiedPair) -> np.ndarray:
    """The image seen so that the baseline runs along the rows with the right camera
    on the right (``RectifiedPair.transpose``, ``mirror``); its own inverse swapped:
    ``_unoriented``."""
    image = image.T if pair.transpose else image
    return np.ascontiguousarray(image[:, ::-1] if pair.mirror else image)


def _unoriented(image: np.ndarray, pair: RectifiedPair) -> np.ndarray:
    image = image[:, ::-1] if pair.mirror else image
    return np.ascontiguousarray(image.T if pair.transpose else image)


def max_disparity(pair: RectifiedPair, config: DepthConfig, factor: int) -> float:
    """The largest offset-corrected disparity searched [px at the resolution ``factor`` x
    coarser than full]: ``config.max_disparity``, or when 0 a quarter of the image's
    extent along the baseline (OpenCV's samples search a fixed fraction of the width: no
    rig's depth band is assumed; a nearer surface needs a larger max_disparity)."""
    if config.max_disparity > 0:
        return config.max_disparity / factor
    along_baseline = pair.size[1] if pair.transpose else pair.size[0]
    return float(np.ceil(along_baseline / 4))


def disparity_band(pair: RectifiedPair, config: DepthConfig, factor: int) -> tuple[int, int]:
    """Integer raw disparities (lo, hi) to search on ``pair`` (``factor`` x coarser than
    full resolution): the offset-corrected [min_disparity, max_disparity] narrowed to the
    depth band [min_depth, max_depth] when one is set (Z = f b / (d - offset)), one layer
    of margin each side."""
    fb = pair.focal_px * pair.baseline_m
    d_max = max_disparity(pair, config, factor)
    d_min = config.min_disparity / factor
    if config.min_depth > 0:
        d_max = min(d_max, fb / config.min_depth)
    if config.max_depth > 0:
        d_min = max(d_min, fb / config.max_depth)
    if not d_min < d_max:
        raise InvalidInput(
            f'empty disparity band: {d_min:.1f}..{d_max:.1f} px (check '
            'min/max_disparity against min/max_depth)',
            key='max_disparity',
        )
    offset = pair.disparity_offset
    return int(np.floor(offset + d_min)) - 1, int(np.ceil(offset + d_max)) + 1


def check_size(width: int, height: int, config: DepthConfig) -> None:
    """Refuses, before any work, images whose pixels or whose matching memory (a few
    float32 images per pixel plus the coarsest level's band) exceed the bounds."""
    if width * height > config.max_pixels:
        raise InvalidInput(
            f'image {width}x{height} has {width * height} pixels, more than '
            f'max_pixels {config.max_pixels}',
            key='size',
            value=(width, height),
        )


class _RawMatches(NamedTuple):
    """One matcher's disparities in the oriented frame (raw: offset included; NaN = no
    match), its support (the matcher's measure of how much of the pair matched), the
    matcher's entries of ``DepthResult.confidence`` and, when the support says the
    images are no pair of one scene, why ('' otherwise)."""

    disparity: FloatArray
    support: float
    confidence: dict[str, float]
    unmatched: str


class _StereoDepth(NamedTuple):
    """The stereo stage's disparity (offset-corrected, [px]) and depth [m] on the
    surface, NaN where no confident match, the matches' density over the surface and the
    match-quality entries of ``DepthResult.confidence`` (density included)."""

    disparity: FloatArray
    depth: FloatArray
    density: float
    confidence: dict[str, float]
    searched: tuple[float, float]  # offset-corrected disparities [px, processing grid]
    step: float  # the matcher's disparity resolution [px, processing grid]
    unmatched: bool  # the matches look like no pair of one scene: no depth scale from them


def process_pair(
    left_raw: npt.ArrayLike,
    right_raw: npt.ArrayLike,
    pair: RectifiedPair,
    raw_size: tuple[int, int],
    config: DepthConfig,
    rng: np.random.Generator | None = None,
    want_sfs: bool = True,
) -> DepthResult:
    """Run the pipeline on one raw pair of grey images (2-D arrays, 0..255).

    ``pair`` a full-resolution ``RectifiedPair``; ``raw_size`` (width, height) of the raw
    images. Raises InvalidInput when the pair gives nothing (no surface, or the same
    image twice); otherwise returns what exists: with too few stereo matches depth_sfs
    and depth_fused are None, and when the chosen fusion cannot start a fallback fills
    depth_fused; each such case adds its reason to ``warnings``. ``want_sfs`` False: the
    Tsai-Shah depth is computed only when the fusion needs it (shading_refine does not;
    depth_sfs is then None), a third of the time at 320x240.
    """
    timings: dict[str, float] = {}
    warnings: list[str] = []
    started = time.perf_counter()
    check_size(*raw_size, config)
    factor = int(config.downsample)
    small = scaled_pair(pair, factor)
    rectified = _rectify_pair(left_raw, right_raw, pair, small, raw_size, factor)
    left, valid = rectified.left, rectified.valid
    surface = _seen_surface(left, valid, config.min_intensity)
    _check_distinct(left_raw, right_raw)
    timings['rectify'] = time.perf_counter() - started

    t = time.perf_counter()
    stereo = _stereo_depth(rectified, pair, small, surface, config, factor, warnings)
    matched = np.isfinite(stereo.depth)
    timings['stereo'] = time.perf_counter() - t
    result = DepthResult(
        disparity=stereo.disparity.astype(np.float32),
        depth_stereo=stereo.depth.astype(np.float32),
        depth_sfs=None,
        depth_fused=None,
        surface=surface,
        focal_px=small.focal_px,
        baseline_m=small.baseline_m,
        P=small.P_left,
        valid_window=_valid_window(valid),
        density=stereo.density,
        timings=timings,
        confidence=stereo.confidence,
        left_rect=np.clip(np.rint(left), 0, 255).astype(np.uint8),
        disparity_range=(max(stereo.searched[0], 0.0), stereo.searched[1]),
        disparity_step=stereo.step,
    )
    if matched.sum() < 8 or stereo.unmatched:
        warnings.append(
            f'only {int(matched.sum())} confident stereo matches: nothing '
            'fixes the depth scale, no SFS or fused depth'
            if matched.sum() < 8
            else 'no SFS or fused depth: the stereo matches fix no depth scale'
        )
        timings['total'] = time.perf_counter() - started
        return result._replace(warnings=tuple(warnings))

    light = light_in_rectified_frame(config.light_direction, pair.R_left)
    on = matched & surface
    sfs_depth_m: list[np.ndarray] = []

    def depth_sfs() -> np.ndarray:
        """The Tsai-Shah relief mapped onto the stereo depths, computed once."""
        if not sfs_depth_m:
            t = time.perf_counter()
            relief = _sfs_relief(left, surface, light, small.size, config)
            sfs_depth_m.append(_scaled_to_stereo(relief, stereo.depth, on))
            timings['sfs'] = time.perf_counter() - t
        return sfs_depth_m[0]

    if want_sfs or config.fusion != 'shading_refine':
        depth_sfs()
    sfs_in_fusion = not sfs_depth_m  # a fallback fusion may still ask for it
    t = time.perf_counter()
    fused, fusion = _fused_depth(
        left, stereo.depth, on, surface, depth_sfs, small, light, config, rng, warnings
    )
    confidence = stereo_confidence(on, surface)
    stereo.confidence['fused backed by stereo'] = float(
        (confidence[surface] >= np.exp(-1.0)).mean()
    )
    timings['fusion'] = time.perf_counter() - t - sfs_in_fusion * timings.get('sfs', 0.0)
    timings['total'] = time.perf_counter() - started
    return result._replace(
        depth_sfs=sfs_depth_m[0].astype(np.float32) if sfs_depth_m else None,
        depth_fused=fused.astype(np.float32),
        depth_confidence=confidence,
        fusion=fusion,
        warnings=tuple(warnings),
    )


class _Rectified(NamedTuple):
    """The rectified pair as float32 grey images, at full and at processing resolution,
    and the (h, w) mask of processing pixels both raw images see."""

    left_full: Float32Array
    right_full: Float32Array
    left: Float32Array
    right: Float32Array
    valid: npt.NDArray[np.bool_]


def _rectify_pair(
    left_raw: npt.ArrayLike,
    right_raw: npt.ArrayLike,
    pair: RectifiedPair,
    small: RectifiedPair,
    raw_size: tuple[int, int],
    factor: int,
) -> _Rectified:
    """The raw pair rectified by the full-resolution ``pair`` and averaged down to
    ``small`` (the pair at processing resolution, ``factor`` x coarser)."""
    w, h = small.size
    full = [
        rectify(to_grey(raw), maps).astype(np.float32)
        for raw, maps in ((left_raw, pair.maps_left), (right_raw, pair.maps_right))
    ]
    left, right = (_coarser(image, factor) for image in full)
    valid = rectified_valid_mask(small.maps_left, raw_size) & rectified_valid_mask(
        small.maps_right, raw_size
    )
    if small.maps_left is None:
        valid = np.ones((h, w), dtype=bool)
    return _Rectified(full[0], full[1], left, right, valid)


def _check_distinct(left_raw: npt.ArrayLike, right_raw: npt.ArrayLike) -> None:
    """Refuses a pair whose two images are the same (one camera's image published on
    both topics, a common wiring mistake): a few spurious matches on it would scale a
    fused depth that no stereo measured. Two cameras never see the same pixels exactly;
    the bound, a mean difference of a quarter grey level, lies below any sensor's noise.
    On the raw images: rectification resamples each by its own camera's maps."""
    difference = float(np.mean(np.abs(to_grey(left_raw) - to_grey(right_raw))))
    if difference < 0.25:
        raise InvalidInput(
            f'left and right images are the same (mean difference {difference:.2f} grey '
            'levels): is one camera published on both topics?',
            key='image',
        )


def _seen_surface(
    left: Float32Array, valid: npt.NDArray[np.bool_], min_intensity: float
) -> npt.NDArray[np.bool_]:
    """(h, w) mask of the surface: pixels of the rectified left image brighter than
    ``min_intensity`` (holes closed), away from the invalid border. Raises InvalidInput
    when fewer than 16 pixels are left."""
    surface = cv2.morphologyEx(
        (left > min_intensity).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)
    ).astype(bool)
    surface &= cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if surface.sum() < 16:
        raise InvalidInput(
            f'no surface seen: fewer than 16 pixels brighter than min_intensity {min_intensity:g}',
            key='image',
        )
    return surface


def _stereo_depth(
    rectified: _Rectified,
    pair: RectifiedPair,
    small: RectifiedPair,
    surface: npt.NDArray[np.bool_],
    config: DepthConfig,
    factor: int,
    warnings: list[str],
) -> _StereoDepth:
    """Disparity and depth of the confident matches on the surface, by ``config.stereo``
    over the disparity band; adds a warning to ``warnings`` when the matches look like
    no pair of one scene (too few backed by their neighbours)."""
    if config.stereo == 'sgbm':  # at full resolution, reduced to the processing grid
        d_lo, d_hi = disparity_band(pair, config, 1)
        searched = (
            (d_lo - pair.disparity_offset) / factor,
            (d_hi - pair.disparity_offset) / factor,
        )
        step = 1.0 / 16.0 / factor  # SGBM's sixteenth of a pixel
        raw = _sgbm_matches(
            _oriented(rectified.left_full, pair),
            _oriented(rectified.right_full, pair),
            d_lo,
            d_hi,
            factor,
            config,
        )
    else:
        d_lo, d_hi = disparity_band(small, config, factor)
        searched = (d_lo - small.disparity_offset, d_hi - small.disparity_offset)
        step = 0.1  # the parabola's sub-pixel refinement, about a tenth of a pixel
        raw = _ssd_matches(
            _oriented(rectified.left, small), _oriented(rectified.right, small), d_lo, d_hi, config
        )
    confidence = {**raw.confidence, 'match support': raw.support}
    disparity = _unoriented(raw.disparity, small) - small.disparity_offset
    disparity = np.where(surface & (disparity > 0), disparity, np.nan)
    depth = depth_from_disparity(disparity, small.focal_px, small.baseline_m)
    density = float(np.isfinite(depth).sum() / surface.sum())
    confidence['match density'] = density
    if raw.unmatched:
        warnings.append(
            f'pair looks unmatched (noise, or not a pair of one scene): {raw.unmatched}'
        )
    return _StereoDepth(disparity, depth, density, confidence, searched, step, bool(raw.unmatched))


def _sgbm_matches(
    left_o: np.ndarray,
    right_o: np.ndarray,
    d_lo: int,
    d_hi: int,
    factor: int,
    config: DepthConfig,
) -> _RawMatches:
    """Semi-global matching (OpenCV's StereoSGBM, 3-way, left-right checked) of the
    oriented full-resolution pair over the raw band [d_lo, d_hi], its sub-pixel step
    re-estimated by Lucas-Kanade (``refine_subpixel``), kept where the block has
    texture (``texture_snr`` x the image's noise std: SGBM's smoothness otherwise carries
    a disparity across a textureless region, dense but biased), reduced to the
    processing grid (``reduce_disparity``: blocks whose matches agree); NaN within half a
    pixel of the band's ends. Matches no neighbour backs are counted, not removed (the
    speckle filter has done that): their share is the pair's ``support``."""
    block = config.sgbm_block_size
    disparity = sgbm_disparity(
        left_o, right_o, d_hi, block, d_lo, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY, pad_left=True
    )
    with np.errstate(invalid='ignore'):
        disparity[(disparity <= d_lo + 0.5) | (disparity >= d_hi - 0.5)] = np.nan
    texture_floor = max(config.texture_snr * noise_sigma(left_o), config.min_texture)
    textured = window_std(left_o, block) >= texture_floor
    disparity[~textured] = np.nan
    with np.errstate(invalid='ignore'):
        disparity[match_correlation(left_o, right_o, disparity, block) < MIN_CORRELATION] = np.nan
    disparity = refine_subpixel(left_o, right_o, disparity, block)
    # The pair's support: the share of the textured pixels that found a checked match
    # (most, on a pair of one scene; a few chance clusters on unrelated images).
    support = float(np.isfinite(disparity).sum() / max(textured.sum(), 1))
    raw_disparity = reduce_disparity(disparity, factor)
    unmatched = ''
    if support < SGBM_MIN_SUPPORT and np.isfinite(raw_disparity).sum() >= 8:
        unmatched = (
            f'only {100 * support:.1f} % of the textured pixels found a match that '
            f'correlates (a pair of one scene: {100 * SGBM_MIN_SUPPORT:.0f} % or more)'
        )
    return _RawMatches(raw_disparity, support, {}, unmatched)


def _ssd_matches(
    left_o: np.ndarray, right_o: np.ndarray, d_lo: int, d_hi: int, config: DepthConfig
) -> _RawMatches:
    """The thesis's SSD matches of the oriented pair (coarse-to-fine, right image
    normalised onto the left's histogram) that their neighbours back, with the median
    distinctiveness of those and the pyramid's level count as confidence entries."""
    # The thesis normalises the other image onto the reference's histogram (5.2.2).
    # Over the seen surface only: the black borders rectification leaves (or a
    # darker background) would bend the line.
    seen_left = left_o[left_o > config.min_intensity]
    seen_right = right_o[right_o > config.min_intensity]
    alpha, beta = (
        histogram_line_fit(seen_left[None], seen_right[None])
        if min(len(seen_left), len(seen_right)) > 16
        else (1.0, 0.0)
    )
    matches, levels = match_pyramid(
        left_o,
        alpha * right_o + beta,
        d_lo,
        d_hi,
        config.window,
        config.match_threshold,
        config.texture_snr,
        config.min_texture,
        config.uniqueness,
        config.left_right_check,
        config.full_band_layers,
    )
    raw_count = int(np.isfinite(matches.disparity).sum())
    raw_disparity, support = coherent_matches(matches.disparity)
    distinct = matches.distinctiveness[np.isfinite(raw_disparity)]
    confidence: dict[str, float] = {
        'match quality': float(np.median(distinct)) if len(distinct) else 0.0,
        'match levels': levels,
    }
    unmatched = ''
    if support < config.min_support and raw_count >= 8:
        unmatched = (
            f'only {100 * support:.0f} % of the matches are backed by their '
            f'neighbours (min_support {100 * config.min_support:.0f} %)'
        )
    return _RawMatches(raw_disparity, support, confidence, unmatched)


def _sfs_relief(
    left: Float32Array,
    surface: npt.NDArray[np.bool_],
    light: FloatArray,
    size: tuple[int, int],
    config: DepthConfig,
) -> np.ndarray:
    """Tsai-Shah SFS relief of the surface at processing resolution ``size`` (w, h): the
    negated height toward the viewer in pixel units (it grows with depth), NaN off the
    surface."""
    w, h = size
    E = np.clip(left / 255.0 - config.albedo * config.ambient, 0.0, None)
    # Tsai-Shah needs ~grid-width iterations to carry the relief across: a grid of at
    # most SFS_MAX_WIDTH px keeps sfs_iterations (and the per-iteration step, in that
    # grid's pixels) meaning the same at every resolution, and the time bounded.
    k = max(int(config.sfs_downsample), int(np.ceil(w / SFS_MAX_WIDTH)))
    # The height step (sfs_max_step, the damping) is in pixel units of the SFS grid.
    E_grid, surface_grid = _coarser(E, k), _coarser(surface.astype(np.float32), k) > 0.5
    height_grid = sfs_depth(
        E_grid,
        light_gradient(light),
        config.albedo,
        config.roughness,
        config.sfs_iterations,
        tol=1e-4,
        max_step=config.sfs_max_step,
        mask=surface_grid,
    )
    height = (
        k * cv2.resize(height_grid, (w, h), interpolation=cv2.INTER_LINEAR)
        if k > 1
        else height_grid
    )
    # Height toward the viewer, in pixel units: depth grows as height falls.
    return np.where(surface, -height, np.nan)


def _scaled_to_stereo(
    relief: np.ndarray, depth_stereo: np.ndarray, on: npt.NDArray[np.bool_]
) -> np.ndarray:
    """The SFS depth [m]: ``relief`` mapped onto the stereo depths by the least-squares
    line through the pixels ``on`` (confident matches on the surface)."""
    a, b = np.polyfit(relief[on], depth_stereo[on], 1)
    return a * relief + b


def _fused_depth(
    left: Float32Array,
    depth_stereo: np.ndarray,
    on: npt.NDArray[np.bool_],
    surface: npt.NDArray[np.bool_],
    depth_sfs: Callable[[], np.ndarray],
    small: RectifiedPair,
    light: FloatArray,
    config: DepthConfig,
    rng: np.random.Generator | None,
    warnings: list[str],
) -> tuple[np.ndarray, str]:
    """(fused depth [m], NaN off the surface; the fusion that made it): by
    ``config.fusion``, or by local_affine when that cannot run (the reason added to
    ``warnings``). ``depth_sfs`` gives the SFS depth when a fusion needs it."""
    stereo_on_surface = np.where(on, depth_stereo, np.nan)
    fusion = config.fusion
    try:
        fused = _fuse(
            fusion, left, stereo_on_surface, surface, depth_sfs, small, light, config, rng
        )
    except ShadingModelMismatch as error:
        # A textured or non-Lambertian scene: stereo is dense there, shading only misleads
        # (Aloe: fused p90 error 40 % by shading_refine, 13 % from stereo alone).
        warnings.append(f'{fusion} fusion set aside ({error}): fused by stereo_fill instead')
        fusion = 'stereo_fill'
        fused = fusion_cores.fill_from_stereo(stereo_on_surface, surface)
    except InvalidInput as error:
        warnings.append(
            f'{fusion} fusion could not run ({error}): fused depth by local_affine instead'
        )
        fusion = 'local_affine'
        fused = fusion_cores.fuse_local_affine(depth_sfs(), stereo_on_surface, config.fusion_sigma)
    return np.where(surface, fused, np.nan), fusion


def stereo_confidence(on: npt.NDArray[np.bool_], surface: npt.NDArray[np.bool_]) -> Float32Array:
    """(h, w) how much of the fused depth stereo measured, in [0, 1]: 1 on a confident
    match ``on``, exp(-distance / reach) beside, reach 2 % of the image width (at least
    2 px; farther, the shading alone carries the depth), NaN off the ``surface``."""
    reach = max(2.0, 0.02 * on.shape[1])
    distance = cv2.distanceTransform((~on).astype(np.uint8), cv2.DIST_L2, 3)
    return np.where(surface, np.exp(-distance / reach), np.nan).astype(np.float32)


def _fuse(
    fusion: str,
    left: Float32Array,
    stereo_on_surface: FloatArray,
    surface: npt.NDArray[np.bool_],
    depth_sfs: Callable[[], FloatArray],
    small: RectifiedPair,
    light: FloatArray,
    config: DepthConfig,
    rng: np.random.Generator | None,
) -> FloatArray:
    if fusion == 'shading_refine':
        model = ShadingModel(light, config.albedo, config.ambient, config.roughness)
        return refine_depth(
            left,
            stereo_on_surface,
            surface,
            small.P_left[:3, :3],
            model,
            sigma_i=config.refine_shading_sigma,
            sigma_z=config.refine_stereo_sigma,
            curvature_sigma=config.refine_curvature_sigma,
            finest_steps=config.refine_finest_steps,
            search_axis=0 if small.transpose else 1,
        ).depth
    filled = np.where(surface, depth_sfs(), np.nanmean(depth_sfs()))
    if fusion == 'mlp_rows':
        rng = rng if rng is not None else np.random.default_rng(config.seed)
        return thesis.fuse_mlp_rows(filled, stereo_on_surface, rng, epochs=config.mlp_epochs).depth
    if fusion == 'least_squares':
        return fusion_cores.fuse_least_squares(filled, stereo_on_surface, config.fusion_weight)
    return fusion_cores.fuse_local_affine(depth_sfs(), stereo_on_surface, config.fusion_sigma)
