"""Calibration files: camera_calibration_parsers per camera, the rig file with poses."""

import numpy as np
import pytest
import yaml

from calib_node.rig_files import read_rig
from vgm_common.calibration_io import (
    read_calibration,
    read_camera_yaml,
    stereo_rectification,
    write_calibration,
)
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput
from vgm_common.geometry import make_transform, rpy_to_matrix
from vgm_common.topics import OPTICAL_FRAMES


def _rig():
    K = np.array([[800.0, 0.0, 320.5], [0.0, 790.0, 240.25], [0.0, 0.0, 1.0]])
    return {
        name: PinholeCamera(
            640,
            480,
            K,
            [-0.1, 0.02, 0.001, -0.002, 0.0],
            make_transform(rpy_to_matrix(3.0, 0.1 * i, 0.2), [i, 0.5, 1.2]),
        )
        for i, name in enumerate(('left', 'right', 'aux'))
    }


def test_rig_round_trip(tmp_path):
    rig = _rig()
    P_right = np.hstack([rig['right'].K, [[-800.0 * 0.14], [0.0], [0.0]]])
    path = write_calibration(
        tmp_path,
        rig,
        OPTICAL_FRAMES,
        rectification={'right': (rpy_to_matrix(0.01, 0, 0), P_right)},
        quality={'left': {'rms_px': 0.12}},
    )
    loaded = read_calibration(path)
    assert set(loaded) == set(rig)
    for name, (camera, _, _) in loaded.items():
        np.testing.assert_allclose(camera.K, rig[name].K, atol=0)
        np.testing.assert_allclose(camera.D, rig[name].D, atol=0)
        np.testing.assert_allclose(camera.T_base_camera, rig[name].T_base_camera, atol=1e-12)
    np.testing.assert_allclose(loaded['right'][2], P_right, atol=0)
    # The per-camera file is plain camera_calibration_parsers YAML.
    document = yaml.safe_load((tmp_path / 'right.yaml').read_text())
    assert document['camera_name'] == 'stereo_right'
    assert document['projection_matrix']['rows'] == 3
    camera, R, P = read_camera_yaml(tmp_path / 'right.yaml')
    np.testing.assert_allclose(P, P_right, atol=0)
    assert read_calibration(tmp_path)['left'][0].width == 640  # the directory works too


@pytest.mark.parametrize(
    'edit, key',
    [
        (lambda d: d['cameras']['left'].pop('pose_in_base_link'), 'cameras.left'),
        (
            lambda d: d['cameras']['left']['camera_matrix']['data'].__setitem__(0, float('nan')),
            'cameras.left',
        ),
        (
            lambda d: d['cameras']['aux']['pose_in_base_link'].__setitem__(
                'orientation', [0, 0, 0, 2]
            ),
            'cameras.aux',
        ),
        (lambda d: d.pop('cameras'), 'calibration_file'),
    ],
)
def test_malformed_rig_file_names_the_key(tmp_path, edit, key):
    path = write_calibration(tmp_path, _rig(), OPTICAL_FRAMES)
    document = yaml.safe_load(path.read_text())
    edit(document)
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(InvalidInput) as error:
        read_calibration(path)
    assert error.value.key == key


def test_missing_file_is_invalid_input(tmp_path):
    with pytest.raises(InvalidInput, match='cannot read'):
        read_calibration(tmp_path / 'nope.yaml')


def test_stereo_rectification_puts_the_baseline_in_the_right_projection():
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    R = rpy_to_matrix(np.pi, 0.0, 0.0)  # looking down
    left = PinholeCamera(640, 480, K, np.zeros(5), make_transform(R, [0.0, 0.0, 1.0]))
    right = PinholeCamera(
        640, 480, K, np.zeros(5), make_transform(R @ rpy_to_matrix(0, 0.05, 0), [0.14, 0.0, 1.0])
    )
    rectified = stereo_rectification(left, right)
    (R1, P1), (R2, P2) = rectified['left'], rectified['right']
    baseline = -P2[0, 3] / P2[0, 0]
    assert baseline == pytest.approx(0.14, rel=1e-9)
    # A base point projects to the same row in both rectified images.
    point = np.array([0.05, 0.1, 0.0])
    rows = []
    for camera, Rr, P in ((left, R1, P1), (right, R2, P2)):
        x = Rr @ camera.to_camera(point[None])[0]
        rows.append((P @ np.append(x, 1.0))[1] / x[2])
    assert rows[0] == pytest.approx(rows[1], abs=1e-9)


def test_calib_node_reads_a_saved_rig_with_left_right_rectified_again(tmp_path):
    rig = _rig()
    stored = {'aux': (np.eye(3), np.hstack([rig['aux'].K, np.zeros((3, 1))]))}
    path = write_calibration(tmp_path, rig, OPTICAL_FRAMES, stored)
    cameras, rectification = read_rig(path, ('left', 'right', 'aux'))
    assert np.allclose(cameras['right'].T_base_camera, rig['right'].T_base_camera)
    expected = stereo_rectification(rig['left'], rig['right'])
    for name in ('left', 'right'):
        assert np.allclose(rectification[name][1], expected[name][1])
    assert np.allclose(rectification['aux'][1], stored['aux'][1])
    write_calibration(tmp_path / 'two', {n: rig[n] for n in ('left', 'right')}, OPTICAL_FRAMES)
    with pytest.raises(InvalidInput, match='lacks aux'):
        read_rig(tmp_path / 'two', ('left', 'right', 'aux'))
