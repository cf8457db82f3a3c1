"""Ours: a blind, keyed stereo image coding that survives JPEG and filtering.

The disparity is coded compactly (``disparity_code``): its median on a grid of
``CELL_PX`` cells, 6 bits each (0 = unknown), between a 1/8-px minimum and maximum, then
a CRC-32, then Reed-Solomon parity (``RS_PARITY_BYTES`` per 255-byte block, correcting
half as many byte errors). The bits are repeated over every 8x8 block's low-mid DCT coefficients
(``BANDS``, the ones JPEG quantises least), each coefficient carrying one copy by dithered
quantisation index modulation (QIM, Chen and Wornell 2001) with step ``step`` [grey
levels]. The key seeds both the slot-to-bit permutation and the dither, so only the key
holder finds the bits; decoding sums soft decisions over the copies, and the CRC tells a
marked image from an unmarked or wrong-key one (false alarm 2^-32 per image).

Nothing but the key and the step is shared: the decoder needs neither the original
image nor the disparity (blind).
"""

from __future__ import annotations

import hashlib
import zlib
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import reedsolo

from stereo_coding_node.errors import CodingError
from vgm_common.geometry import FloatArray

Bits = npt.NDArray[np.uint8]  # (n,) bits, 0 or 1

CELL_PX = 48  # grid cell of the disparity code [px]: the code grows with the image
LEVEL_BITS = 6  # per cell; level 0 marks an unknown cell
RANGE_UNIT_PX = 1.0 / 8.0  # header resolution of the disparity range [px]
HEADER_BITS = 32  # minimum and maximum disparity, 16 bits each in RANGE_UNIT_PX
CRC_BITS = 32
RS_PARITY_BYTES = 20  # corrects 10 byte errors per block: channel BER up to about 1 %
BLOCK = 8
BANDS = ((0, 1), (1, 0), (1, 1))  # (row, col) of the 8x8 DCT: JPEG's finest steps
DEFAULT_STEP = 28.0  # QIM step [grey levels]: MSE 3 * step^2 / 12 / 64, about 43 dB
# Low-pass channels (filters, resizing) shrink the coefficients and shift them off the
# lattice: the decoder also tries the gains of Gaussian blurs of these widths [px].
BLUR_SIGMAS_PX = (0.0, 0.5, 0.7, 0.9, 1.1, 1.3)
MIN_VALID_FRACTION = 0.25  # a cell with fewer known pixels is coded as unknown


@dataclass(frozen=True)
class Detection:
    """What the decoder found. ``found``: the CRC matched. ``confidence``: mean agreement
    of the copies with the decided bits, 1 = clean, about 1/sqrt(copies) for no mark.
    ``raw_ber``: fraction of copies that disagree with the decided bit (channel errors).
    ``disparity_px``: (H, W) float64 [px], NaN where unknown; None when not found."""

    found: bool
    confidence: float
    raw_ber: float
    disparity_px: FloatArray | None = None
    bits: Bits | None = None


def code_grid(shape: tuple[int, ...]) -> tuple[int, int]:
    """(rows, cols) of the disparity code for an image of ``shape`` (H, W)."""
    return max(1, int(np.ceil(shape[0] / CELL_PX))), max(1, int(np.ceil(shape[1] / CELL_PX)))


def payload_bits(shape: tuple[int, ...]) -> int:
    """Number of bits carried in an image of ``shape``, CRC included."""
    return 8 * len(_RS.encode(bytes(_message_bytes(shape))))


def _body_bits(shape: tuple[int, ...]) -> int:
    rows, cols = code_grid(shape)
    return HEADER_BITS + rows * cols * LEVEL_BITS


def _message_bytes(shape: tuple[int, ...]) -> int:
    """Bytes of the body (padded to whole bytes) and its CRC-32."""
    return (_body_bits(shape) + 7) // 8 + CRC_BITS // 8


def disparity_code(disparity_px: npt.ArrayLike) -> Bits:
    """(H, W) disparity [px] (NaN or < 0 unknown) -> payload bits (uint8 0/1), CRC included."""
    d = np.asarray(disparity_px, dtype=float)
    rows, cols = code_grid(d.shape)
    padded = np.full((rows * CELL_PX, cols * CELL_PX), np.nan)
    padded[: d.shape[0], : d.shape[1]] = np.where(np.isfinite(d) & (d >= 0), d, np.nan)
    windows = (
        padded.reshape(rows, CELL_PX, cols, CELL_PX).transpose(0, 2, 1, 3).reshape(rows, cols, -1)
    )
    inside = np.zeros_like(padded, dtype=bool)
    inside[: d.shape[0], : d.shape[1]] = True
    area = inside.reshape(rows, CELL_PX, cols, CELL_PX).sum(axis=(1, 3))
    count = np.isfinite(windows).sum(axis=2)
    # Unknown pixels sort last: the median of the known ones is at (count - 1) / 2.
    ordered = np.sort(windows, axis=2)
    low_i = np.clip((count - 1) // 2, 0, None)
    high_i = np.clip(count // 2, 0, None)
    median = 0.5 * (
        np.take_along_axis(ordered, low_i[..., None], 2)[..., 0]
        + np.take_along_axis(ordered, high_i[..., None], 2)[..., 0]
    )
    cells = np.where((count > 0) & (count >= MIN_VALID_FRACTION * area), median, np.nan)
    valid = np.isfinite(cells)
    low = np.floor(np.nanmin(cells) / RANGE_UNIT_PX) if valid.any() else 0
    high = np.ceil(np.nanmax(cells) / RANGE_UNIT_PX) if valid.any() else 0
    low, high = int(np.clip(low, 0, 65535)), int(np.clip(high, 0, 65535))
    top = 2**LEVEL_BITS - 1
    span = max(high - low, 1) * RANGE_UNIT_PX
    levels = np.where(
        valid, 1 + np.rint((np.nan_to_num(cells) - low * RANGE_UNIT_PX) / span * (top - 1)), 0
    )
    levels = np.clip(levels, 0, top).astype(np.uint16)
    body = np.concatenate(
        [_to_bits(np.array([low, high]), 16), _to_bits(levels.ravel(), LEVEL_BITS)]
    )
    message = np.packbits(body).tobytes() + zlib.crc32(np.packbits(body).tobytes()).to_bytes(
        4, 'big'
    )
    return np.unpackbits(np.frombuffer(bytes(_RS.encode(message)), np.uint8))


def disparity_from_code(bits: npt.ArrayLike, shape: tuple[int, ...]) -> FloatArray | None:
    """Inverse of ``disparity_code``: (H, W) float64 disparity [px], NaN where unknown;
    None if the CRC fails or the header is inconsistent. The cells are interpolated
    bilinearly (weighting cells by the decoded image's grey levels, a joint bilateral
    upsampling, was tried: on textured scenes it doubled the > 2 px errors)."""
    body = _checked_body(bits, shape)
    if body is None:
        return None
    low, high = _from_bits(body[:HEADER_BITS], 16)
    if high < low:
        return None
    rows, cols = code_grid(shape)
    levels = _from_bits(body[HEADER_BITS:], LEVEL_BITS).reshape(rows, cols).astype(float)
    top = 2**LEVEL_BITS - 1
    span = max(high - low, 1) * RANGE_UNIT_PX
    cells = np.where(levels > 0, low * RANGE_UNIT_PX + (levels - 1) / (top - 1) * span, np.nan)
    return _upsample_cells(cells, shape)


def encode(
    image: npt.ArrayLike, disparity_px: npt.ArrayLike, key: str, step: float = DEFAULT_STEP
) -> npt.NDArray[np.uint8]:
    """Embed the disparity code of ``disparity_px`` (H, W) [px] in ``image`` (H, W)
    uint8. Returns the coded (H, W) uint8 image."""
    image = _check_grey(image)
    disparity_px = np.asarray(disparity_px, dtype=float)
    if disparity_px.shape != image.shape:
        raise CodingError(f'disparity {disparity_px.shape} and image {image.shape} differ in size')
    bits = disparity_code(disparity_px)
    blocks, coefficients = _band_coefficients(image)
    slots = _slot_layout(coefficients.shape[:2], bits.size, key)
    values = coefficients.reshape(-1)
    lattice_offset = (slots.dither + 0.5 * bits[slots.bit_of_slot]) * step
    change = step * np.rint((values - lattice_offset) / step) + lattice_offset - values
    # Only the band coefficients change: add their basis functions, scaled.
    blocks = blocks + np.einsum(
        'rcb,bij->ricj', change.reshape(coefficients.shape), _BAND_BASIS, optimize=True
    )
    marked = image.astype(float)
    marked[: blocks.shape[0] * BLOCK, : blocks.shape[2] * BLOCK] = blocks.reshape(
        blocks.shape[0] * BLOCK, blocks.shape[2] * BLOCK
    )
    return np.clip(np.rint(marked), 0, 255).astype(np.uint8)


def decode(image: npt.ArrayLike, key: str, step: float = DEFAULT_STEP) -> Detection:
    """Look for the watermark of ``key`` in ``image`` (H, W) uint8; returns a Detection."""
    image = _check_grey(image)
    n_bits = payload_bits(image.shape)
    _, values = _band_coefficients(image)
    slots = _slot_layout(values.shape[:2], n_bits, key)
    best: tuple[float, Bits, FloatArray] | None = None  # (confidence, bits, soft)
    for sigma in BLUR_SIGMAS_PX:
        gains = np.exp(-0.5 * (sigma * _BAND_FREQUENCIES) ** 2)
        phase = 2.0 * np.pi * ((values / gains).reshape(-1) / step - slots.dither)
        soft = np.cos(phase)  # +1: on the bit-0 lattice, -1: on the bit-1 lattice
        sums = np.bincount(slots.bit_of_slot, weights=soft, minlength=n_bits)
        copies = np.bincount(slots.bit_of_slot, minlength=n_bits)
        bits = (sums < 0).astype(np.uint8)
        confidence = float(np.mean(np.abs(sums) / np.maximum(copies, 1)))
        if best is None or confidence > best[0]:
            best = (confidence, bits, soft)
        if _checked_body(bits, image.shape) is not None:
            best = (confidence, bits, soft)
            break
    assert best is not None  # BLUR_SIGMAS_PX is not empty
    confidence, bits, soft = best
    raw_ber = float(np.mean((soft < 0) != bits[slots.bit_of_slot]))
    disparity = disparity_from_code(bits, image.shape)
    return Detection(
        found=disparity is not None,
        confidence=confidence,
        raw_ber=raw_ber,
        disparity_px=disparity,
        bits=bits,
    )


def decode_rotated(
    image: npt.ArrayLike,
    key: str,
    step: float = DEFAULT_STEP,
    max_degrees: float = 15.0,
    step_degrees: float = 0.1,
) -> tuple[Detection, float]:
    """Resynchronisation for a rotated image: rotate back by every angle of a grid over
    +-``max_degrees`` (the copies only agree within ~0.1 deg of the true angle), keep the
    angle where the copies agree best, and decode there (Reed-Solomon and the CRC still
    decide). Returns (Detection, angle [deg] that undoes the rotation). Exhaustive:
    about 300 soft evaluations, seconds per 640x480 image; for the bench, not the node."""
    image = _check_grey(image)
    H, W = image.shape
    n_bits = payload_bits(image.shape)
    best = (-1.0, 0.0)
    for angle in np.arange(-max_degrees, max_degrees + 1e-9, step_degrees):
        candidate = _rotate(image, angle)
        _, values = _band_coefficients(candidate)
        slots = _slot_layout(values.shape[:2], n_bits, key)
        soft = np.cos(2.0 * np.pi * (values.reshape(-1) / step - slots.dither))
        sums = np.bincount(slots.bit_of_slot, weights=soft, minlength=n_bits)
        agreement = float(np.mean(np.abs(sums)))
        if agreement > best[0]:
            best = (agreement, float(angle))
    return decode(_rotate(image, best[1]), key, step), best[1]


def _rotate(image: np.ndarray, degrees: float) -> np.ndarray:
    H, W = image.shape
    M = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), degrees, 1.0)
    return cv2.warpAffine(image, M, (W, H), flags=cv2.INTER_LINEAR, borderValue=0)


def copies_per_bit(shape: tuple[int, ...]) -> int:
    """Copies of each payload bit an (H, W) image carries (the smallest count)."""
    slots = (shape[0] // BLOCK) * (shape[1] // BLOCK) * len(BANDS)
    return slots // payload_bits(shape)


# --- internals ------------------------------------------------------------------------

_BAND_ROWS = np.array([b[0] for b in BANDS])
_BAND_COLS = np.array([b[1] for b in BANDS])
# Radian frequency of each band's DCT basis function, for the blur gains.
_BAND_FREQUENCIES = np.pi / BLOCK * np.hypot(_BAND_ROWS, _BAND_COLS)


def _dct_matrix(n: int = BLOCK) -> FloatArray:
    k = np.arange(n)
    D = np.sqrt(2.0 / n) * np.cos(np.pi * (2 * k[None, :] + 1) * k[:, None] / (2 * n))
    D[0] /= np.sqrt(2.0)
    return D


_DCT = _dct_matrix()


_BAND_BASIS = np.stack([np.outer(_DCT[u], _DCT[v]) for u, v in BANDS])  # (bands, 8, 8)


def _band_coefficients(image: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """(blocks (rows, 8, cols, 8) float64 of the whole 8x8 blocks, their orthonormal DCT
    coefficients of ``BANDS``, (rows, cols, bands))."""
    rows, cols = image.shape[0] // BLOCK, image.shape[1] // BLOCK
    if rows == 0 or cols == 0:
        raise CodingError(f'image {image.shape} is smaller than one {BLOCK}x{BLOCK} block')
    blocks = image[: rows * BLOCK, : cols * BLOCK].astype(float).reshape(rows, BLOCK, cols, BLOCK)
    coefficients = np.einsum('ricj,bij->rcb', blocks, _BAND_BASIS, optimize=True)
    return blocks, coefficients


@dataclass(frozen=True)
class _Slots:
    bit_of_slot: np.ndarray  # (slots,) int64: which payload bit each coefficient carries
    dither: np.ndarray  # (slots,) float64 in [0, 1): the keyed lattice shift, in steps


# (block grid, number of bits, key) -> slots
_SLOT_CACHE: dict[tuple[tuple[int, ...], int, str], _Slots] = {}


def _slot_layout(block_grid: tuple[int, ...], n_bits: int, key: str) -> _Slots:
    """The keyed assignment of coefficients to bits, and the dither (cached)."""
    cache_key = (block_grid, n_bits, key)
    if cache_key not in _SLOT_CACHE:
        n_slots = block_grid[0] * block_grid[1] * len(BANDS)
        if n_slots < n_bits:
            raise CodingError(
                f'an image of {block_grid[0] * BLOCK}x{block_grid[1] * BLOCK} '
                f'px has {n_slots} coefficients for {n_bits} bits'
            )
        seed = int.from_bytes(hashlib.sha256(str(key).encode()).digest()[:8], 'little')
        rng = np.random.default_rng(seed)
        bit_of_slot = np.empty(n_slots, dtype=np.int64)
        bit_of_slot[rng.permutation(n_slots)] = np.arange(n_slots) % n_bits
        slots = _Slots(bit_of_slot=bit_of_slot, dither=rng.uniform(0.0, 1.0, n_slots))
        if len(_SLOT_CACHE) > 32:
            _SLOT_CACHE.clear()
        _SLOT_CACHE[cache_key] = slots
    return _SLOT_CACHE[cache_key]


def _to_bits(values: npt.ArrayLike, width: int) -> Bits:
    values = np.asarray(values, dtype=np.int64)
    return ((values[:, None] >> np.arange(width - 1, -1, -1)) & 1).astype(np.uint8).ravel()


def _from_bits(bits: npt.ArrayLike, width: int) -> npt.NDArray[np.int64]:
    bits = np.asarray(bits, dtype=np.int64).reshape(-1, width)
    return bits @ (1 << np.arange(width - 1, -1, -1))


_RS = reedsolo.RSCodec(RS_PARITY_BYTES)


def _checked_body(bits: npt.ArrayLike, shape: tuple[int, ...]) -> Bits | None:
    """The body bits of a received code word after Reed-Solomon correction, or None if
    it cannot be corrected or its CRC-32 does not match."""
    bits = np.asarray(bits, dtype=np.uint8)
    if bits.size != payload_bits(shape):
        return None
    try:
        message = bytes(_RS.decode(bytearray(np.packbits(bits).tobytes()))[0])
    except reedsolo.ReedSolomonError:
        return None
    body, crc = message[:-4], message[-4:]
    if zlib.crc32(body).to_bytes(4, 'big') != crc:
        return None
    return np.unpackbits(np.frombuffer(body, np.uint8))[: _body_bits(shape)]


def _upsample_cells(cells: FloatArray, shape: tuple[int, ...]) -> FloatArray:
    """Cell values (rows, cols) -> (H, W), NaN where the nearest cell is unknown."""
    H, W = shape
    y = (np.arange(H) + 0.5) / CELL_PX - 0.5
    x = (np.arange(W) + 0.5) / CELL_PX - 0.5
    known = np.isfinite(cells)
    nearest_known = known[np.clip(np.rint(y).astype(int), 0, cells.shape[0] - 1)][
        :, np.clip(np.rint(x).astype(int), 0, cells.shape[1] - 1)
    ]
    filled = np.where(known, cells, np.nanmean(cells) if known.any() else 0.0)
    dense = cv2.resize(filled.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
    return np.where(nearest_known, dense.astype(float), np.nan)


def _check_grey(image: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise CodingError(f'expected an (H, W) uint8 grey image, got {image.dtype} {image.shape}')
    return image
