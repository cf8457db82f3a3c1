"""Checks of the coding nodes' inputs before any work: a disparity as the stereo_msgs
convention defines it, and the size of a compressed image read from its header."""

import io
import struct

import numpy as np
import numpy.typing as npt
from PIL import JpegImagePlugin, PngImagePlugin

from stereo_coding_node.errors import CodingError
from vgm_common.geometry import FloatArray

GREY_ENCODINGS = ('mono8', '8UC1')  # the host image and the coded one: 8-bit grey


def known_disparity(disparity_px: npt.ArrayLike, min_disparity: float) -> FloatArray:
    """The (H, W) disparity [px] to code, unknown pixels NaN.

    By the stereo_msgs convention a value below ``min_disparity`` (or NaN) marks an unknown
    pixel; every other value is a match, and a match is finite and shifts a pixel by at
    most the image width.

    Raises:
        CodingError: ``min_disparity`` is not finite (every comparison with NaN is false:
            each pixel would be unknown, the coded disparity empty), or known values are
            infinite or beyond the image width (coded, they would be clipped and stretch
            the coded range, raising the error of every other cell).
    """
    values = np.array(disparity_px, dtype=float)
    if not np.isfinite(min_disparity):
        raise CodingError(
            f'min_disparity is {min_disparity}: no pixel could be told known or unknown',
            key='min_disparity',
        )
    known = values >= min_disparity  # False for NaN
    width = values.shape[1] if values.ndim == 2 else 0
    absurd = known & ~(np.abs(values) <= width)  # also +inf
    if absurd.any():
        worst = values[absurd][np.argmax(np.abs(values[absurd]))]
        raise CodingError(
            f'{int(absurd.sum())} disparities are not finite or beyond the image width '
            f'{width} px (up to {worst:.4g} px)',
            key='disparity',
        )
    return np.where(known, values, np.nan)


def compressed_image_size(data: bytes) -> tuple[int, int]:
    """(width, height) [px] of a PNG or JPEG image, read from its header without
    decoding it (a few hundred kB can declare gigabytes of pixels).

    Raises:
        CodingError: the data is not a PNG or JPEG image.
    """
    reasons = []
    # Pillow's image classes parse the header on construction and decode nothing until
    # load(); PIL.Image.open would add its own decompression-bomb warning and limit.
    for image_class in (PngImagePlugin.PngImageFile, JpegImagePlugin.JpegImageFile):
        try:
            with image_class(io.BytesIO(data)) as image:
                width, height = image.size
                return int(width), int(height)
        except (SyntaxError, OSError, ValueError, IndexError, struct.error) as error:
            reasons.append(f'{image_class.format}: {error}')
    raise CodingError(
        f'compressed image ({len(data)} bytes) does not decode as JPEG or PNG '
        f'({"; ".join(reasons)})',
        key='data',
    )
