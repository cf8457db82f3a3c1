"""The coding nodes' settings: the one source of their parameters (name, default, unit,
range, description). Both nodes declare ``CodingSettings`` and must agree on its values;
each has its own beside it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from stereo_coding_node import blind, thesis
from vgm_common.settings import setting

METHODS = ('ours', 'thesis')
TRANSPORTS = ('raw', 'compressed')
# As sfs_stereo_node's max_pixels, which bounds the rectified image that is coded: a
# 2048x2048 image at most. Decoding takes about 17 bytes a pixel (a 16000x16000 PNG of
# 249 kB took 4.4 GB), so 70 MB here.
DEFAULT_MAX_PIXELS = 4_194_304


def _two_finite_angles(angles: Sequence[float]) -> str | None:
    if len(angles) != 2:
        return 'needs two angles'
    return None if all(np.isfinite(angles)) else 'angles must be finite'


def _not_empty(value: str) -> str | None:
    return None if value else 'must not be empty'


@dataclass(frozen=True)
class CodingSettings:
    """How the disparity is hidden in the image: the encoder and decoder must agree."""

    method: str = setting(
        'ours',
        'ours = blind keyed QIM in the 8x8 DCT mid band; thesis = ZIG-ZAG + DFrFT + SVD, '
        'non-blind (key_file).',
        choices=METHODS,
    )
    key: str = setting(
        'vgm-stereo',
        'Shared secret of method ours: seeds where and how the bits are hidden (the '
        'slot-to-bit permutation and the QIM dither).',
        check=_not_empty,
    )
    strength: float = setting(
        0.0,
        "Embedding strength; 0 = the method's default. thesis: alpha_w (0.45); ours: QIM "
        'step [grey levels] (28, about 43 dB).',
        range=(0.0, 128.0),
    )
    key_file: str = setting(
        '',
        'method thesis: the side information (.npz: angles, alpha_w, S_f, U_w, V_w, scaling) '
        'the encoder writes (atomically, each frame) and the decoder reads (reloaded when it '
        'changes).',
    )
    frft_angles: tuple[float, ...] = setting(
        thesis.DEFAULT_ANGLES,
        'method thesis: DFrFT angles (a, b) (order 2a/pi: 0.6, 0.8), not given by the '
        'thesis (A6.2).',
        unit='rad',
        check=_two_finite_angles,
    )
    watermark_scale: str = setting(
        'pixels',
        'method thesis: how the disparity becomes the watermark (unstated in the thesis, '
        "A6.7): pixels (unscaled), full_range ([0, 255], ALGORITHMS.md's reading), unit "
        '([0, 1]).',
        choices=thesis.WATERMARK_SCALES,
    )

    @property
    def effective_strength(self) -> float:
        """``strength`` when > 0, else the method's default (thesis: alpha_w; ours: the QIM
        step [grey levels])."""
        if self.strength > 0:
            return self.strength
        return thesis.THESIS_STRENGTH if self.method == 'thesis' else blind.DEFAULT_STEP


@dataclass(frozen=True)
class EncoderSettings:
    """The encoder's own: the JPEG it publishes and how long it pairs its inputs."""

    jpeg_quality: int = setting(
        90, 'JPEG quality of /stereo/coded/image/compressed.', range=(1, 100)
    )
    sync_max_wait: float = setting(
        1.0,
        'An image or disparity without its partner of identical stamp is dropped after '
        'this (counted).',
        unit='s',
        range=(0.01, 60.0),
        read_only=True,
    )


@dataclass(frozen=True)
class DecoderSettings:
    """The decoder's own: what it takes and what its DisparityImage says."""

    transport: str = setting(
        'raw',
        'raw = /stereo/coded/image; compressed = /stereo/coded/image/compressed (JPEG).',
        choices=TRANSPORTS,
        read_only=True,
    )
    focal_px: float = setting(
        0.0, 'f of the decoded DisparityImage (0 = unknown).', unit='px', range=(0.0, 1e6)
    )
    baseline_m: float = setting(
        0.0,
        't (the baseline) of the decoded DisparityImage (0 = unknown).',
        unit='m',
        range=(0.0, 1e3),
    )
    max_pixels: int = setting(
        DEFAULT_MAX_PIXELS,
        'Coded images with more pixels are refused before any decoding, a compressed one '
        'by the size in its PNG/JPEG header (memory bound: a 249 kB PNG can declare '
        "16000x16000); as sfs_stereo_node's max_pixels, which bounds the image that is "
        'coded: raise both together.',
        range=(64, 100_000_000),
    )
