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
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import reedsolo

from stereo_coding_node.errors import CodingError
from vgm_common.geometry import FloatArray

Bits = npt.NDArray[np.uint8]  # (n,) bits, 0 or 1

CELL_PX = 52  # coarse node spacing [px]: as many nodes as 48-px cells had on 640x555
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
# The fine layer: a second, independent code word (own CRC-32 and Reed-Solomon parity)
# carrying the disparity as the least-squares nodes of a bilinear surface on a
# FINE_CELL_PX grid. It rides on a coefficient the coarse layer leaves alone, (0, 2),
# whose JPEG quality-50 step (10) is the finest of the 8x8 table, with a smaller QIM step
# (PSNR cost about 0.9 dB): it survives the channels that leave single copies intact
# (JPEG 50 and better); where it does not decode, the coarse layer's cells are used.
FINE_CELL_PX = 24
FINE_BANDS = ((0, 2),)
FINE_STEP_RATIO = 24.0 / 28.0  # fine QIM step / coarse QIM step


@dataclass(frozen=True)
class Detection:
    """What the decoder found. ``found``: the CRC matched. ``confidence``: mean agreement
    of the copies with the decided bits, 1 = clean, about 1/sqrt(copies) for no mark.
    ``raw_ber``: fraction of copies that disagree with the decided bit (channel errors).
    ``disparity_px``: (H, W) float64 [px], NaN where unknown; None when not found:
    the fine layer's surface when it decoded (``fine``), else the coarse cells.
    ``bits``: the coarse layer's code word as received."""

    found: bool
    confidence: float
    raw_ber: float
    disparity_px: FloatArray | None = None
    bits: Bits | None = None
    fine: bool = False


def code_grid(shape: tuple[int, ...]) -> tuple[int, int]:
    """(rows, cols) of the coarse layer's nodes for an image of ``shape`` (H, W)."""
    return _node_grid(shape, CELL_PX)


def payload_bits(shape: tuple[int, ...]) -> int:
    """Number of bits carried in an image of ``shape``, CRC included."""
    return 8 * len(_RS.encode(bytes(_message_bytes(shape))))


def _body_bits(shape: tuple[int, ...]) -> int:
    rows, cols = code_grid(shape)
    return HEADER_BITS + rows * cols * LEVEL_BITS


def _fine_body_bits(shape: tuple[int, ...]) -> int:
    rows, cols = fine_grid(shape)
    return HEADER_BITS + rows * cols * LEVEL_BITS


def _message_bytes(shape: tuple[int, ...]) -> int:
    """Bytes of the coarse body (padded to whole bytes) and its CRC-32."""
    return _message_bytes_of(_body_bits(shape))


def _message_bytes_of(body_bits: int) -> int:
    return (body_bits + 7) // 8 + CRC_BITS // 8


def disparity_code(disparity_px: npt.ArrayLike) -> Bits:
    """(H, W) disparity [px] (NaN or < 0 unknown) -> the coarse layer's code word (uint8
    0/1): least-squares bilinear nodes every ``CELL_PX`` px (see ``fine_code``), CRC
    and Reed-Solomon parity included."""
    return _seal(_quantised_body(_node_fit(_known_or_nan(disparity_px), CELL_PX)))


def disparity_from_code(bits: npt.ArrayLike, shape: tuple[int, ...]) -> FloatArray | None:
    """Inverse of ``disparity_code``: (H, W) float64 disparity [px], NaN where the
    nearest node is unknown; None if the CRC fails or the header is inconsistent.
    (Weighting by the decoded image's grey levels, a joint bilateral upsampling or a
    guided filter, was tried: on textured scenes it lowered the correlation.)"""
    body = _checked_body(bits, payload_bits(shape), _body_bits(shape))
    nodes = None if body is None else _dequantised(body, code_grid(shape))
    return None if nodes is None else _node_surface(nodes, shape, CELL_PX)


def fine_grid(shape: tuple[int, ...]) -> tuple[int, int]:
    """(rows, cols) of the fine layer's nodes for an image of ``shape`` (H, W)."""
    return _node_grid(shape, FINE_CELL_PX)


def _node_grid(shape: tuple[int, ...], cell_px: int) -> tuple[int, int]:
    return int(np.ceil(shape[0] / cell_px)) + 1, int(np.ceil(shape[1] / cell_px)) + 1


def fine_payload_bits(shape: tuple[int, ...]) -> int:
    """Bits of the fine layer's code word for an image of ``shape``, CRC and parity
    included; 0 when it does not fit in the image's fine coefficients (small images)."""
    rows, cols = fine_grid(shape)
    n_bits = 8 * len(_RS.encode(bytes(_message_bytes_of(_fine_body_bits(shape)))))
    n_slots = (shape[0] // BLOCK) * (shape[1] // BLOCK) * len(FINE_BANDS)
    return n_bits if n_slots >= n_bits else 0


def fine_code(disparity_px: npt.ArrayLike) -> Bits:
    """(H, W) disparity [px] -> the fine layer's code word: the nodes of the bilinear
    surface nearest the disparity in least squares (unknown pixels filled from their
    known neighbours first, so the fit is separable: two small matrix products), 6 bits
    each; a node with less than ``MIN_VALID_FRACTION`` known support is unknown."""
    return _seal(_quantised_body(_node_fit(_known_or_nan(disparity_px), FINE_CELL_PX)))


def fine_disparity_from_code(bits: npt.ArrayLike, shape: tuple[int, ...]) -> FloatArray | None:
    """Inverse of ``fine_code``: (H, W) float64 disparity [px], NaN where the nearest
    node is unknown; None if the CRC fails or the header is inconsistent."""
    n_bits = fine_payload_bits(shape)
    body = _checked_body(bits, n_bits, _fine_body_bits(shape)) if n_bits else None
    nodes = None if body is None else _dequantised(body, fine_grid(shape))
    return None if nodes is None else _node_surface(nodes, shape, FINE_CELL_PX)


def _node_fit(d: FloatArray, cell_px: int) -> FloatArray:
    """Least-squares bilinear nodes every ``cell_px`` of ``d`` (NaN unknown); NaN for a
    node with less than ``MIN_VALID_FRACTION`` known support."""
    known = np.isfinite(d)
    basis_rows, basis_cols = (_hat_basis(n, cell_px) for n in d.shape)
    weights = basis_rows.T @ known.astype(float) @ basis_cols  # known support of each node
    support = basis_rows.sum(axis=0)[:, None] * basis_cols.sum(axis=0)[None, :]
    filled = _filled(d, known, cell_px)
    nodes = np.linalg.pinv(basis_rows) @ filled @ np.linalg.pinv(basis_cols).T
    return np.where(weights >= MIN_VALID_FRACTION * support, np.maximum(nodes, 0.0), np.nan)


def _node_surface(nodes: FloatArray, shape: tuple[int, ...], cell_px: int) -> FloatArray:
    """The bilinear surface of ``nodes`` (NaN unknown) on (H, W) pixels; NaN where the
    nearest node is unknown."""
    basis_rows, basis_cols = (_hat_basis(n, cell_px) for n in shape)
    known = np.isfinite(nodes)
    # Unknown nodes take no part: the known ones' weights are renormalised.
    weight = basis_rows @ known.astype(float) @ basis_cols.T
    surface = basis_rows @ np.where(known, nodes, 0.0) @ basis_cols.T
    nearest = known[np.argmax(basis_rows, axis=1)][:, np.argmax(basis_cols, axis=1)]
    return np.where(nearest, surface / np.maximum(weight, 1e-9), np.nan)


def encode(
    image: npt.ArrayLike,
    disparity_px: npt.ArrayLike,
    key: str,
    step: float = DEFAULT_STEP,
    fine: bool = True,
) -> npt.NDArray[np.uint8]:
    """Embed the disparity code of ``disparity_px`` (H, W) [px] in ``image`` (H, W)
    uint8: the coarse layer, and the fine layer unless ``fine`` is False (the code
    before the fine layer, kept for comparison) or the image is too small for it. Returns the
    coded (H, W) uint8 image."""
    image = _check_grey(image)
    disparity_px = np.asarray(disparity_px, dtype=float)
    if disparity_px.shape != image.shape:
        raise CodingError(f'disparity {disparity_px.shape} and image {image.shape} differ in size')
    return _embed(image, disparity_px, key, step, fine)


def _embed(
    image: npt.NDArray[np.uint8], disparity_px: FloatArray, key: str, step: float, fine: bool
) -> npt.NDArray[np.uint8]:
    blocks, coefficients = _band_coefficients(image)
    change = np.zeros_like(coefficients)
    coarse = len(BANDS)
    change[..., :coarse] = _qim_change(
        coefficients[..., :coarse], disparity_code(disparity_px), key, step
    )
    if fine and fine_payload_bits(image.shape):
        change[..., coarse:] = _qim_change(
            coefficients[..., coarse:],
            fine_code(disparity_px),
            _fine_key(key),
            FINE_STEP_RATIO * step,
        )
    # Only the band coefficients change: add their basis functions, scaled.
    blocks = blocks + np.einsum('rcb,bij->ricj', change, _BAND_BASIS, optimize=True)
    marked = image.astype(float)
    marked[: blocks.shape[0] * BLOCK, : blocks.shape[2] * BLOCK] = blocks.reshape(
        blocks.shape[0] * BLOCK, blocks.shape[2] * BLOCK
    )
    return np.clip(np.rint(marked), 0, 255).astype(np.uint8)


def _qim_change(coefficients: FloatArray, bits: Bits, key: str, step: float) -> FloatArray:
    """The change that moves each coefficient onto the keyed lattice of its bit."""
    slots = _slot_layout(coefficients.shape, bits.size, key)
    values = coefficients.reshape(-1)
    lattice_offset = (slots.dither + 0.5 * bits[slots.bit_of_slot]) * step
    change = step * np.rint((values - lattice_offset) / step) + lattice_offset - values
    return change.reshape(coefficients.shape)


def decode(image: npt.ArrayLike, key: str, step: float = DEFAULT_STEP) -> Detection:
    """Look for the watermark of ``key`` in ``image`` (H, W) uint8; returns a Detection.
    The fine layer's surface is returned when its word decodes, else the coarse cells."""
    image = _check_grey(image)
    shape = image.shape
    _, coefficients = _band_coefficients(image)
    coarse = len(BANDS)
    confidence, bits, raw_ber = _read_word(
        coefficients[..., :coarse],
        payload_bits(shape),
        key,
        step,
        _BAND_FREQUENCIES[:coarse],
        lambda word: _checked_body(word, payload_bits(shape), _body_bits(shape)) is not None,
    )
    disparity = disparity_from_code(bits, shape)
    fine_disparity = None
    n_fine = fine_payload_bits(shape)
    if n_fine:
        _, fine_bits, _ = _read_word(
            coefficients[..., coarse:],
            n_fine,
            _fine_key(key),
            FINE_STEP_RATIO * step,
            _BAND_FREQUENCIES[coarse:],
            lambda word: _checked_body(word, n_fine, _fine_body_bits(shape)) is not None,
        )
        fine_disparity = fine_disparity_from_code(fine_bits, shape)
    return Detection(
        found=disparity is not None or fine_disparity is not None,
        confidence=confidence,
        raw_ber=raw_ber,
        disparity_px=fine_disparity if fine_disparity is not None else disparity,
        bits=bits,
        fine=fine_disparity is not None,
    )


def _read_word(
    coefficients: FloatArray,
    n_bits: int,
    key: str,
    step: float,
    frequencies: FloatArray,
    accept: Callable[[Bits], bool],
) -> tuple[float, Bits, float]:
    """Soft-decode a keyed word of ``n_bits`` from QIM ``coefficients`` (rows, cols,
    bands), trying the gains of ``BLUR_SIGMAS_PX``: the first word ``accept`` takes,
    else the one whose copies agree best. (confidence, bits, raw bit error rate)."""
    slots = _slot_layout(coefficients.shape, n_bits, key)
    copies = np.bincount(slots.bit_of_slot, minlength=n_bits)
    best: tuple[float, Bits, FloatArray] | None = None  # (confidence, bits, soft)
    for sigma in BLUR_SIGMAS_PX:
        gains = np.exp(-0.5 * (sigma * frequencies) ** 2)
        phase = 2.0 * np.pi * ((coefficients / gains).reshape(-1) / step - slots.dither)
        soft = np.cos(phase)  # +1: on the bit-0 lattice, -1: on the bit-1 lattice
        sums = np.bincount(slots.bit_of_slot, weights=soft, minlength=n_bits)
        bits = (sums < 0).astype(np.uint8)
        confidence = float(np.mean(np.abs(sums) / np.maximum(copies, 1)))
        if accept(bits):
            best = (confidence, bits, soft)
            break
        if best is None or confidence > best[0]:
            best = (confidence, bits, soft)
    assert best is not None  # BLUR_SIGMAS_PX is not empty
    confidence, bits, soft = best
    return confidence, bits, float(np.mean((soft < 0) != bits[slots.bit_of_slot]))


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
        _, coefficients = _band_coefficients(candidate)
        values = coefficients[..., : len(BANDS)]
        slots = _slot_layout(values.shape, n_bits, key)
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

_ALL_BANDS = BANDS + FINE_BANDS  # the coefficients read: coarse layer first, then fine
_BAND_ROWS = np.array([b[0] for b in _ALL_BANDS])
_BAND_COLS = np.array([b[1] for b in _ALL_BANDS])
# Radian frequency of each band's DCT basis function, for the blur gains.
_BAND_FREQUENCIES = np.pi / BLOCK * np.hypot(_BAND_ROWS, _BAND_COLS)


def _dct_matrix(n: int = BLOCK) -> FloatArray:
    k = np.arange(n)
    D = np.sqrt(2.0 / n) * np.cos(np.pi * (2 * k[None, :] + 1) * k[:, None] / (2 * n))
    D[0] /= np.sqrt(2.0)
    return D


_DCT = _dct_matrix()


_BAND_BASIS = np.stack([np.outer(_DCT[u], _DCT[v]) for u, v in _ALL_BANDS])  # (bands, 8, 8)


def _band_coefficients(image: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """(blocks (rows, 8, cols, 8) float64 of the whole 8x8 blocks, their orthonormal DCT
    coefficients of ``BANDS`` then ``FINE_BANDS``, (rows, cols, bands))."""
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


# (coefficient array shape (rows, cols, bands), number of bits, key) -> slots
_SLOT_CACHE: dict[tuple[tuple[int, ...], int, str], _Slots] = {}


def _fine_key(key: str) -> str:
    """The fine layer's own key: its permutation and dither are independent."""
    return f'{key}\x00fine'


def _slot_layout(grid: tuple[int, ...], n_bits: int, key: str) -> _Slots:
    """The keyed assignment of the coefficients of a (rows, cols, bands) array to bits,
    and the dither (cached)."""
    cache_key = (grid, n_bits, key)
    if cache_key not in _SLOT_CACHE:
        block_grid = grid[:2]
        n_slots = int(np.prod(grid))
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


def _known_or_nan(disparity_px: npt.ArrayLike) -> FloatArray:
    d = np.asarray(disparity_px, dtype=float)
    return np.where(np.isfinite(d) & (d >= 0), d, np.nan)


def _quantised_body(values: FloatArray) -> Bits:
    """Values [px] (NaN unknown) -> body bits: the 1/8-px range, then ``LEVEL_BITS``
    levels each (0 = unknown)."""
    valid = np.isfinite(values)
    low = np.floor(np.nanmin(values) / RANGE_UNIT_PX) if valid.any() else 0
    high = np.ceil(np.nanmax(values) / RANGE_UNIT_PX) if valid.any() else 0
    low, high = int(np.clip(low, 0, 65535)), int(np.clip(high, 0, 65535))
    top = 2**LEVEL_BITS - 1
    span = max(high - low, 1) * RANGE_UNIT_PX
    levels = np.where(
        valid, 1 + np.rint((np.nan_to_num(values) - low * RANGE_UNIT_PX) / span * (top - 1)), 0
    )
    levels = np.clip(levels, 0, top).astype(np.uint16)
    return np.concatenate(
        [_to_bits(np.array([low, high]), 16), _to_bits(levels.ravel(), LEVEL_BITS)]
    )


def _dequantised(body: Bits, grid: tuple[int, int]) -> FloatArray | None:
    """Inverse of ``_quantised_body``: (rows, cols) values [px], NaN unknown; None if
    the header is inconsistent."""
    low, high = _from_bits(body[:HEADER_BITS], 16)
    if high < low:
        return None
    levels = _from_bits(body[HEADER_BITS:], LEVEL_BITS).reshape(grid).astype(float)
    top = 2**LEVEL_BITS - 1
    span = max(high - low, 1) * RANGE_UNIT_PX
    return np.where(levels > 0, low * RANGE_UNIT_PX + (levels - 1) / (top - 1) * span, np.nan)


def _seal(body: Bits) -> Bits:
    """Body bits -> code word: padded to bytes, CRC-32, Reed-Solomon parity."""
    message = np.packbits(body).tobytes()
    message += zlib.crc32(message).to_bytes(4, 'big')
    return np.unpackbits(np.frombuffer(bytes(_RS.encode(message)), np.uint8))


def _hat_basis(n: int, cell_px: int = FINE_CELL_PX) -> FloatArray:
    """(n, nodes) 1-D bilinear interpolation weights of ``n`` pixels on nodes every
    ``cell_px`` px (node j at pixel coordinate j * cell_px - 0.5)."""
    nodes = int(np.ceil(n / cell_px)) + 1
    position = (np.arange(n) + 0.5) / cell_px
    return np.maximum(0.0, 1.0 - np.abs(position[:, None] - np.arange(nodes)[None, :]))


def _filled(d: FloatArray, known: np.ndarray, cell_px: int = FINE_CELL_PX) -> FloatArray:
    """``d`` with unknown pixels replaced by the mean of the known ones around them
    (normalised box filters of growing size), or by the overall mean where none is."""
    out = np.where(known, d, 0.0).astype(np.float32)
    weight = known.astype(np.float32)
    filled = out.copy()
    missing = ~known
    size = cell_px
    while missing.any() and size <= 4 * max(d.shape):
        sums = cv2.boxFilter(out, -1, (size, size), normalize=False)
        counts = cv2.boxFilter(weight, -1, (size, size), normalize=False)
        reach = missing & (counts > 0.5)
        filled[reach] = sums[reach] / counts[reach]
        missing &= ~reach
        size *= 2
    filled[missing] = float(np.nanmean(d)) if known.any() else 0.0
    return filled.astype(float)


def _checked_body(bits: npt.ArrayLike, n_bits: int, body_bits: int) -> Bits | None:
    """The ``body_bits`` body bits of a received ``n_bits`` code word after Reed-Solomon
    correction, or None if it cannot be corrected or its CRC-32 does not match."""
    bits = np.asarray(bits, dtype=np.uint8)
    if bits.size != n_bits:
        return None
    try:
        message = bytes(_RS.decode(bytearray(np.packbits(bits).tobytes()))[0])
    except reedsolo.ReedSolomonError:
        return None
    body, crc = message[:-4], message[-4:]
    if zlib.crc32(body).to_bytes(4, 'big') != crc:
        return None
    return np.unpackbits(np.frombuffer(body, np.uint8))[:body_bits]


def _check_grey(image: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise CodingError(f'expected an (H, W) uint8 grey image, got {image.dtype} {image.shape}')
    return image
