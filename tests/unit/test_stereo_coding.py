"""Chapter 6 cores: the DFrFT against its definition, the thesis's coding round trip,
ours under JPEG, and no watermark on unmarked or wrong-key images."""

import struct
import zlib

import cv2
import numpy as np
import pytest
from stereo_coding_node.channel import correlation, jpeg, psnr, ssim
from stereo_coding_node.dfrft import (
    commuting_matrix,
    dfrft2,
    dfrft_matrix,
    zigzag_degrade,
    zigzag_order,
    zigzag_restore,
)
from stereo_coding_node.errors import CodingError, KeyFileError
from stereo_coding_node.inputs import compressed_image_size, known_disparity
from stereo_coding_node.scenes import generated_scene
from stereo_coding_node.views import synthesise_right
from vgm_evaluation.metrics import disparity_agreement

from stereo_coding_node import blind, thesis
from vgm_common.sample_data import aloe_scaled

# --- DFrFT ------------------------------------------------------------------------------


@pytest.mark.parametrize('n', [2, 7, 8, 33, 64])
def test_dfrft_is_unitary_additive_and_order_one_is_the_dft(n):
    dft = np.fft.fft(np.eye(n), norm='ortho')
    assert np.allclose(commuting_matrix(n) @ dft, dft @ commuting_matrix(n), atol=1e-12)
    assert np.allclose(dfrft_matrix(n, np.pi / 2), dft, atol=1e-12)
    assert np.allclose(dfrft_matrix(n, 0.0), np.eye(n), atol=1e-12)
    assert np.allclose(dfrft_matrix(n, np.pi), dft @ dft, atol=1e-12)  # order 2: parity
    rng = np.random.default_rng(n)
    for a, b in rng.uniform(-np.pi, np.pi, (3, 2)):
        K = dfrft_matrix(n, a)
        assert np.allclose(K.conj().T @ K, np.eye(n), atol=1e-12)
        assert np.allclose(K @ dfrft_matrix(n, b), dfrft_matrix(n, a + b), atol=1e-11)
        assert np.allclose(dfrft_matrix(n, -a) @ K, np.eye(n), atol=1e-12)


def test_dfrft2_at_quarter_turns_is_the_2d_dft_and_keeps_energy():
    X = np.random.default_rng(1).random((12, 17))
    assert np.allclose(dfrft2(X, (np.pi / 2, np.pi / 2)), np.fft.fft2(X, norm='ortho'))
    Y = dfrft2(X, (0.4, 1.1))
    assert np.isclose(np.linalg.norm(Y), np.linalg.norm(X))
    assert np.allclose(dfrft2(Y, (-0.4, -1.1)), X)


def test_zigzag_is_jpegs_scan_and_inverts():
    expected = [0, 1, 4, 8, 5, 2, 3, 6, 9, 12, 13, 10, 7, 11, 14, 15]  # JPEG's 4x4 order
    assert zigzag_order(4, 4).tolist() == expected
    X = np.random.default_rng(2).integers(0, 255, (9, 14)).astype(np.uint8)
    assert np.array_equal(zigzag_restore(zigzag_degrade(X)), X)
    assert not np.array_equal(zigzag_degrade(X), X)


# --- thesis method ------------------------------------------------------------------------


def test_thesis_round_trip_returns_the_disparity_within_quantisation(tmp_path):
    left, _, disparity = aloe_scaled(160)
    coded, key = thesis.encode(left, disparity)
    key.save(tmp_path / 'key.npz')
    restored, decoded, singular = thesis.decode(coded, thesis.ThesisKey.load(tmp_path / 'key.npz'))
    watermark = np.nan_to_num(disparity)
    error = decoded - watermark
    # Only the real part and 8-bit rounding of F* lose information (A6.3): measured
    # RMS 0.05 px, max 0.29 px.
    assert np.sqrt(np.mean(error**2)) < 0.2
    assert np.max(np.abs(error)) < 1.0
    assert correlation(thesis.watermark_singular_values(disparity), singular) > 0.999
    # A permutation keeps the MSE: Table 6.2's two columns agree here (A6.1).
    assert np.isclose(psnr(zigzag_degrade(left), coded), psnr(left, restored))
    assert 25.0 < psnr(left, restored) < 60.0


def test_thesis_key_file_errors_name_the_file(tmp_path):
    with pytest.raises(KeyFileError, match='does not exist'):
        thesis.ThesisKey.load(tmp_path / 'missing.npz')
    corrupt = tmp_path / 'corrupt.npz'
    corrupt.write_bytes(b'not a key at all')
    with pytest.raises(KeyFileError, match='not a thesis key'):
        thesis.ThesisKey.load(corrupt)
    left, _, disparity = generated_scene((24, 32), seed=3)
    _, key = thesis.encode(left, disparity)
    with pytest.raises(KeyFileError, match='24x32'):
        thesis.decode(np.zeros((24, 30), np.uint8), key)


# --- ours ---------------------------------------------------------------------------------


def cell_truth(disparity, host, received):
    """The embedded disparity as the coarse word represents it (fitted on the ``host``,
    interpolated with the ``received`` image)."""
    return blind.disparity_from_code(
        blind.disparity_code(disparity, host), disparity.shape, received
    )


@pytest.mark.parametrize('source', ['aloe', 'generated'])
def test_ours_survives_jpeg_50_with_its_payload_exact(source):
    if source == 'aloe':
        left, _, disparity = aloe_scaled(640)
    else:
        left, _, disparity = generated_scene((480, 640), seed=11)
    coded = blind.encode(left, disparity, key='k1')
    assert psnr(left, coded) > 42.0
    assert ssim(left, coded) > 0.96  # 0.967 on the generated scene with the fine layer
    received, _ = jpeg(coded, 50)
    detection = blind.decode(received, key='k1')
    assert detection.found and detection.confidence > 0.5
    assert np.array_equal(detection.bits, blind.disparity_code(disparity, left))
    # Both layers arrive bit-exact: the decoded map is the fine layer's surface,
    # interpolated with the received image.
    assert detection.fine
    fine_truth = blind.fine_disparity_from_code(
        blind.fine_code(disparity, left), disparity.shape, received
    )
    np.testing.assert_array_equal(detection.disparity_px, fine_truth)
    assert np.isfinite(fine_truth).mean() > 0.95


# Measured (2026-12-05, the fine word on (0, 2) and (1, 1)): after JPEG 50, Aloe 640x555
# coarse layer only (32-px nodes) 0.908 / 5.84 px, with the fine layer (9-px nodes)
# 0.978 / 2.89 px (bilinear nodes: 0.973 / 3.19 px); generated seed 1 (28-px nodes)
# 0.963 / 3.23 px -> (8-px nodes) 0.989 / 1.77 px (bilinear 1.76 px: its texture does
# not follow its depth).
@pytest.mark.parametrize(
    'source, min_correlation, max_rms_px', [('aloe', 0.975, 3.0), ('generated', 0.985, 1.85)]
)
def test_ours_fine_layer_carries_the_disparity_through_jpeg_50(
    source, min_correlation, max_rms_px
):
    if source == 'aloe':
        left, _, disparity = aloe_scaled(640)
    else:
        left, _, disparity = generated_scene((480, 640), seed=1)
    coded = blind.encode(left, disparity, key='k29')
    assert psnr(left, coded) > 42.0
    received, _ = jpeg(coded, 50)
    detection = blind.decode(received, key='k29')
    assert detection.found and detection.fine
    correlation_fine, rms_fine, _ = disparity_agreement(detection.disparity_px, disparity)
    assert correlation_fine >= min_correlation and rms_fine <= max_rms_px
    before = blind.decode(jpeg(blind.encode(left, disparity, 'k29', fine=False), 50)[0], 'k29')
    assert before.found and not before.fine
    correlation_coarse, rms_coarse, _ = disparity_agreement(before.disparity_px, disparity)
    assert correlation_fine > correlation_coarse + 0.02 and rms_fine < 0.7 * rms_coarse
    bilinear = blind.decode(jpeg(blind.encode(left, disparity, 'k29', guided=False), 50)[0], 'k29')
    _, rms_bilinear, _ = disparity_agreement(bilinear.disparity_px, disparity)
    # Aloe's leaves: 3.19 -> 2.89 px; on the generated scene within 1 % of each other.
    assert rms_fine < (0.92 if source == 'aloe' else 1.01) * rms_bilinear


def test_ours_coarse_layer_carries_aloe_through_jpeg_30_with_correlation_0_9():
    left, _, disparity = aloe_scaled(640)
    received = jpeg(blind.encode(left, disparity, key='k29'), 30)[0]
    detection = blind.decode(received, key='k29')
    assert detection.found and not detection.fine
    correlation, rms, _ = disparity_agreement(detection.disparity_px, disparity)
    # Measured 0.908 / 5.84 px (bilinear nodes: 0.887 / 6.45 px).
    assert correlation >= 0.9 and rms < 6.0


def step_scene(shape=(240, 320)):
    """A host of two grey regions (60 and 170, seeded texture of 8 grey levels RMS)
    split by a slanted line, and a disparity of 12 px on one side and 36 px on the
    other, stepping on the same line (a fronto-parallel object before a wall)."""
    rows, cols = np.indices(shape)
    near = cols > 0.35 * rows + 0.4 * shape[1]
    texture = np.random.default_rng(5).normal(0.0, 8.0, shape)
    host = np.clip(np.where(near, 170.0, 60.0) + texture, 0, 255).astype(np.uint8)
    return host, np.where(near, 36.0, 12.0)


def test_ours_guided_nodes_keep_a_depth_step_that_follows_a_grey_edge():
    host, disparity = step_scene()
    results = {}
    for guided in (False, True):
        received = jpeg(blind.encode(host, disparity, 'k3', guided=guided), 50)[0]
        detection = blind.decode(received, 'k3')
        assert detection.found and detection.fine
        results[guided] = disparity_agreement(detection.disparity_px, disparity)
    # Bilinear nodes smear the 24-px step over a cell on each side of it; the guided
    # interpolation keeps it to the blur of the guide. (Measured: RMS 1.26 -> 0.70 px,
    # off by > 2 px 3.8 % -> 0.6 %.)
    assert results[True].rms_px < 0.8 and results[True].rms_px < 0.6 * results[False].rms_px
    assert results[True].beyond_2px < 0.01 and results[False].beyond_2px > 0.03


def test_ours_falls_back_to_the_coarse_layer_when_the_fine_one_is_lost():
    left, _, disparity = generated_scene((480, 640), seed=1)
    coded = blind.encode(left, disparity, key='k29')
    received = jpeg(coded, 30)[0]
    detection = blind.decode(received, key='k29')  # the fine step does not survive
    assert detection.found and not detection.fine
    np.testing.assert_array_equal(detection.disparity_px, cell_truth(disparity, left, received))


@pytest.mark.parametrize(
    'code, from_code',
    [
        (blind.fine_code, blind.fine_disparity_from_code),
        (blind.disparity_code, blind.disparity_from_code),
    ],
)
def test_ours_compact_code_reproduces_a_slanted_plane_to_an_eighth_of_a_pixel(code, from_code):
    rows, cols = np.indices((480, 640))
    plane = 20.0 + 0.05 * cols - 0.03 * rows  # 5.6 to 52 px
    plane[:40, :60] = np.nan  # unknown corner: unknown nodes, NaN pixels
    decoded = from_code(code(plane), plane.shape)
    known = np.isfinite(decoded) & np.isfinite(plane)
    assert known.sum() > 0.95 * plane.size and np.isnan(decoded[:15, :15]).all()
    # A plane fits exactly, so the step is the finest (1/8 px). Away from the unknown
    # corner the error is half of it; within two node spacings (at most 32 px here) of
    # it the fit saw filled-in values (local means) and the known nodes' weights are
    # renormalised. (Measured: 0.058 / 0.169 px fine (10-px nodes), 0.068 / 0.476 px
    # coarse (32-px nodes).)
    away = known & ((rows >= 40 + 64) | (cols >= 60 + 64))
    error = np.abs(decoded - plane)
    assert np.max(error[away]) < 0.5 * blind.RANGE_UNIT_PX + 0.01
    assert np.max(error[known]) < 0.6


def test_ours_guided_code_of_a_slanted_plane_keeps_it_and_needs_the_image():
    host, _ = step_scene((480, 640))
    rows, cols = np.indices(host.shape)
    plane = 20.0 + 0.05 * cols - 0.03 * rows
    bits = blind.fine_code(plane, host)
    decoded = blind.fine_disparity_from_code(bits, plane.shape, host)
    # The guided nodes do not carry a plane better than bilinear ones, whose error is
    # the step's rounding: the encoder keeps those (measured max 0.06 px).
    assert np.max(np.abs(decoded - plane)) < 0.5 * blind.RANGE_UNIT_PX + 0.01
    guided_bits = blind.fine_code(step_scene((480, 640))[1], host)
    with pytest.raises(CodingError, match='needs the image'):
        blind.fine_disparity_from_code(guided_bits, plane.shape)
    with pytest.raises(CodingError, match='differ in size'):
        blind.fine_disparity_from_code(guided_bits, plane.shape, host[:, :320])


def test_ours_fine_layer_needs_room_for_more_than_the_coarse_word():
    assert blind.fine_payload_bits((64, 80)) == 0  # 160 slots against 280 coarse bits
    # 320x240: 2400 slots, one copy each, against the coarse word's 512 bits.
    assert (blind.fine_payload_bits((240, 320)), blind.payload_bits((240, 320))) == (2400, 512)
    with pytest.raises(CodingError, match='too small for the fine layer'):
        blind.fine_code(np.full((64, 80), 5.0))


def test_exp_golomb_stream_round_trips_and_refuses_a_truncated_one():
    assert blind._exp_golomb([0, 1, 2]).tolist() == [1, 0, 1, 0, 0, 1, 1]
    numbers = np.array([0, 1, 2, 3, 6, 7, 1000, 0])
    stream = blind._exp_golomb(np.concatenate([[3, 5], numbers]))  # runs 3 + 5 = 8 nodes
    runs, decoded = blind._exp_golomb_decoded(stream, 8)
    assert runs.tolist() == [3, 5] and decoded.tolist() == numbers.tolist()
    assert blind._exp_golomb_decoded(stream[:-1], 8) is None
    assert blind._exp_golomb_decoded(blind._exp_golomb([9]), 8) is None  # runs overshoot
    # One run of 1 node, then a level of 71 bits (beyond int64): refused, no overflow.
    huge = np.concatenate([blind._exp_golomb([1]), np.zeros(70, np.uint8), np.ones(71, np.uint8)])
    assert blind._exp_golomb_decoded(huge, 1) is None


def test_med_prediction_residuals_reconstruct_the_levels():
    levels = np.random.default_rng(3).integers(-50, 200, (7, 9))
    residuals = levels - blind._med_prediction(levels)
    np.testing.assert_array_equal(blind._med_reconstruction(residuals), levels)


def test_ours_says_no_watermark_on_unmarked_and_wrong_key_images():
    left, _, disparity = generated_scene((240, 320), seed=5)
    coded = blind.encode(left, disparity, key='right key')
    assert blind.decode(coded, key='right key').found
    false_positives = 0
    for trial in range(100):
        unmarked, _, _ = generated_scene((240, 320), seed=1000 + trial)
        false_positives += blind.decode(unmarked, key='right key').found
        false_positives += blind.decode(coded, key=f'wrong key {trial}').found
    assert false_positives == 0
    miss = blind.decode(coded, key='wrong key')
    assert miss.disparity_px is None and miss.confidence < 0.5


def test_ours_fine_layer_says_no_watermark_on_unmarked_and_wrong_key_images():
    left, _, disparity = generated_scene((480, 640), seed=5)
    coded = blind.encode(left, disparity, key='right key')
    assert blind.decode(coded, key='right key').fine
    detections = 0
    for trial in range(15):  # the bench runs 1000 (README)
        unmarked, _, _ = generated_scene((480, 640), seed=2000 + trial)
        detections += blind.decode(unmarked, key='right key').found
        detections += blind.decode(coded, key=f'wrong key {trial}').found
    assert detections == 0


def test_ours_rejects_bad_input():
    left, _, disparity = generated_scene((64, 80), seed=6)
    with pytest.raises(CodingError, match='differ in size'):
        blind.encode(left, disparity[:, :40], key='k')
    with pytest.raises(CodingError, match='uint8'):
        blind.encode(left.astype(float), disparity, key='k')
    with pytest.raises(CodingError, match='smaller than one'):
        blind.decode(np.zeros((4, 4), np.uint8), key='k')


def test_synthesised_right_view_of_a_constant_shift_is_the_shifted_image():
    left = np.random.default_rng(7).integers(0, 255, (20, 40)).astype(np.uint8)
    right = synthesise_right(left, np.full(left.shape, 5.0))
    assert np.array_equal(right[:, :35], left[:, 5:])
    # The uncovered right border takes the nearest known pixel on its left.
    assert np.array_equal(right[:, 35:], np.repeat(left[:, 39:40], 5, axis=1))


def test_synthesised_right_view_of_aloe_beats_the_left_view():
    left, right, disparity = aloe_scaled(320)
    synthetic = synthesise_right(left, disparity)
    assert psnr(right, synthetic) > psnr(right, left) + 3.0


def test_ours_code_corrects_byte_errors_and_refuses_beyond_its_capacity():
    _, _, disparity = generated_scene((240, 320), seed=8)
    bits = blind.disparity_code(disparity)
    clean = blind.disparity_from_code(bits, disparity.shape)
    rng = np.random.default_rng(9)
    correctable = bits.copy()
    bytes_hit = rng.choice(bits.size // 8, blind.RS_PARITY_BYTES // 2, replace=False)
    correctable[bytes_hit * 8 + rng.integers(0, 8, bytes_hit.size)] ^= 1
    np.testing.assert_array_equal(blind.disparity_from_code(correctable, disparity.shape), clean)
    too_many = bits.copy()
    too_many[rng.choice(bits.size, bits.size // 4, replace=False)] ^= 1
    assert blind.disparity_from_code(too_many, disparity.shape) is None


@pytest.mark.parametrize('message_bytes', [10, 235, 236, 1380])
def test_syndromes_vanish_on_code_words_only(message_bytes):
    # The numpy syndromes that let a clean word skip reedsolo's decoder: zero on its
    # code words (one to six 255-byte blocks, the last one short), not after any one
    # byte error.
    rng = np.random.default_rng(message_bytes)
    word = bytes(blind._RS.encode(rng.integers(0, 256, message_bytes, np.uint8).tobytes()))
    assert blind._syndromes_vanish(word)
    for position in rng.choice(len(word), 30, replace=False):
        damaged = bytearray(word)
        damaged[position] ^= int(rng.integers(1, 256))
        assert not blind._syndromes_vanish(bytes(damaged))


def test_ours_code_decodes_beyond_its_capacity_when_the_wrong_bytes_are_the_least_reliable():
    _, _, disparity = generated_scene((240, 320), seed=8)
    bits = blind.disparity_code(disparity)
    clean = blind.disparity_from_code(bits, disparity.shape)
    rng = np.random.default_rng(10)
    n_bytes = bits.size // 8
    # 16 byte errors: beyond the 10 that plain decoding corrects, within the 20 erasures.
    bytes_hit = rng.choice(n_bytes, 16, replace=False)
    wrong_bits = bytes_hit * 8 + rng.integers(0, 8, bytes_hit.size)
    received = bits.copy()
    received[wrong_bits] ^= 1
    assert blind._checked_body(received, bits.size) is None
    reliability = np.full(bits.size, 0.9)
    reliability[wrong_bits] = 0.1  # the copies disagreed on those bits
    body = blind._erasure_decoded(received, reliability)
    assert body is not None
    np.testing.assert_array_equal(blind._compact_surface(body, disparity.shape), clean)
    # Reliabilities that point at other bytes do not help.
    elsewhere = np.setdiff1d(np.arange(n_bytes), bytes_hit)[:20]
    misleading = np.full(bits.size, 0.9)
    misleading[elsewhere * 8] = 0.1
    assert blind._erasure_decoded(received, misleading) is None


def test_ours_resynchronises_a_rotation_and_finds_nothing_in_a_rotated_unmarked_image():
    from stereo_coding_node.channel import rotate

    left, _, disparity = generated_scene((240, 320), seed=12)
    coded = blind.encode(left, disparity, key='k')
    assert not blind.decode(rotate(coded, 7.3), key='k').found  # without resynchronisation
    detection, angle = blind.decode_rotated(rotate(coded, 7.3), key='k', max_degrees=10.0)
    assert detection.found and abs(angle + 7.3) < 0.051
    # Twice resampled, ~2.3 copies a bit at 320x240: measured 7 of 512 bits corrected.
    assert np.mean(detection.bits != blind.disparity_code(disparity, left)) < 0.03
    unmarked, _ = blind.decode_rotated(rotate(left, 7.3), key='k', max_degrees=10.0)
    assert not unmarked.found


# --- inputs checked before any work ---------------------------------------------------


def _disparity_with(value, at=(100, 100)):
    disparity = np.full((240, 320), 12.0)
    disparity[at] = value
    return disparity


def test_known_disparity_marks_values_below_min_disparity_unknown():
    disparity = _disparity_with(-1.0)
    disparity[0, 0] = np.nan
    disparity[0, 1] = -np.inf
    known = known_disparity(disparity, 0.0)
    assert np.isnan(known[100, 100]) and np.isnan(known[0, 0]) and np.isnan(known[0, 1])
    assert np.sum(np.isfinite(known)) == disparity.size - 3


@pytest.mark.parametrize('value, reason', [(np.inf, 'inf'), (1e9, '1e\\+09'), (321.0, '321')])
def test_known_disparity_refuses_infinite_or_wider_than_the_image(value, reason):
    with pytest.raises(CodingError, match=f'1 disparities .* width 320 px \\(up to {reason}'):
        known_disparity(_disparity_with(value), 0.0)


@pytest.mark.parametrize('min_disparity', [np.nan, np.inf, -np.inf])
def test_known_disparity_refuses_a_min_disparity_that_is_not_finite(min_disparity):
    with pytest.raises(CodingError, match='min_disparity'):
        known_disparity(_disparity_with(12.0), min_disparity)


def _png_header_declaring(width, height):
    def chunk(kind, data):
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack('>I', len(data)) + kind + data + struct.pack('>I', crc)

    header = struct.pack('>IIBBBBB', width, height, 8, 0, 0, 0, 0)
    return b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', header) + chunk(b'IDAT', zlib.compress(b'\0'))


def test_compressed_image_size_is_read_from_the_header_alone():
    assert compressed_image_size(_png_header_declaring(16000, 16000)) == (16000, 16000)
    _, jpeg_bytes = cv2.imencode('.jpg', np.zeros((24, 40), np.uint8))
    assert compressed_image_size(jpeg_bytes.tobytes()) == (40, 24)
    _, png_bytes = cv2.imencode('.png', np.zeros((24, 40), np.uint8))
    assert compressed_image_size(png_bytes.tobytes()) == (40, 24)
    for data in (b'', b'\x00\x01not a jpeg', jpeg_bytes.tobytes()[:4]):
        with pytest.raises(CodingError, match='does not decode as JPEG or PNG'):
            compressed_image_size(data)
