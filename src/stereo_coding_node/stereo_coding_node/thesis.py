"""The thesis's stereo image coding (chapter 6.5, ALGORITHMS.md §5.3-5.4): the left
image, zig-zag degraded and 2-D DFrFT transformed, carries the disparity map in its
singular values. Non-blind: decoding needs the key (``ThesisKey``) that the encoder
writes to a ``key_file``.

The transmitted image is the *degraded* (zig-zag scrambled) marked image, 8 bits, as
the thesis sends F*; the receiver restores the left image by the inverse scan.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from stereo_coding_node.dfrft import dfrft2, zigzag_degrade, zigzag_restore
from stereo_coding_node.errors import CodingError, KeyFileError
from vgm_common.geometry import FloatArray

THESIS_STRENGTH = 0.45  # alpha_w of (6.5.3)
DEFAULT_ANGLES = (0.6 * np.pi / 2, 0.8 * np.pi / 2)  # (a, b) [rad]: not given (A6.2)
# The disparity-to-watermark scaling is unstated (A6.7): 'pixels' embeds the disparity
# unscaled, 'full_range' scaled to [0, 255] (ALGORITHMS.md's choice), 'unit' to [0, 1]
# (MATLAB's im2double). The bench measures the PSNR of each beside Table 6.2.
WATERMARK_SCALES = ('pixels', 'full_range', 'unit')


@dataclass(frozen=True)
class ThesisKey:
    """The side information of §5.4: angles (a, b) [rad], alpha_w, S_f (r,), U_w (M, r),
    V_w (N, r), and how the disparity was scaled into the watermark (value = offset +
    gain * disparity [px])."""

    angles: tuple[float, ...]
    strength: float
    S_f: np.ndarray
    U_w: np.ndarray
    V_w: np.ndarray
    shape: tuple[int, ...]
    gain: float
    offset: float

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the key as .npz (``numpy.savez``) to ``path``."""
        with open(path, 'wb') as f:
            np.savez(
                f,
                angles=np.asarray(self.angles, float),
                strength=self.strength,
                S_f=self.S_f,
                U_w=self.U_w,
                V_w=self.V_w,
                shape=np.asarray(self.shape, int),
                gain=self.gain,
                offset=self.offset,
            )

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ThesisKey:
        """Read a key written by ``save``; KeyFileError names what is wrong."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                fields = {
                    k: data[k]
                    for k in ('angles', 'strength', 'S_f', 'U_w', 'V_w', 'shape', 'gain', 'offset')
                }
        except FileNotFoundError:
            raise KeyFileError(
                f'key file {path} does not exist', key='key_file', value=str(path)
            ) from None
        except (OSError, ValueError, KeyError, EOFError) as error:
            raise KeyFileError(
                f'key file {path} is not a thesis key (.npz with angles, '
                f'strength, S_f, U_w, V_w, shape, gain, offset): {error}',
                key='key_file',
                value=str(path),
            ) from None
        shape = tuple(int(v) for v in fields['shape'])
        r = min(shape) if len(shape) == 2 else -1
        if (
            len(shape) != 2
            or fields['S_f'].shape != (r,)
            or fields['U_w'].shape != (shape[0], r)
            or fields['V_w'].shape != (shape[1], r)
            or fields['angles'].shape != (2,)
        ):
            raise KeyFileError(
                f'key file {path} has inconsistent array shapes', key='key_file', value=str(path)
            )
        return cls(
            angles=tuple(float(a) for a in fields['angles']),
            strength=float(fields['strength']),
            S_f=fields['S_f'],
            U_w=fields['U_w'],
            V_w=fields['V_w'],
            shape=shape,
            gain=float(fields['gain']),
            offset=float(fields['offset']),
        )


def disparity_to_watermark(
    disparity_px: FloatArray, scale: str
) -> tuple[FloatArray, float, float]:
    """(watermark (M, N) float64, gain, offset): invalid (NaN or < 0) pixels become 0."""
    d = np.where(np.isfinite(disparity_px) & (disparity_px >= 0), disparity_px, 0.0)
    if scale == 'pixels':
        return d.astype(float), 1.0, 0.0
    if scale not in WATERMARK_SCALES:
        raise CodingError(f'watermark scale must be one of {WATERMARK_SCALES}, got {scale!r}')
    low, high = float(d.min()), float(d.max())
    top = 255.0 if scale == 'full_range' else 1.0
    gain = top / (high - low) if high > low else 1.0
    return (d - low) * gain, gain, -low * gain


def encode(
    left: npt.ArrayLike,
    disparity_px: npt.ArrayLike,
    angles: Sequence[float] = DEFAULT_ANGLES,
    strength: float = THESIS_STRENGTH,
    scale: str = 'pixels',
) -> tuple[npt.NDArray[np.uint8], ThesisKey]:
    """Thesis coding, §5.3. ``left``: (M, N) uint8 rectified left image;
    ``disparity_px``: (M, N) disparity [px], NaN or negative where unknown.

    Returns (coded (M, N) uint8: the degraded marked image F*, key ``ThesisKey``)."""
    left = _check_grey(left)
    disparity_px = np.asarray(disparity_px, dtype=float)
    if disparity_px.shape != left.shape:
        raise CodingError(f'disparity {disparity_px.shape} and image {left.shape} differ in size')
    watermark, gain, offset = disparity_to_watermark(disparity_px, scale)
    f = dfrft2(zigzag_degrade(left).astype(float), angles)
    U_f, S_f, V_fh = np.linalg.svd(f, full_matrices=False)
    U_w, S_w, V_wt = np.linalg.svd(watermark, full_matrices=False)
    f_marked = (U_f * (S_f + strength * S_w)) @ V_fh
    coded = dfrft2(f_marked, (-angles[0], -angles[1])).real  # A6.3: the real part
    key = ThesisKey(
        angles=tuple(angles),
        strength=float(strength),
        S_f=S_f,
        U_w=U_w,
        V_w=V_wt.T.copy(),
        shape=left.shape,
        gain=gain,
        offset=offset,
    )
    return np.clip(np.rint(coded), 0, 255).astype(np.uint8), key


def decode(coded: npt.ArrayLike, key: ThesisKey) -> tuple[np.ndarray, FloatArray, FloatArray]:
    """Thesis decoding, §5.4. Returns (left (M, N) uint8 restored by the inverse scan,
    disparity [px] (M, N) float64, extracted singular values S_w^ext (r,))."""
    coded = _check_grey(coded)
    if coded.shape != tuple(key.shape):
        raise KeyFileError(
            f'the key is for {key.shape[0]}x{key.shape[1]} images, the '
            f'coded image is {coded.shape[0]}x{coded.shape[1]}',
            key='key_file',
        )
    S_prime = np.linalg.svd(dfrft2(coded.astype(float), key.angles), compute_uv=False)
    S_extracted = (S_prime - key.S_f) / key.strength
    watermark = (key.U_w * S_extracted) @ key.V_w.T
    disparity = (watermark - key.offset) / key.gain
    return zigzag_restore(coded), disparity, S_extracted


def watermark_singular_values(disparity_px: npt.ArrayLike, scale: str = 'pixels') -> FloatArray:
    """S_w of the watermark made from ``disparity_px`` (the w of (6.6.1))."""
    # (the ignore: float64 in, float64 out; numpy's stubs say any float precision)
    return np.linalg.svd(
        disparity_to_watermark(np.asarray(disparity_px, float), scale)[0], compute_uv=False
    )  # type: ignore[return-value]


def _check_grey(image: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8 or min(image.shape) < 2:
        raise CodingError(f'expected an (M, N) uint8 grey image, got {image.dtype} {image.shape}')
    return image
