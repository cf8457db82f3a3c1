"""Round trips of every message conversion, and rejection of malformed messages."""

import numpy as np
import pytest
from sensor_msgs.msg import Image

from vgm_common.camera_model import PinholeCamera
from vgm_common.conversions import (
    camera_info_rectification,
    camera_info_to_camera,
    camera_to_camera_info,
    image_to_grey,
    image_to_numpy,
    matrices_to_path,
    ns_to_stamp,
    numpy_to_disparity_image,
    numpy_to_image,
    path_to_matrices,
    pointcloud2_to_points,
    points_to_pointcloud2,
    pose_to_matrix,
    stamp_to_ns,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import make_transform, rpy_to_matrix

rng = np.random.default_rng(3)


@pytest.mark.parametrize(
    'encoding, dtype, shape',
    [
        ('mono8', np.uint8, (48, 64)),
        ('mono16', np.uint16, (48, 64)),
        ('rgb8', np.uint8, (48, 64, 3)),
        ('32FC1', np.float32, (48, 64)),
    ],
)
def test_image_round_trip(encoding, dtype, shape):
    array = (rng.random(shape) * 200).astype(dtype)
    if dtype == np.float32:
        array[0, :5] = np.nan  # REP 118: NaN = no depth
    msg = numpy_to_image(array, encoding, 1_500_000_123, 'cam')
    back = image_to_numpy(msg)
    np.testing.assert_array_equal(back, array)
    assert back.dtype == dtype and msg.header.frame_id == 'cam'
    assert stamp_to_ns(msg.header.stamp) == 1_500_000_123
    array[1, 1] = 7  # the message does not alias the caller's array
    np.testing.assert_array_equal(image_to_numpy(msg)[1, 1], back[1, 1])


def test_image_with_row_padding_and_big_endian():
    values = np.arange(12, dtype='>u2').reshape(3, 4)
    padded = np.zeros((3, 10), dtype=np.uint8)
    padded[:, :8] = values.view(np.uint8).reshape(3, 8)
    msg = Image(
        height=3, width=4, encoding='mono16', is_bigendian=1, step=10, data=padded.tobytes()
    )
    np.testing.assert_array_equal(image_to_numpy(msg), values.astype(np.uint16))


@pytest.mark.parametrize(
    'field, value, words',
    [
        ('encoding', 'yuv422_weird', 'encoding'),
        ('step', 10, 'step'),
        ('data', b'\x00' * 5, 'bytes'),
        ('width', 0, 'empty'),
    ],
)
def test_malformed_image_is_rejected(field, value, words):
    msg = numpy_to_image(np.zeros((4, 6), np.uint8), 'mono8', 0, 'cam')
    setattr(msg, field, value)
    with pytest.raises(InvalidInput, match=words):
        image_to_numpy(msg)


def test_camera_info_round_trip_and_bad_k():
    K = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    camera = PinholeCamera(640, 480, K, [0.1, -0.05, 0.001, 0.002, 0.01], np.eye(4))
    msg = camera_to_camera_info(camera, 42, 'stereo_left_optical_frame')
    back = camera_info_to_camera(msg)
    np.testing.assert_array_equal(back.K, K)
    np.testing.assert_array_equal(back.D, camera.D)
    assert (back.width, back.height, msg.distortion_model) == (640, 480, 'plumb_bob')
    msg.k[0] = float('nan')
    with pytest.raises(InvalidInput, match='K'):
        camera_info_to_camera(msg)
    msg.k[0] = 0.0
    with pytest.raises(InvalidInput, match='K'):
        camera_info_to_camera(msg)


def _camera_info():
    K = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    camera = PinholeCamera(640, 480, K, [0.1, -0.05, 0.001, 0.002, 0.01], np.eye(4))
    return camera_to_camera_info(camera, 42, 'stereo_left_optical_frame')


@pytest.mark.parametrize(
    'field, value, words',
    [
        ('k', [500.0, 0, 320, 3.0, 510, 240, 0, 0, 1], 'upper-triangular'),
        ('d', [], 'D has 0 coefficients'),
        ('d', [0.01] * 14, 'D has 14 coefficients'),
        ('distortion_model', 'kannala_brandt', "unsupported distortion model 'kannala_brandt'"),
        ('distortion_model', 'rational_polynomial', 'rational_polynomial takes 8'),
    ],
)
def test_camera_info_with_a_bad_k_or_d_is_rejected(field, value, words):
    msg = _camera_info()
    setattr(msg, field, value)
    with pytest.raises(InvalidInput, match=words):
        camera_info_to_camera(msg)


def test_camera_info_without_a_model_is_undistorted():
    msg = _camera_info()
    msg.distortion_model, msg.d = '', []
    np.testing.assert_array_equal(camera_info_to_camera(msg).D, np.zeros(5))
    msg.d = [0.1, 0, 0, 0, 0]
    with pytest.raises(InvalidInput, match='no distortion_model'):
        camera_info_to_camera(msg)


def test_camera_info_rectification():
    msg = _camera_info()
    R, P = camera_info_rectification(msg)
    np.testing.assert_array_equal(R, np.eye(3))
    msg.r = [0.0] * 9  # "not set": the identity
    np.testing.assert_array_equal(camera_info_rectification(msg)[0], np.eye(3))
    msg.r = [2.0, 0, 0, 0, 1, 0, 0, 0, 1]
    with pytest.raises(InvalidInput, match='R is not a rotation'):
        camera_info_rectification(msg)
    msg = _camera_info()
    msg.p = [0.0] * 12
    with pytest.raises(InvalidInput, match='P is not a projection'):
        camera_info_rectification(msg)
    msg.p = [float('inf')] * 12
    with pytest.raises(InvalidInput, match='non-finite'):
        camera_info_rectification(msg)


def test_pointcloud_round_trip():
    points = rng.normal(size=(100, 3)).astype(np.float32)
    msg = points_to_pointcloud2(points, 5, 'base_link')
    np.testing.assert_array_equal(pointcloud2_to_points(msg), points)
    assert msg.width == 100 and msg.point_step == 12


def test_path_round_trip_and_rejections():
    poses = np.stack(
        [
            make_transform(rpy_to_matrix(*rng.uniform(-3, 3, 3)), rng.normal(size=3))
            for _ in range(20)
        ]
    )
    msg = matrices_to_path(poses, 7, 'base_link')
    np.testing.assert_allclose(path_to_matrices(msg), poses, atol=1e-12)
    msg.poses[3].pose.orientation.w = 5.0
    with pytest.raises(InvalidInput, match='quaternion'):
        path_to_matrices(msg)
    msg.poses[3].pose.position.x = float('inf')
    with pytest.raises(InvalidInput, match='non-finite'):
        pose_to_matrix(msg.poses[3].pose)
    msg.poses = []
    with pytest.raises(InvalidInput, match='empty'):
        path_to_matrices(msg)


def test_stamp_conversion():
    for ns in (0, 1, 999_999_999, 1_000_000_000, 1_732_000_000_123_456_789):
        assert stamp_to_ns(ns_to_stamp(ns)) == ns


def test_image_to_grey_puts_every_encoding_on_one_scale():
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    expected = grey.astype(np.float32)
    np.testing.assert_array_equal(image_to_grey(numpy_to_image(grey, 'mono8', 1, 'f')), expected)
    mono16 = grey.astype(np.uint16) * 257  # 255 -> 65535
    np.testing.assert_allclose(
        image_to_grey(numpy_to_image(mono16, 'mono16', 1, 'f')), expected, atol=1e-4
    )
    rgb = np.stack([grey] * 3, axis=2)
    for encoding in ('rgb8', 'bgr8'):
        np.testing.assert_allclose(
            image_to_grey(numpy_to_image(rgb, encoding, 1, 'f')), expected, atol=1e-4
        )
    with pytest.raises(InvalidInput, match="encoding '32FC1'"):
        image_to_grey(numpy_to_image(expected, '32FC1', 1, 'f'))


def test_disparity_image_as_stereo_image_proc_fills_it():
    disparity = np.array([[np.nan, 2.5], [7.0, np.nan]], np.float32)
    msg = numpy_to_disparity_image(disparity, 5, 'cam', 700.0, 0.12, (0.0, 64.0), 0.0625)
    assert (msg.f, msg.min_disparity, msg.max_disparity, msg.delta_d) == (700.0, 0.0, 64.0, 0.0625)
    assert msg.t == pytest.approx(0.12)  # the baseline: `T=` would be dropped silently
    assert (msg.valid_window.width, msg.valid_window.height) == (2, 2)
    assert image_to_numpy(msg.image).tolist() == [[-1.0, 2.5], [7.0, -1.0]]
    windowed = numpy_to_disparity_image(disparity, 5, 'cam', 1, 1, (-8.0, 8.0), 1, (1, 0, 1, 2))
    assert image_to_numpy(windowed.image)[0, 0] == -9.0  # below a negative minimum
    assert (windowed.valid_window.x_offset, windowed.valid_window.width) == (1, 1)
