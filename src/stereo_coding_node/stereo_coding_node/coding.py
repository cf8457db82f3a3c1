"""The coding nodes' work on one input, without ROS: code a disparity into its image by
the chosen method (and write the thesis method's side information), look for it in a
coded image, and the figures each reports on /diagnostics."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stereo_coding_node import blind, thesis
from stereo_coding_node.errors import CodingError
from stereo_coding_node.inputs import known_disparity
from stereo_coding_node.settings import CodingSettings
from stereo_coding_node.views import synthesise_right
from vgm_common.geometry import FloatArray

Grey = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class Coded:
    """A coded image and what the encoder reports of it."""

    image: Grey  # (H, W) the image carrying the disparity
    figures: dict[str, Any]  # 'psnr [dB]', 'encode [ms]', method ours: payload bits


def encode_image(
    left: Grey,
    disparity_px: npt.ArrayLike,
    min_disparity: float,
    settings: CodingSettings,
    clock: Callable[[], float] = time.perf_counter,
) -> Coded:
    """Hide ``disparity_px`` ((H, W) [px], below ``min_disparity`` unknown, the
    stereo_msgs convention) in ``left`` ((H, W) mono8) by ``settings.method``; method
    thesis also writes its side information to ``settings.key_file``. ``clock`` [s]
    times the coding.

    Raises:
        CodingError: sizes that differ, an unusable disparity (``known_disparity``),
            method thesis without a key_file or one that cannot be written.
    """
    disparity = np.asarray(disparity_px, dtype=float)
    if disparity.shape != left.shape:
        raise CodingError(
            f'disparity {disparity.shape[1]}x{disparity.shape[0]} and image '
            f'{left.shape[1]}x{left.shape[0]} differ in size',
            key='size',
        )
    disparity = known_disparity(disparity, min_disparity)
    started = clock()
    if settings.method == 'thesis':
        if not settings.key_file:
            raise CodingError(
                'method thesis needs key_file (where the side information is written)',
                key='key_file',
            )
        coded, key = thesis.encode(
            left,
            disparity,
            settings.frft_angles,
            settings.effective_strength,
            settings.watermark_scale,
        )
        write_key(key, settings.key_file)
        reference = thesis.zigzag_degrade(left)
    else:
        coded = blind.encode(left, disparity, settings.key, settings.effective_strength)
        reference = left
    elapsed = clock() - started
    mse = float(np.mean((coded.astype(float) - reference) ** 2))
    figures: dict[str, Any] = {
        'psnr [dB]': f'{10 * np.log10(255**2 / max(mse, 1e-12)):.2f}',
        'encode [ms]': f'{1000 * elapsed:.1f}',
    }
    if settings.method == 'ours':
        figures['payload bits'] = blind.payload_bits(left.shape)
        figures['fine payload bits'] = blind.fine_payload_bits(left.shape)  # 0: too small
    return Coded(coded, figures)


def write_key(key: thesis.ThesisKey, path: str) -> None:
    """Write the thesis method's side information to ``path``, whole then renamed: a
    decoder never reads half a key. Raises CodingError naming the file."""
    temporary = f'{path}.tmp{os.getpid()}'
    try:
        key.save(temporary)
        os.replace(temporary, path)
    except OSError as error:
        raise CodingError(
            f'cannot write key_file {path}: {error.strerror}', key='key_file'
        ) from None


class KeyFile:
    """The thesis method's side information, read from ``path`` when first needed and
    again whenever the file changes (its modification time or size)."""

    def __init__(self) -> None:
        # ((path, mtime [ns], size [bytes]), the key read from that file)
        self._cache: tuple[tuple[str, int, int], thesis.ThesisKey] | None = None

    def key(self, path: str) -> thesis.ThesisKey:
        """The key in ``path``.

        Raises:
            CodingError: no path given; KeyFileError: a missing or corrupt file.
        """
        if not path:
            raise CodingError(
                'method thesis needs key_file (written by the encoder)', key='key_file'
            )
        try:
            status = os.stat(path)
            signature: tuple[str, int, int] | None = (path, status.st_mtime_ns, status.st_size)
        except OSError:
            signature = None
        if signature is not None and self._cache and self._cache[0] == signature:
            return self._cache[1]
        key = thesis.ThesisKey.load(path)  # KeyFileError names a missing or corrupt file
        self._cache = None if signature is None else (signature, key)
        return key


@dataclass(frozen=True)
class Decoded:
    """What a coded image held: the watermark found or not and, found, the restored left
    image, the disparity and the right view synthesised from them."""

    found: bool
    figures: dict[str, Any]  # 'watermark', 'confidence', 'decode [ms]', method ours: BER, layer
    left: Grey | None = None  # (H, W)
    disparity_px: FloatArray | None = None  # (H, W) [px], NaN unknown
    right: Grey | None = None  # (H, W)


def decode_image(
    coded: Grey,
    settings: CodingSettings,
    key_file: KeyFile,
    clock: Callable[[], float] = time.perf_counter,
) -> Decoded:
    """Look for the disparity in ``coded`` ((H, W) mono8) by ``settings.method``: ours
    decides by its CRC whether a watermark is there; thesis (non-blind) always extracts
    one, with the key in ``settings.key_file``. ``clock`` [s] times the decoding.

    Raises:
        CodingError: method thesis without a usable key file.
    """
    started = clock()
    disparity: FloatArray | None  # None: no watermark found
    if settings.method == 'thesis':
        left, disparity, _ = thesis.decode(coded, key_file.key(settings.key_file))
        found, confidence, values = True, float('nan'), {}
    else:
        detection = blind.decode(coded, settings.key, settings.effective_strength)
        left, disparity = coded, detection.disparity_px
        found, confidence = detection.found, detection.confidence
        values = {
            'raw bit error rate': f'{detection.raw_ber:.4f}',
            'layer': 'fine' if detection.fine else 'coarse',
        }
    elapsed = clock() - started
    figures = {
        'watermark': 'found' if found else 'none',
        'confidence': f'{confidence:.3f}',
        'decode [ms]': f'{1000 * elapsed:.1f}',
        **values,
    }
    if not found:
        return Decoded(False, figures)
    assert disparity is not None  # found: the watermark carried a disparity
    return Decoded(True, figures, left, disparity, synthesise_right(left, disparity))
