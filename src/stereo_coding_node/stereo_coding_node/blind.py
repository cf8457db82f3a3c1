"""Ours: a blind, keyed stereo image coding that survives JPEG and filtering.

The disparity is coded compactly (``disparity_code``): the least-squares nodes of a
bilinear surface, or of an interpolation guided by the image's grey levels where that
fits better (``_corner_weights``), at the finest spacing whose code fits the word,
quantised with a step near the fit's error, as Exp-Golomb residuals of LOCO-I's median
edge prediction (the known-node mask as run lengths), then a CRC-32, then Reed-Solomon parity
(``RS_PARITY_BYTES`` per 255-byte block, correcting half as many byte errors). The
coarse word's bits are repeated over the 8x8 blocks, each copy a block's pair of low
DCT coefficients (``BANDS``, the ones JPEG quantises least) by spread-transform dither
modulation of their projection (``_pair_change``); the fine word's bits take one
coefficient each (``FINE_BANDS``) by plain dithered quantisation index modulation
(QIM, Chen and Wornell 2001). ``step`` [grey levels] sets how far a coefficient moves.
The key seeds the slot-to-bit permutation, the projections' signs and the dither, so
only the key holder finds the bits; decoding sums soft decisions over the copies, and
the CRC tells a marked image from an unmarked or wrong-key one (false alarm 2^-32 per
image).

Nothing but the key and the step is shared: the decoder needs neither the original
image nor the disparity (blind).
"""

from __future__ import annotations

import functools
import hashlib
import zlib
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import reedsolo
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

from stereo_coding_node.errors import CodingError
from vgm_common.geometry import FloatArray

Bits = npt.NDArray[np.uint8]  # (n,) bits, 0 or 1

# Both layers carry the disparity as the least-squares nodes of a bilinear surface, at
# the finest of NODE_SPACINGS_PX whose compact code (Exp-Golomb residuals of a median
# edge prediction, ``_node_code``) fits the layer's word; the header says which.
NODE_SPACINGS_PX = (8, 9, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 64, 96, 160, 4096)
SPACING_BITS = 4  # index into NODE_SPACINGS_PX
GUIDED_BITS = 1  # 1: the nodes are interpolated with the image's grey levels (``_corner_weights``)
RANGE_UNIT_PX = 1.0 / 8.0  # resolution of the lowest node value and of the step [px]
LOW_BITS = 16  # lowest node value, in RANGE_UNIT_PX
STEP_BITS = 12  # quantisation step of the node values, in RANGE_UNIT_PX
MAX_STEP_PX = (2**STEP_BITS - 1) * RANGE_UNIT_PX
HEADER_BITS = SPACING_BITS + GUIDED_BITS + LOW_BITS + STEP_BITS
# Guided interpolation: within its cell a pixel weighs each of the four corner nodes by
# its bilinear weight times exp(-(g - g_node)^2 / 2 GUIDE_GREY_SCALE^2), g the image
# blurred by GUIDE_BLUR_PX (so JPEG and the mark barely move it) and g_node its value at
# the node: across a grey edge that is also a depth edge, a pixel takes the nodes on its
# own side. The encoder fits the nodes by least squares through these weights, computed
# on the host; the decoder computes them on the image it receives. (Aloe, 14-px nodes,
# no quantisation: RMS 3.74 px bilinear, 3.36 px guided; 12 to 32 grey levels and blurs
# of 0.7 to 1.5 px within 0.05 px of that; the generated scene, whose texture does not
# follow its depth, unchanged.)
GUIDE_BLUR_PX = 1.5
GUIDE_GREY_SCALE = 20.0  # [grey levels]
GUIDE_FLOOR = 1e-6  # least affinity: no pixel loses all four of its nodes
# Least squares of the guided fit: a node that few pixels weigh is held to its
# neighbours by this weight of the squared second differences of the nodes (zero on a
# plane), per pixel of a cell's area.
GUIDED_SMOOTHNESS = 1e-3
GUIDED_FIT_SAMPLE = 2  # the guided fit reads every 2nd row and column (a quarter the time)
# The coarse word's size was set by the header it had before the guided flag.
WORD_HEADER_BITS = 32
# Quantisation step / RMS error of the node fit: adds ~3 % to the fit's RMS error
# (step^2 / 12 = 0.06 fit^2) and saves ~1 bit a node against a step of 1/4 of it.
QUANTISATION_PER_FIT_RMS = 0.85
# Coarser steps tried on the next finer spacing (see ``_compact_body``).
FINER_STEP_FACTORS = tuple(2.0 ** (k / 4) for k in range(1, 9))
# Steps tried for the guided nodes at the chosen spacing, finest first.
GUIDED_STEP_FACTORS = tuple(2.0 ** (k / 8) for k in range(0, 17))
# The guided surface costs the decoder ~35 ms at 640x480 (the bilinear one a few): the
# guided nodes are kept only where they predict this fraction of the bilinear nodes'
# error or less (Aloe's words 0.89-0.90, the generated scenes' fine words 0.99-1.0).
GUIDED_MAX_ERROR_RATIO = 0.97
# The coarse word keeps the size of the 6-bit levels of CELL_PX nodes it had before the
# compact code (~4.5 copies, blocks, a bit); it now holds finer nodes.
CELL_PX = 52
LEVEL_BITS = 6
CRC_BITS = 32
RS_PARITY_BYTES = 20  # corrects 10 byte errors per block: channel BER up to about 1 %
# Least reliable bytes per block tried as erasures when plain decoding fails.
ERASURE_COUNTS = (8, 14, 20)
BLOCK = 8
BANDS = ((0, 1), (1, 0))  # (row, col) of the 8x8 DCT: JPEG's finest steps
# A copy of a coarse bit is a block's pair of BANDS coefficients (spread-transform
# dither modulation, Chen and Wornell 2001): QIM of their projection (c0 +- c1) / sqrt 2
# (keyed sign) with step ``step`` x sqrt 2, so each coefficient moves as much as by QIM
# with ``step`` (MSE step^2 / 12) while the channel's independent errors on the two add
# up only as sqrt 2 against a lattice sqrt 2 wider. The pair lies in one block, so a
# lost block (cropped to one grey level, a rotation's corner, saturated) loses whole
# copies, which are then left out; a bit keeps ~4.5 of them in as many blocks. (Each
# bit's ~9 coefficients as one projection, over as many blocks: Aloe's bit errors after
# the 3x3 median 2.1 % against 5.7 % for pairs, noise of 3 % decoded, but a 25 % crop
# or a rotation's black corners leave no projection whole: not decodable.)
DEFAULT_STEP = 28.0  # QIM step [grey levels] a coefficient: MSE step^2 / 12 / 64 a band
# Low-pass channels (filters, resizing) shrink the coefficients and shift them off the
# lattice: the decoder also tries the gains of Gaussian blurs of these widths [px].
BLUR_SIGMAS_PX = (0.0, 0.5, 0.7, 0.9, 1.1, 1.3)
MIN_VALID_FRACTION = 0.25  # a cell with fewer known pixels is coded as unknown
# The fine layer: a second, independent code word (own CRC-32 and Reed-Solomon parity)
# as large as one copy per coefficient allows, with the same compact node code. It rides
# on the coefficients the coarse layer leaves alone, (0, 2) and (1, 1), whose JPEG
# quality-50 steps (10, 12) are among the finest of the 8x8 table, by plain QIM with
# steps FINE_STEP_RATIOS x ``step`` (24 and 28: JPEG 50's rounding, at most 5 and 6,
# stays within a quarter step): it survives the channels that leave single copies
# intact (JPEG 50 and better); where it does not decode, the coarse layer's word is used.
FILL_WINDOW_PX = 24  # first window [px] of the fill of unknown pixels before the fit
FINE_BANDS = ((0, 2), (1, 1))
FINE_STEP_RATIOS = (24.0 / 28.0, 1.0)  # each fine band's QIM step / ``step``


@dataclass(frozen=True)
class Detection:
    """What the decoder found. ``found``: the CRC matched. ``confidence``: mean agreement
    of the coarse word's copies with the decided bits, 1 = clean, about 1/sqrt(pi copies)
    for no mark (0.28 at ~4.5 copies). ``raw_ber``: fraction of its copies that disagree
    with the decided bit (channel errors).
    ``disparity_px``: (H, W) float64 [px], NaN where unknown; None when not found:
    the fine layer's surface when it decoded (``fine``), else the coarse cells.
    ``bits``: the coarse layer's code word as received."""

    found: bool
    confidence: float
    raw_ber: float
    disparity_px: FloatArray | None = None
    bits: Bits | None = None
    fine: bool = False


def payload_bits(shape: tuple[int, ...]) -> int:
    """Number of bits of the coarse layer's word in an image of ``shape``, CRC and
    parity included (the size of the 6-bit-per-node code of ``CELL_PX`` nodes it
    replaced: ~4.5 copies a bit)."""
    rows, cols = _node_grid(shape, CELL_PX)
    return _sealed_bits(_message_bytes_of(WORD_HEADER_BITS + rows * cols * LEVEL_BITS))


def fine_payload_bits(shape: tuple[int, ...]) -> int:
    """Bits of the fine layer's code word for an image of ``shape``, CRC and parity
    included: as many as its ``FINE_BANDS`` coefficients hold, one copy each; 0 when that is
    no more than the coarse word (the image is too small for a second word to add)."""
    n_slots = (shape[0] // BLOCK) * (shape[1] // BLOCK) * len(FINE_BANDS)
    message_bytes = n_slots // 8
    while message_bytes > 0 and _sealed_bits(message_bytes) > n_slots:
        message_bytes -= 1
    n_bits = _sealed_bits(message_bytes) if message_bytes > CRC_BITS // 8 else 0
    return n_bits if n_bits > payload_bits(shape) else 0


def _sealed_bits(message_bytes: int) -> int:
    """Bits of the Reed-Solomon code word of a ``message_bytes`` message."""
    blocks = -(-message_bytes // (255 - RS_PARITY_BYTES))
    return 8 * (message_bytes + RS_PARITY_BYTES * blocks)


def _body_bits_of(n_bits: int) -> int:
    """Body bits of a sealed word of ``n_bits``: without parity and CRC."""
    blocks = -(-n_bits // (8 * 255))
    return n_bits - 8 * RS_PARITY_BYTES * blocks - CRC_BITS


def _message_bytes_of(body_bits: int) -> int:
    return (body_bits + 7) // 8 + CRC_BITS // 8


def disparity_code(disparity_px: npt.ArrayLike, guide: npt.ArrayLike | None = None) -> Bits:
    """(H, W) disparity [px] (NaN or < 0 unknown) -> the coarse layer's code word (uint8
    0/1) of ``payload_bits``: the compact node code (``_compact_body``) of the finest
    node spacing that fits, CRC and Reed-Solomon parity included. With ``guide`` (the
    (H, W) uint8 host image) the nodes are fitted for the guided interpolation
    (``_corner_weights``), else for the bilinear one."""
    d = _known_or_nan(disparity_px)
    guide = _checked_guide(guide, d.shape)
    return _seal(_compact_body(d, _filled(d), _body_bits_of(payload_bits(d.shape)), guide))


def disparity_from_code(
    bits: npt.ArrayLike, shape: tuple[int, ...], guide: npt.ArrayLike | None = None
) -> FloatArray | None:
    """Inverse of ``disparity_code``: (H, W) float64 disparity [px], NaN where the
    nearest node is unknown; None if the CRC fails or the code is inconsistent.
    ``guide``: the received image, needed by a guided code (CodingError without it).
    (Weighting the decoded nodes by the image's grey levels after the fact, a joint
    bilateral upsampling or a guided filter, lowered the correlation on textured
    scenes; the guided code works because the encoder fits its nodes for the weights.)"""
    body = _checked_body(bits, payload_bits(shape))
    return None if body is None else _compact_surface(body, shape, _checked_guide(guide, shape))


def fine_code(disparity_px: npt.ArrayLike, guide: npt.ArrayLike | None = None) -> Bits:
    """(H, W) disparity [px] -> the fine layer's code word of ``fine_payload_bits``
    (which must not be 0): the same compact node code (``guide`` as in
    ``disparity_code``), with the room of the fine layer's word."""
    d = _known_or_nan(disparity_px)
    n_bits = fine_payload_bits(d.shape)
    if not n_bits:
        raise CodingError(f'an image of {d.shape} is too small for the fine layer')
    guide = _checked_guide(guide, d.shape)
    return _seal(_compact_body(d, _filled(d), _body_bits_of(n_bits), guide))


def fine_disparity_from_code(
    bits: npt.ArrayLike, shape: tuple[int, ...], guide: npt.ArrayLike | None = None
) -> FloatArray | None:
    """Inverse of ``fine_code``: (H, W) float64 disparity [px], NaN where the nearest
    node is unknown; None if the CRC fails or the code is inconsistent."""
    n_bits = fine_payload_bits(shape)
    body = _checked_body(bits, n_bits) if n_bits else None
    return None if body is None else _compact_surface(body, shape, _checked_guide(guide, shape))


def _checked_guide(guide: npt.ArrayLike | None, shape: tuple[int, ...]) -> np.ndarray | None:
    if guide is None:
        return None
    guide = _check_grey(guide)
    if guide.shape != tuple(shape):
        raise CodingError(f'guide image {guide.shape} and disparity {tuple(shape)} differ in size')
    return guide


def _node_grid(shape: tuple[int, ...], cell_px: int) -> tuple[int, int]:
    return int(np.ceil(shape[0] / cell_px)) + 1, int(np.ceil(shape[1] / cell_px)) + 1


def _compact_body(
    d: FloatArray, filled: FloatArray, body_bits: int, guide: np.ndarray | None = None
) -> Bits:
    """``d`` (NaN unknown; ``filled``: with its unknown pixels filled in) ->
    ``body_bits`` bits: the least-squares nodes (``_node_fit``) at a spacing of
    ``NODE_SPACINGS_PX``, quantised, coded by ``_node_code``; zero-padded. The spacing
    is the finest whose bilinear code fits with a step matched to its fit's error
    (``QUANTISATION_PER_FIT_RMS``; found by bisection: finer spacings take more bits),
    or the next finer one with a coarser step (up to ``FINER_STEP_FACTORS``) if that
    fits and predicts less error (fit and quantisation: hypot(fit, step / sqrt(12))).
    If even the widest spacing does not fit, its step doubles until it does. With
    ``guide`` (the host image) the nodes of the guided interpolation are then fitted at
    the chosen spacing and coded with the finest step that fits (``GUIDED_STEP_FACTORS``),
    kept if that predicts ``GUIDED_MAX_ERROR_RATIO`` of the error or less (the guided
    fit costs a sparse solve, so the bisection runs on the bilinear fits, whose code
    sizes are close)."""
    bits, error, spacing = _bilinear_code(d, filled, body_bits)
    if guide is not None:
        guided = _guided_code(d, filled, body_bits, spacing, guide)
        if guided is not None and guided[1] <= GUIDED_MAX_ERROR_RATIO * error:
            bits = guided[0]
    return np.concatenate([bits, np.zeros(body_bits - bits.size, np.uint8)])


def _bilinear_code(d: FloatArray, filled: FloatArray, body_bits: int) -> tuple[Bits, float, int]:
    """The bilinear nodes' code of ``_compact_body``'s choice (unpadded), the error it
    predicts [px] and its spacing index."""
    fits: dict[int, tuple[FloatArray, np.ndarray, float]] = {}

    def code(index: int, step_factor: float = 1.0) -> tuple[Bits, float]:
        if index not in fits:
            fits[index] = _node_fit(d, filled, NODE_SPACINGS_PX[index])
        return _quantised_code(index, *fits[index], step_factor)

    # Every node takes at least one bit: the bisection starts where that holds.
    fitting = [int(np.prod(_node_grid(d.shape, c))) <= body_bits for c in NODE_SPACINGS_PX]
    first = fitting.index(True) if any(fitting) else len(NODE_SPACINGS_PX) - 1
    low, high = first, len(NODE_SPACINGS_PX) - 1  # the answer is in [low, high]
    codes: dict[int, tuple[Bits, float]] = {}
    while low < high:
        middle = (low + high) // 2
        codes[middle] = code(middle)
        if codes[middle][0].size <= body_bits:
            high = middle
        else:
            low = middle + 1
    bits, error = codes[low] if low in codes else code(low)
    step_factor = 1.0
    while bits.size > body_bits and step_factor * RANGE_UNIT_PX < MAX_STEP_PX:
        step_factor *= 2.0
        bits, error = code(low, step_factor)
    if bits.size > body_bits:
        raise CodingError(f'no disparity code fits in {body_bits} bits')
    spacing = low
    if low > first:
        for step_factor in FINER_STEP_FACTORS:
            finer_bits, finer_error = code(low - 1, step_factor)
            if finer_bits.size <= body_bits:
                if finer_error < error:
                    bits, error, spacing = finer_bits, finer_error, low - 1
                break
    return bits, error, spacing


def _guided_code(
    d: FloatArray, filled: FloatArray, body_bits: int, spacing: int, guide: np.ndarray
) -> tuple[Bits, float] | None:
    """The guided nodes' code at spacing index ``spacing`` with the finest step of
    ``GUIDED_STEP_FACTORS`` that fits ``body_bits``, and the error it predicts [px];
    None if none fits."""
    guided_fit = _node_fit(d, filled, NODE_SPACINGS_PX[spacing], guide)
    for step_factor in GUIDED_STEP_FACTORS:
        bits, error = _quantised_code(spacing, *guided_fit, step_factor, True)
        if bits.size <= body_bits:
            return bits, error
    return None


def _quantised_code(
    index: int,
    values: FloatArray,
    known: np.ndarray,
    fit_rms: float,
    step_factor: float = 1.0,
    guided: bool = False,
) -> tuple[Bits, float]:
    """``_node_code`` of a fit (``_node_fit``'s values, known, fit RMS) at spacing
    ``index`` with ``step_factor`` times the fit-matched step, and the error it predicts
    [px] (fit and quantisation)."""
    step = step_factor * max(QUANTISATION_PER_FIT_RMS * fit_rms, RANGE_UNIT_PX)
    step = min(step, MAX_STEP_PX)
    bits = _node_code(index, values, known, step, guided)
    return bits, float(np.hypot(fit_rms, step / 12**0.5))


def _node_code(
    spacing_index: int,
    values: FloatArray,
    known: np.ndarray,
    step_px: float,
    guided: bool = False,
) -> Bits:
    """The compact code of node ``values`` (rows, cols) [px] and their ``known`` mask,
    quantised with ``step_px``: header (spacing index, ``guided`` (the interpolation the
    nodes were fitted for), lowest value, step), the known-node mask as
    run lengths, then every node's level (unknown ones too: they hold the fit of the
    filled-in disparity, so the prediction stays smooth) as the residual from the
    LOCO-I median edge detector's prediction; all numbers Exp-Golomb (order 0)."""
    low = int(np.clip(np.floor(values.min() / RANGE_UNIT_PX), 0, 2**LOW_BITS - 1))
    step_units = int(np.clip(np.rint(step_px / RANGE_UNIT_PX), 1, 2**STEP_BITS - 1))
    levels = np.rint((values - low * RANGE_UNIT_PX) / (step_units * RANGE_UNIT_PX))
    levels = levels.astype(np.int64)
    residuals = (levels - _med_prediction(levels)).ravel()
    zigzag = np.where(residuals >= 0, 2 * residuals, -2 * residuals - 1)
    return np.concatenate(
        [
            _to_bits(np.array([spacing_index]), SPACING_BITS),
            _to_bits(np.array([int(guided)]), GUIDED_BITS),
            _to_bits(np.array([low]), LOW_BITS),
            _to_bits(np.array([step_units]), STEP_BITS),
            _exp_golomb(_run_lengths(known.ravel())),
            _exp_golomb(zigzag),
        ]
    )


def _compact_surface(
    body: Bits, shape: tuple[int, ...], guide: np.ndarray | None = None
) -> FloatArray | None:
    """Inverse of ``_compact_body``: the (H, W) surface [px], NaN where the nearest node
    is unknown; None if the body is inconsistent (possible only past the CRC's 2^-32).
    A guided code is interpolated with ``guide`` (the received image; CodingError
    without it)."""
    fields = np.cumsum([0, SPACING_BITS, GUIDED_BITS, LOW_BITS, STEP_BITS])
    spacing_index, guided, low, step_units = (
        int(_from_bits(body[start:end], end - start)[0])
        for start, end in zip(fields[:-1], fields[1:], strict=True)
    )
    if spacing_index >= len(NODE_SPACINGS_PX) or step_units == 0:
        return None
    cell_px = NODE_SPACINGS_PX[spacing_index]
    rows, cols = _node_grid(shape, cell_px)
    numbers = _exp_golomb_decoded(body[HEADER_BITS:], rows * cols)
    if numbers is None:
        return None
    runs, zigzag = numbers
    residuals = np.where(zigzag % 2 == 0, zigzag // 2, -(zigzag + 1) // 2).reshape(rows, cols)
    levels = _med_reconstruction(residuals)
    values = np.maximum(0.0, (low + step_units * levels) * RANGE_UNIT_PX)
    known = np.repeat(np.arange(len(runs)) % 2 == 0, runs).reshape(rows, cols)
    nodes = np.where(known, values, np.nan)
    if not guided:
        return _node_surface(nodes, shape, cell_px)
    if guide is None:
        raise CodingError('the code is guided by the image: the decoder needs the image')
    return _guided_surface(nodes, cell_px, _guide_grey(guide))


def _node_fit(
    d: FloatArray, filled: FloatArray, cell_px: int, guide: np.ndarray | None = None
) -> tuple[FloatArray, np.ndarray, float]:
    """Least-squares nodes every ``cell_px`` of ``filled`` (``d`` with its unknown
    pixels filled in, so the bilinear fit is two small matrix products; with ``guide``,
    the host image, the fit of the guided interpolation ``_guided_nodes``): (node values
    (rows, cols) [px] >= 0, known (rows, cols): at least ``MIN_VALID_FRACTION`` known
    support, the fit's RMS error [px] over ``d``'s known pixels (every 4th row and
    column: it only sets the quantisation step))."""
    known = np.isfinite(d)
    basis_rows, basis_cols = (_hat_basis(n, cell_px) for n in d.shape)
    # The two image-sized products in single precision (half the time; the node values
    # need far less than its 1e-7).
    weights = _hat_pseudo_inverse(d.shape[0], cell_px)[1] @ known.astype(np.float32) @ basis_cols
    support = basis_rows.sum(axis=0)[:, None] * basis_cols.sum(axis=0)[None, :]
    sample = (slice(None, None, 4), slice(None, None, 4))
    if guide is None:
        inverse_rows, inverse_cols = (_hat_pseudo_inverse(n, cell_px)[0] for n in d.shape)
        nodes = inverse_rows @ filled.astype(np.float32) @ inverse_cols.T
        nodes = np.maximum(nodes.astype(float), 0.0)
        fit = basis_rows[sample[0]] @ nodes @ basis_cols[sample[1]].T
    else:
        grey = _guide_grey(guide)
        nodes = np.maximum(_guided_nodes(filled, cell_px, grey), 0.0)
        fit = _guided_surface(nodes, cell_px, grey, 4)
    error = (fit - d[sample])[known[sample]]
    fit_rms = float(np.sqrt(np.mean(error**2))) if error.size else 0.0
    return nodes, weights >= MIN_VALID_FRACTION * support, fit_rms


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


# The four corners of a pixel's cell, (row, col) offsets from its top-left node.
_CORNERS = ((0, 0), (0, 1), (1, 0), (1, 1))


def _cell_of(
    n: int, cell_px: int, sample: int = 1
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """Each of ``n`` pixels' (every ``sample``-th) cell (its lower node, node j at pixel
    coordinate j * cell_px - 0.5, as ``_hat_basis``) and its fraction of the way to the
    next node."""
    position = (np.arange(0, n, sample) + 0.5) / cell_px
    lower = np.floor(position).astype(np.int64)
    return lower, (position - lower).astype(np.float32)


def _guide_grey(guide: np.ndarray) -> npt.NDArray[np.float32]:
    """The grey levels the guided interpolation compares: ``guide`` blurred by
    ``GUIDE_BLUR_PX``."""
    return np.asarray(
        cv2.GaussianBlur(guide.astype(np.float32), (0, 0), GUIDE_BLUR_PX), np.float32
    )


def _corner_weights(
    cell_px: int, grey: npt.NDArray[np.float32], sample: int = 1
) -> npt.NDArray[np.float32]:
    """(4, H, W) float32 (every ``sample``-th row and column): each pixel's weights of
    its cell's corners (``_CORNERS``), summing to 1: the bilinear weight times the
    grey-level affinity of the pixel and the node in ``grey`` (``_guide_grey``; see
    ``GUIDE_GREY_SCALE``)."""
    (row_cells, row_fractions), (col_cells, col_fractions) = (
        _cell_of(n, cell_px, sample) for n in grey.shape
    )
    node_rows, node_cols = (
        np.clip(np.rint(np.arange(count) * cell_px - 0.5), 0, n - 1).astype(np.int64)
        for count, n in zip(_node_grid(grey.shape, cell_px), grey.shape, strict=True)
    )
    node_grey = grey[node_rows][:, node_cols]
    pixel_grey = grey[::sample, ::sample]
    weights = np.empty((len(_CORNERS), *pixel_grey.shape), np.float32)
    for k, (row_offset, col_offset) in enumerate(_CORNERS):
        row_hat = row_fractions if row_offset else 1.0 - row_fractions
        col_hat = col_fractions if col_offset else 1.0 - col_fractions
        corner_grey = node_grey[row_cells + row_offset][:, col_cells + col_offset]
        contrast = (pixel_grey - corner_grey) * np.float32(1.0 / GUIDE_GREY_SCALE)
        affinity = np.exp(np.float32(-0.5) * contrast * contrast) + np.float32(GUIDE_FLOOR)
        weights[k] = row_hat[:, None] * col_hat[None, :] * affinity
    weights /= weights.sum(axis=0)
    return weights


def _guided_nodes(filled: FloatArray, cell_px: int, grey: npt.NDArray[np.float32]) -> FloatArray:
    """(rows, cols) nodes [px] of the guided interpolation (``_corner_weights`` of
    ``grey``) that fit ``filled`` (H, W) [px] best in least squares on every
    ``GUIDED_FIT_SAMPLE``-th row and column, held to their neighbours by
    ``GUIDED_SMOOTHNESS``. The normal equations are summed cell by cell (each cell's
    pixels weigh the same four nodes) and solved as a sparse system."""
    weights = _corner_weights(cell_px, grey, GUIDED_FIT_SAMPLE)
    filled = filled[::GUIDED_FIT_SAMPLE, ::GUIDED_FIT_SAMPLE].astype(np.float32)
    rows, cols = _node_grid(grey.shape, cell_px)
    (row_cells, _), (col_cells, _) = (_cell_of(n, cell_px, GUIDED_FIT_SAMPLE) for n in grey.shape)
    row_starts = np.flatnonzero(np.diff(row_cells, prepend=-1))
    col_starts = np.flatnonzero(np.diff(col_cells, prepend=-1))

    def per_cell(values: np.ndarray) -> FloatArray:
        """Sums of (H, W) ``values`` over each cell, raveled (cells row by row)."""
        sums = np.add.reduceat(np.add.reduceat(values, row_starts, 0), col_starts, 1)
        return sums.ravel().astype(float)

    # The cells that hold sampled pixels (a last one-pixel cell may hold none).
    cell_rows, cell_cols = np.meshgrid(row_cells[row_starts], col_cells[col_starts], indexing='ij')
    corner_node = [
        ((cell_rows + row_offset) * cols + cell_cols + col_offset).ravel()
        for row_offset, col_offset in _CORNERS
    ]
    entries: list[tuple[np.ndarray, np.ndarray, FloatArray]] = []
    for k in range(len(_CORNERS)):
        for m in range(k, len(_CORNERS)):
            sums = per_cell(weights[k] * weights[m])
            entries.append((corner_node[k], corner_node[m], sums))
            if m != k:
                entries.append((corner_node[m], corner_node[k], sums))
    n_nodes = rows * cols
    normal = scipy.sparse.coo_matrix(
        (
            np.concatenate([e[2] for e in entries]),
            (np.concatenate([e[0] for e in entries]), np.concatenate([e[1] for e in entries])),
        ),
        shape=(n_nodes, n_nodes),
    ).tocsc()
    index = np.arange(n_nodes).reshape(rows, cols)
    differences = scipy.sparse.vstack(
        [
            _second_differences(index[:, :-2], index[:, 1:-1], index[:, 2:], n_nodes),
            _second_differences(index[:-2], index[1:-1], index[2:], n_nodes),
        ]
    )
    pixels_per_cell = (cell_px / GUIDED_FIT_SAMPLE) ** 2
    normal = normal + GUIDED_SMOOTHNESS * pixels_per_cell * (differences.T @ differences)
    right_side = np.bincount(
        np.concatenate(corner_node),
        weights=np.concatenate([per_cell(w * filled) for w in weights]),
        minlength=n_nodes,
    )
    # The matrix couples nodes up to two rows apart in the order rows are numbered:
    # numbered column by column when the columns are the shorter side, its band is
    # narrower (8-px nodes at 640x480: 124 against 164; 18 against 24 ms).
    order = index.T.ravel() if cols > rows else index.ravel()
    nodes = np.empty(n_nodes)
    nodes[order] = _solved_symmetric_banded(
        normal[order][:, order], right_side[order].astype(float)
    )
    return nodes.reshape(rows, cols)


def _solved_symmetric_banded(matrix: scipy.sparse.spmatrix, right_side: FloatArray) -> FloatArray:
    """x of ``matrix`` x = ``right_side`` for a sparse symmetric positive definite
    matrix whose entries lie near its diagonal (the nodes' normal equations, row by row:
    within two rows of nodes): banded Cholesky, a third of SuperLU's time at 14-px nodes
    on Aloe (7 against 19 ms), the same nodes to 1e-12 px; SuperLU if it is not
    positive definite."""
    entries = scipy.sparse.coo_matrix(matrix)
    upper = entries.col >= entries.row
    offsets = (entries.col - entries.row)[upper]
    bandwidth = int(offsets.max()) if offsets.size else 0
    banded = np.zeros((bandwidth + 1, matrix.shape[0]))
    np.add.at(banded, (bandwidth - offsets, entries.col[upper]), entries.data[upper])
    try:
        return np.asarray(scipy.linalg.solveh_banded(banded, right_side), dtype=float)
    except np.linalg.LinAlgError:
        solved = scipy.sparse.linalg.spsolve(scipy.sparse.csc_matrix(matrix), right_side)
        return np.asarray(solved, dtype=float)


def _second_differences(
    before: np.ndarray, middle: np.ndarray, after: np.ndarray, n: int
) -> scipy.sparse.csr_matrix:
    """The (m, n) sparse matrix of x[before] - 2 x[middle] + x[after] for the m index
    triples (zero on planes, so a plane's nodes are not pulled)."""
    count = before.size
    rows = np.tile(np.arange(count), 3)
    columns = np.concatenate([before.ravel(), middle.ravel(), after.ravel()])
    values = np.repeat([1.0, -2.0, 1.0], count)
    return scipy.sparse.csr_matrix((values, (rows, columns)), shape=(count, n))


def _guided_surface(
    nodes: FloatArray, cell_px: int, grey: npt.NDArray[np.float32], sample: int = 1
) -> FloatArray:
    """The guided interpolation (``_corner_weights`` of ``grey``) of ``nodes`` (rows,
    cols) [px] (NaN unknown: the known corners' weights are renormalised) on the (H, W)
    pixels of ``grey`` (every ``sample``-th); NaN where the nearest node is unknown."""
    weights = _corner_weights(cell_px, grey, sample)
    known = np.isfinite(nodes)
    values = np.where(known, nodes, 0.0).astype(np.float32)
    (row_cells, row_fractions), (col_cells, col_fractions) = (
        _cell_of(n, cell_px, sample) for n in grey.shape
    )
    surface = np.zeros(weights.shape[1:], np.float32)
    total = np.zeros(weights.shape[1:], np.float32)
    for weight, (row_offset, col_offset) in zip(weights, _CORNERS, strict=True):
        # Each pixel's corner node, gathered row then column (a third of the time of
        # one flat index per pixel).
        corner_rows, corner_cols = row_cells + row_offset, col_cells + col_offset
        weight = weight * known[corner_rows][:, corner_cols]
        surface += weight * values[corner_rows][:, corner_cols]
        total += weight
    # The nearest node, as ``_node_surface``'s (ties to the lower one).
    nearest_rows = row_cells + (row_fractions > 0.5)
    nearest_cols = col_cells + (col_fractions > 0.5)
    nearest = known[nearest_rows][:, nearest_cols]
    return np.where(nearest, surface.astype(float) / np.maximum(total, 1e-12), np.nan)


def encode(
    image: npt.ArrayLike,
    disparity_px: npt.ArrayLike,
    key: str,
    step: float = DEFAULT_STEP,
    fine: bool = True,
    guided: bool = True,
) -> npt.NDArray[np.uint8]:
    """Embed the disparity code of ``disparity_px`` (H, W) [px] in ``image`` (H, W)
    uint8: the coarse layer, and the fine layer unless ``fine`` is False (the code
    before the fine layer, kept for comparison) or the image is too small for it; the
    nodes fitted for the interpolation guided by the image, or for the bilinear one
    (``guided`` False: the code before, kept for comparison; the decoder reads which
    from the code). Returns the coded (H, W) uint8 image."""
    image = _check_grey(image)
    disparity_px = np.asarray(disparity_px, dtype=float)
    if disparity_px.shape != image.shape:
        raise CodingError(f'disparity {disparity_px.shape} and image {image.shape} differ in size')
    return _embed(image, disparity_px, key, step, fine, guided)


def _embed(
    image: npt.NDArray[np.uint8],
    disparity_px: FloatArray,
    key: str,
    step: float,
    fine: bool,
    guided: bool,
) -> npt.NDArray[np.uint8]:
    blocks, coefficients = _band_coefficients(image)
    change = np.zeros_like(coefficients)
    coarse = len(BANDS)
    d = _known_or_nan(disparity_px)
    filled = _filled(d)  # once for both layers
    guide = image if guided else None
    coarse_word = _seal(_compact_body(d, filled, _body_bits_of(payload_bits(d.shape)), guide))
    change[..., :coarse] = _pair_change(coefficients[..., :coarse], coarse_word, key, step)
    n_fine = fine_payload_bits(image.shape)
    if fine and n_fine:
        change[..., coarse:] = _qim_change(
            coefficients[..., coarse:],
            _seal(_compact_body(d, filled, _body_bits_of(n_fine), guide)),
            _fine_key(key),
            np.array(FINE_STEP_RATIOS) * step,
        )
    # Only the band coefficients change: add their basis functions, scaled.
    blocks = blocks + np.einsum('rcb,bij->ricj', change, _BAND_BASIS, optimize=True)
    marked = image.astype(float)
    marked[: blocks.shape[0] * BLOCK, : blocks.shape[2] * BLOCK] = blocks.reshape(
        blocks.shape[0] * BLOCK, blocks.shape[2] * BLOCK
    )
    return np.clip(np.rint(marked), 0, 255).astype(np.uint8)


def _qim_change(coefficients: FloatArray, bits: Bits, key: str, steps: FloatArray) -> FloatArray:
    """The change that moves each coefficient (rows, cols, bands) onto the keyed lattice
    of its bit, with ``steps`` (bands,) [grey levels]."""
    slots = _slot_layout(coefficients.shape, bits.size, key)
    step = np.broadcast_to(steps, coefficients.shape).reshape(-1)
    values = coefficients.reshape(-1)
    lattice_offset = (slots.dither + 0.5 * bits[slots.bit_of_slot]) * step
    change = step * np.rint((values - lattice_offset) / step) + lattice_offset - values
    return change.reshape(coefficients.shape)


PAIR_GAIN = np.sqrt(2.0)  # the pair's projection's QIM step / ``step``


def _pair_projections(coefficients: FloatArray, key: str, n_bits: int) -> FloatArray:
    """(rows, cols, 1): each block's pair of coarse coefficients (rows, cols, 2)
    projected on the unit vector (1, +-1) / sqrt 2 (the sign keyed per block)."""
    sign = _slot_layout((*coefficients.shape[:2], 1), n_bits, key).sign
    sign = sign.reshape(*coefficients.shape[:2], 1)
    return (coefficients[..., :1] + sign * coefficients[..., 1:]) / np.sqrt(2.0)


def _pair_change(coefficients: FloatArray, bits: Bits, key: str, step: float) -> FloatArray:
    """The change of each block's coarse pair (rows, cols, 2) that moves its projection
    (``_pair_projections``) onto its bit's keyed lattice with step ``step`` x
    ``PAIR_GAIN``, shared equally by the two coefficients."""
    projection = _pair_projections(coefficients, key, bits.size)
    sign = _slot_layout(projection.shape, bits.size, key).sign.reshape(projection.shape)
    change = _qim_change(projection, bits, key, np.array([PAIR_GAIN * step])) / np.sqrt(2.0)
    return np.concatenate([change, sign * change], axis=-1)


def decode(image: npt.ArrayLike, key: str, step: float = DEFAULT_STEP) -> Detection:
    """Look for the watermark of ``key`` in ``image`` (H, W) uint8; returns a Detection.
    The fine layer's surface is returned when its word decodes, else the coarse cells."""
    image = _check_grey(image)
    shape = image.shape
    blocks, coefficients = _band_coefficients(image)
    # A block of one grey level (cropped, saturated) carries nothing: its copies are left out.
    alive = np.ptp(blocks, axis=(1, 3)) > 0
    coarse = len(BANDS)
    n_bits = payload_bits(shape)
    confidence, bits, raw_ber, body = _read_word(
        coefficients[..., :coarse],
        n_bits,
        key,
        np.array([PAIR_GAIN * step]),
        _BAND_FREQUENCIES[:coarse],
        alive,
        pairs=True,
    )
    n_fine = fine_payload_bits(shape)
    fine_body = None
    if n_fine:
        fine_body = _read_word(
            coefficients[..., coarse:],
            n_fine,
            _fine_key(key),
            np.array(FINE_STEP_RATIOS) * step,
            _BAND_FREQUENCIES[coarse:],
            alive,
            erasures=False,  # one copy a bit: its reliabilities say little, and RS is slow
        )[3]
    # The fine word's surface when it decoded, else the coarse one's (built only then).
    disparity = None
    for word in (fine_body, body):
        disparity = None if word is None else _compact_surface(word, shape, image)
        if disparity is not None:
            break
    return Detection(
        found=disparity is not None,
        confidence=confidence,
        raw_ber=raw_ber,
        disparity_px=disparity,
        bits=bits,
        fine=disparity is not None and fine_body is not None,
    )


def _soft_copies(
    coefficients: FloatArray,
    gains: FloatArray,
    n_bits: int,
    key: str,
    steps: FloatArray,
    pairs: bool,
) -> tuple[_Slots, FloatArray]:
    """The slots of a word and each copy's soft decision, cos of its lattice phase (+1:
    on the bit-0 lattice, -1: on the bit-1 one), from ``coefficients`` (rows, cols,
    bands) divided by the blur ``gains`` (bands,): each coefficient with its band's QIM
    step of ``steps`` (``_qim_change``), or each block's pair (``pairs``,
    ``_pair_change``, ``steps`` its one step)."""
    values = coefficients / gains
    if pairs:
        values = _pair_projections(values, key, n_bits)
    slots = _slot_layout(values.shape, n_bits, key)
    slot_steps = np.broadcast_to(steps, values.shape).reshape(-1)
    return slots, np.cos(2.0 * np.pi * (values.reshape(-1) / slot_steps - slots.dither))


def _read_word(
    coefficients: FloatArray,
    n_bits: int,
    key: str,
    steps: FloatArray,
    frequencies: FloatArray,
    alive: np.ndarray,
    pairs: bool = False,
    erasures: bool = True,
) -> tuple[float, Bits, float, Bits | None]:
    """Soft-decode a keyed word of ``n_bits`` from ``coefficients`` (rows, cols, bands;
    ``_soft_copies``), the copies of the blocks not ``alive`` (rows, cols) left out,
    trying the gains of ``BLUR_SIGMAS_PX``: the first word whose Reed-Solomon decoding
    and CRC succeed, else the one whose copies agree best, whose least reliable bytes
    are then tried as erasures (``_erasure_decoded``) if ``erasures``. (confidence, bits,
    raw bit error rate, the checked body or None)."""
    # (confidence, bits, raw bit error rate, each bit's reliability: |sum| / copies)
    best: tuple[float, Bits, float, FloatArray] | None = None
    body = None
    for sigma in BLUR_SIGMAS_PX:
        gains = np.exp(-0.5 * (sigma * frequencies) ** 2)
        slots, soft = _soft_copies(coefficients, gains, n_bits, key, steps, pairs)
        weight = np.broadcast_to(alive[..., None], (*alive.shape, soft.size // alive.size))
        weight = weight.reshape(-1).astype(float)
        sums = np.bincount(slots.bit_of_slot, weights=weight * soft, minlength=n_bits)
        copies = np.bincount(slots.bit_of_slot, weights=weight, minlength=n_bits)
        bits = (sums < 0).astype(np.uint8)
        reliability = np.abs(sums) / np.maximum(copies, 1)
        confidence = float(np.mean(reliability))
        counted = weight > 0
        wrong = (soft[counted] < 0) != bits[slots.bit_of_slot[counted]]
        raw_ber = float(np.mean(wrong)) if wrong.size else 0.5
        body = _checked_body(bits, n_bits)
        if body is not None or best is None or confidence > best[0]:
            best = (confidence, bits, raw_ber, reliability)
        if body is not None:
            break
    assert best is not None  # BLUR_SIGMAS_PX is not empty
    confidence, bits, raw_ber, reliability = best
    if body is None and erasures:
        body = _erasure_decoded(bits, reliability)
    return confidence, bits, raw_ber, body


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
    n_bits = payload_bits(image.shape)
    coarse = len(BANDS)
    best = (-1.0, 0.0)
    for angle in np.arange(-max_degrees, max_degrees + 1e-9, step_degrees):
        _, coefficients = _band_coefficients(_rotate(image, angle))
        slots, soft = _soft_copies(
            coefficients[..., :coarse],
            np.ones(coarse),
            n_bits,
            key,
            np.array([PAIR_GAIN * step]),
            pairs=True,
        )
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
    """Copies (blocks' coarse pairs) of each coarse bit an (H, W) image carries (the
    smallest count)."""
    slots = (shape[0] // BLOCK) * (shape[1] // BLOCK)
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
    sign: np.ndarray  # (slots,) float64 +-1: the keyed sign of a coarse pair's projection


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
                f'px has {n_slots} slots for {n_bits} bits'
            )
        seed = int.from_bytes(hashlib.sha256(str(key).encode()).digest()[:8], 'little')
        rng = np.random.default_rng(seed)
        bit_of_slot = np.empty(n_slots, dtype=np.int64)
        bit_of_slot[rng.permutation(n_slots)] = np.arange(n_slots) % n_bits
        dither = rng.uniform(0.0, 1.0, n_slots)
        slots = _Slots(
            bit_of_slot=bit_of_slot,
            dither=dither,
            sign=rng.choice(np.array([-1.0, 1.0]), n_slots),
        )
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
RS_BLOCK_BYTES = 255  # reedsolo's chunk: a word of more bytes is coded block by block


def _galois_tables() -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Antilog (doubled, so sums of two logs need no modulo) and log tables of GF(256)
    with reedsolo's primitive polynomial 0x11d and generator 2."""
    antilog = np.zeros(510, np.int64)
    log = np.zeros(256, np.int64)
    value = 1
    for power in range(255):
        antilog[power] = value
        log[value] = power
        value <<= 1
        if value & 0x100:
            value ^= 0x11D
    antilog[255:] = antilog[:255]
    return antilog, log


_GF_ANTILOG, _GF_LOG = _galois_tables()


def _syndromes_vanish(received: bytes | bytearray) -> bool:
    """True if every block of a received Reed-Solomon word (``_RS``) has zero
    syndromes, i.e. it is a code word and ``_RS.decode`` would return it unchanged:
    syndrome i of a block is the block's polynomial (first byte the highest power) at
    2^i, i < RS_PARITY_BYTES. In numpy: a fraction of reedsolo's pure-Python syndromes
    (which took ~40 ms of a 640x480 decode)."""
    data = np.frombuffer(received, np.uint8).astype(np.int64)
    powers = np.arange(RS_PARITY_BYTES)[:, None]
    for start in range(0, data.size, RS_BLOCK_BYTES):
        block = data[start : start + RS_BLOCK_BYTES]
        nonzero = np.flatnonzero(block)
        degrees = block.size - 1 - nonzero
        terms = _GF_ANTILOG[(_GF_LOG[block[nonzero]] + powers * degrees) % 255]
        if np.bitwise_xor.reduce(terms, axis=1).any():
            return False
    return True


def _known_or_nan(disparity_px: npt.ArrayLike) -> FloatArray:
    d = np.asarray(disparity_px, dtype=float)
    return np.where(np.isfinite(d) & (d >= 0), d, np.nan)


def _med_prediction(levels: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """LOCO-I's median edge detector on a (rows, cols) array, from the causal
    neighbours (west, north, north-west): the first row predicts from the west, the
    first column from the north, the first node 0. ``_med_reconstruction`` inverts it."""
    west, north, north_west = levels[1:, :-1], levels[:-1, 1:], levels[:-1, :-1]
    prediction = np.zeros_like(levels)
    prediction[0, 1:] = levels[0, :-1]
    prediction[1:, 0] = levels[:-1, 0]
    low, high = np.minimum(west, north), np.maximum(west, north)
    prediction[1:, 1:] = np.where(
        north_west >= high, low, np.where(north_west <= low, high, west + north - north_west)
    )
    return prediction


def _med_reconstruction(residuals: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """The levels whose ``_med_prediction`` residuals are ``residuals`` (node by node:
    each prediction needs the levels before it)."""
    rows, cols = residuals.shape
    levels = [[0] * cols for _ in range(rows)]
    r = residuals.tolist()
    for i in range(rows):
        for j in range(cols):
            if i == 0:
                prediction = levels[0][j - 1] if j else 0
            elif j == 0:
                prediction = levels[i - 1][0]
            else:
                west, north, north_west = levels[i][j - 1], levels[i - 1][j], levels[i - 1][j - 1]
                if north_west >= max(west, north):
                    prediction = min(west, north)
                elif north_west <= min(west, north):
                    prediction = max(west, north)
                else:
                    prediction = west + north - north_west
            levels[i][j] = prediction + r[i][j]
    return np.array(levels, dtype=np.int64)


def _run_lengths(flags: np.ndarray) -> npt.NDArray[np.int64]:
    """Lengths of the alternating runs of a boolean vector, the first one of True
    (0 if it starts False)."""
    change = np.flatnonzero(np.diff(flags.astype(np.int8))) + 1
    runs = np.diff(np.concatenate([[0], change, [flags.size]]))
    return np.concatenate([[0], runs]) if flags.size and not flags[0] else runs


def _exp_golomb(numbers: npt.ArrayLike) -> Bits:
    """Order-0 Exp-Golomb code of non-negative integers: n + 1 in binary, after as many
    zeros as it has bits less one (1 bit for 0, 3 for 1-2, 5 for 3-6, ...)."""
    values = np.asarray(numbers, dtype=np.int64).ravel() + 1
    if values.size == 0:
        return np.zeros(0, np.uint8)
    widths = np.frexp(values.astype(float))[1]  # bit lengths (exact below 2^53)
    ends = np.cumsum(2 * widths - 1)
    out = np.zeros(int(ends[-1]), np.uint8)
    last_bit = ends - 1  # each value ends its code, least significant bit last
    for bit in range(int(widths.max())):
        has = widths > bit
        out[last_bit[has] - bit] = (values[has] >> bit) & 1
    return out


MAX_EXP_GOLOMB_ZEROS = 40  # levels and runs are far below 2^40


def _exp_golomb_decoded(
    bits: Bits, n_nodes: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None:
    """Read the run lengths of an ``n_nodes`` mask, then ``n_nodes`` numbers, from an
    Exp-Golomb stream; None if the stream ends early, holds a number of more than
    ``MAX_EXP_GOLOMB_ZEROS`` + 1 bits, or the runs overshoot."""
    text = (np.asarray(bits, np.uint8) + ord('0')).tobytes().decode()
    position = 0

    def read() -> int | None:
        nonlocal position
        one = text.find('1', position)
        end = 2 * one - position + 1
        if one < 0 or end > len(text) or one - position > MAX_EXP_GOLOMB_ZEROS:
            return None  # a number beyond int64 cannot come from _exp_golomb
        value = int(text[one:end], 2) - 1
        position = end
        return value

    runs: list[int] = []
    while sum(runs) < n_nodes:
        run = read()
        if run is None:
            return None
        runs.append(run)
    if sum(runs) != n_nodes:
        return None
    numbers = [read() for _ in range(n_nodes)]
    if any(n is None for n in numbers):
        return None
    return np.array(runs, dtype=np.int64), np.array(numbers, dtype=np.int64)


def _seal(body: Bits) -> Bits:
    """Body bits -> code word: padded to bytes, CRC-32, Reed-Solomon parity."""
    message = np.packbits(body).tobytes()
    message += zlib.crc32(message).to_bytes(4, 'big')
    return np.unpackbits(np.frombuffer(bytes(_RS.encode(message)), np.uint8))


@functools.lru_cache(maxsize=64)
def _hat_basis(n: int, cell_px: int) -> FloatArray:
    """(n, nodes) 1-D bilinear interpolation weights of ``n`` pixels on nodes every
    ``cell_px`` px (node j at pixel coordinate j * cell_px - 0.5). Cached: read only."""
    nodes = int(np.ceil(n / cell_px)) + 1
    position = (np.arange(n) + 0.5) / cell_px
    basis = np.maximum(0.0, 1.0 - np.abs(position[:, None] - np.arange(nodes)[None, :]))
    basis.setflags(write=False)
    return basis


@functools.lru_cache(maxsize=64)
def _hat_pseudo_inverse(n: int, cell_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The pseudo-inverse and the transpose of ``_hat_basis(n, cell_px)``, both (nodes,
    n) float32. Cached: read only."""
    basis = _hat_basis(n, cell_px)
    pair = np.linalg.pinv(basis).astype(np.float32), basis.T.astype(np.float32)
    for matrix in pair:
        matrix.setflags(write=False)
    return pair


def _filled(d: FloatArray, cell_px: int = FILL_WINDOW_PX) -> FloatArray:
    """``d`` (NaN unknown) with unknown pixels replaced by the mean of the known ones
    around them (normalised box filters of growing size from ``cell_px``), or by the
    overall mean where none is; 0 everywhere if no pixel is known."""
    known = np.isfinite(d)
    if not known.any():  # nothing to spread (the box filters would take ~0.3 s at 1080p)
        return np.zeros(d.shape)
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
    filled[missing] = float(np.mean(d[known]))
    return filled.astype(float)


def _erasure_decoded(bits: Bits, reliability: FloatArray) -> Bits | None:
    """The checked body of a received code word whose plain Reed-Solomon decoding
    failed, with the ``ERASURE_COUNTS`` least reliable bytes of each 255-byte block
    (a byte as reliable as its least reliable bit; ``reliability`` per bit) declared
    erased: a block corrects e errors and f erasures while 2 e + f <= its parity bytes,
    so located errors cost half. None if no count gives a word whose CRC holds (each
    attempt is another 2^-32 chance of a false alarm: a few in all)."""
    byte_reliability = np.asarray(reliability).reshape(-1, 8).min(axis=1)
    for count in ERASURE_COUNTS:
        erased = [
            start + int(position)
            for start in range(0, byte_reliability.size, 255)
            for position in np.argsort(byte_reliability[start : start + 255], kind='stable')[
                :count
            ]
        ]
        body = _checked_body(bits, bits.size, erased)
        if body is not None:
            return body
    return None


def _checked_body(
    bits: npt.ArrayLike, n_bits: int, erased_bytes: list[int] | None = None
) -> Bits | None:
    """The body bits of a received ``n_bits`` code word after Reed-Solomon correction
    (``erased_bytes``: byte positions known to be unreliable), or None if it cannot be
    corrected or its CRC-32 does not match."""
    bits = np.asarray(bits, dtype=np.uint8)
    if bits.size != n_bits:
        return None
    received = bytearray(np.packbits(bits).tobytes())
    if not erased_bytes and _syndromes_vanish(received):  # no error: the parity goes
        message = b''.join(
            received[start : start + RS_BLOCK_BYTES][:-RS_PARITY_BYTES]
            for start in range(0, len(received), RS_BLOCK_BYTES)
        )
    else:
        try:
            message = bytes(_RS.decode(received, erase_pos=erased_bytes)[0])
        except reedsolo.ReedSolomonError:
            return None
    body, crc = message[:-4], message[-4:]
    if zlib.crc32(body).to_bytes(4, 'big') != crc:
        return None
    return np.unpackbits(np.frombuffer(body, np.uint8))


def _check_grey(image: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise CodingError(f'expected an (H, W) uint8 grey image, got {image.dtype} {image.shape}')
    return image
