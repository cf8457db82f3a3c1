"""The coding nodes' steps without ROS (stereo_coding_node.coding): a generated scene's
disparity coded and recovered by each method against its ground truth, no watermark in
an unmarked image, the thesis method's key file written and reloaded when it changes,
bad input refused, and the figures timed by the injected clock."""

import os

import numpy as np
import pytest
from stereo_coding_node.coding import KeyFile, decode_image, encode_image
from stereo_coding_node.errors import CodingError, KeyFileError
from stereo_coding_node.scenes import generated_scene
from stereo_coding_node.settings import CodingSettings

SHAPE = (240, 320)


def scene(seed):
    """(left, disparity [px] with -1 where unknown, the true disparity)."""
    left, _, truth = generated_scene(SHAPE, seed=seed)
    return left, np.where(np.isfinite(truth), truth, -1.0), truth


def rms_px(decoded, truth):
    known = np.isfinite(truth)
    assert np.all(np.isfinite(decoded.disparity_px[known]))
    return float(np.sqrt(np.mean((decoded.disparity_px[known] - truth[known]) ** 2)))


def test_ours_hides_the_disparity_and_finds_it_again_only_where_it_was_hidden():
    left, disparity, truth = scene(3)
    settings = CodingSettings()
    coded = encode_image(left, disparity, 0.0, settings)
    assert coded.image.dtype == np.uint8 and coded.image.shape == SHAPE
    assert float(coded.figures['psnr [dB]']) >= 42.0  # QIM step 28: about 43 dB
    assert coded.figures['payload bits'] > 0 and coded.figures['fine payload bits'] > 0
    decoded = decode_image(coded.image, settings, KeyFile())
    assert decoded.found and decoded.figures['watermark'] == 'found'
    assert rms_px(decoded, truth) < 1.5  # measured 0.98 px (fine layer, no channel loss)
    assert np.array_equal(decoded.left, coded.image)  # blind: the coded image is the host
    assert decoded.right.shape == SHAPE and decoded.right.dtype == np.uint8
    for image, key in ((left, 'vgm-stereo'), (coded.image, 'another key')):
        unmarked = decode_image(image, CodingSettings(key=key), KeyFile())
        assert not unmarked.found and unmarked.figures['watermark'] == 'none'
        assert unmarked.disparity_px is None and unmarked.right is None


def test_thesis_writes_its_key_and_the_decoder_reloads_it_when_it_changes(tmp_path):
    key_path = str(tmp_path / 'key.npz')
    settings = CodingSettings(method='thesis', key_file=key_path)
    key_file = KeyFile()
    for seed in (1, 2):  # each frame's key replaces the last one
        left, disparity, truth = scene(seed)
        coded = encode_image(left, disparity, 0.0, settings)
        assert os.path.exists(key_path) and os.listdir(tmp_path) == ['key.npz']  # renamed
        decoded = decode_image(coded.image, settings, key_file)
        assert decoded.found and rms_px(decoded, truth) < 0.1  # measured 0.04 px
    assert key_file.key(key_path) is key_file.key(key_path)  # unchanged: not read again


def test_bad_input_is_refused_naming_what_is_wrong(tmp_path):
    left, disparity, _ = scene(0)
    with pytest.raises(CodingError, match='differ in size'):
        encode_image(left, disparity[:, :-1], 0.0, CodingSettings())
    with pytest.raises(CodingError, match='needs key_file'):
        encode_image(left, disparity, 0.0, CodingSettings(method='thesis'))
    with pytest.raises(CodingError, match='cannot write key_file'):
        encode_image(
            left, disparity, 0.0, CodingSettings(method='thesis', key_file=str(tmp_path / 'no/k'))
        )
    with pytest.raises(CodingError, match='needs key_file'):
        decode_image(left, CodingSettings(method='thesis'), KeyFile())
    with pytest.raises(KeyFileError, match='does not exist'):
        KeyFile().key(str(tmp_path / 'missing.npz'))


def test_the_figures_time_the_coding_by_the_injected_clock():
    left, disparity, _ = scene(0)
    ticks = iter([10.0, 10.25, 20.0, 20.0125])
    coded = encode_image(left, disparity, 0.0, CodingSettings(), clock=lambda: next(ticks))
    assert coded.figures['encode [ms]'] == '250.0'
    decoded = decode_image(coded.image, CodingSettings(), KeyFile(), clock=lambda: next(ticks))
    assert decoded.figures['decode [ms]'] == '12.5'
