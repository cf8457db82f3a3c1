"""The lens models beyond plumb_bob in vgm_common: rational_polynomial (OpenCV's
CALIB_RATIONAL_MODEL) and equidistant (cv2.fisheye). Projection against OpenCV, the
analytic Jacobian against finite differences, calibration files, CameraInfo and stereo
rectification, and bad input refused naming the model."""

import cv2
import numpy as np
import pytest

from vgm_common.calibration_io import read_calibration, stereo_rectification, write_calibration
from vgm_common.camera_model import PinholeCamera, project_points
from vgm_common.conversions import camera_info_to_camera, camera_to_camera_info
from vgm_common.errors import InvalidInput
from vgm_common.geometry import make_transform, rpy_to_matrix
from vgm_common.topics import OPTICAL_FRAMES

K = np.array([[420.0, 0.0, 330.0], [0.0, 421.0, 236.0], [0.0, 0.0, 1.0]])
LENSES = {
    'plumb_bob': [-0.25, 0.06, 1e-3, -5e-4, 0.0],
    'rational_polynomial': [0.6, 0.05, 1e-3, -1.5e-3, 0.0, 1.1, 0.08, 0.0],
    'equidistant': [0.03, -0.008, 0.002, -0.0005],
}


def _points(rng, count=200, half_angle_deg=70.0):
    """Points 1..3 m away within ``half_angle_deg`` of the axis (camera frame)."""
    angle = np.radians(rng.uniform(0, half_angle_deg, count))
    azimuth = rng.uniform(-np.pi, np.pi, count)
    rays = np.column_stack(
        [np.sin(angle) * np.cos(azimuth), np.sin(angle) * np.sin(azimuth), np.cos(angle)]
    )
    return rays * rng.uniform(1.0, 3.0, count)[:, None]


@pytest.mark.parametrize('model', ['rational_polynomial', 'equidistant'])
def test_projection_agrees_with_opencv_and_undistortion_inverts_it(model):
    rng = np.random.default_rng(1)
    half_angle = 45.0 if model == 'rational_polynomial' else 75.0
    points = _points(rng, half_angle_deg=half_angle)
    camera = PinholeCamera(640, 480, K, LENSES[model], np.eye(4), model)
    pixels, _ = camera.project(points)
    if model == 'equidistant':
        expected = cv2.fisheye.projectPoints(
            points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.array(LENSES[model])
        )[0]
    else:
        expected = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, np.array(LENSES[model]))[
            0
        ]
    np.testing.assert_allclose(pixels, expected.reshape(-1, 2), atol=1e-9)
    xy = camera.undistort_pixels(pixels)
    np.testing.assert_allclose(xy, points[:, :2] / points[:, 2:], atol=1e-10)


@pytest.mark.parametrize('model', list(LENSES))
def test_projection_jacobian_matches_finite_differences(model):
    rng = np.random.default_rng(2)
    points = _points(rng, 40, 40.0) + [0.0, 0.0, 0.5]
    x = np.concatenate(
        [[0.05, -0.1, 0.02], [0.01, -0.02, 0.1], [420, 421, 330, 236], LENSES[model]]
    )

    def project(x):
        Kx = np.array([[x[6], 0, x[8]], [0, x[7], x[9]], [0, 0, 1.0]])
        return project_points(points, x[:3], x[3:6], Kx, x[10:], model)

    _, J = project(x)
    assert J.shape == (2 * len(points), len(x))
    numeric = np.zeros_like(J)
    for i in range(len(x)):
        step = np.zeros(len(x))
        step[i] = 1e-6 * max(1.0, abs(x[i]))
        numeric[:, i] = (project(x + step)[0] - project(x - step)[0]).ravel() / (2 * step[i])
    np.testing.assert_allclose(J, numeric, atol=1e-5 * np.abs(numeric).max())


@pytest.mark.parametrize('model', list(LENSES))
def test_calibration_file_and_camera_info_keep_the_model(tmp_path, model):
    rig = {
        name: PinholeCamera(
            640,
            480,
            K,
            LENSES[model],
            make_transform(rpy_to_matrix(3.0, 0.0, 0.0), [0.1 * i, 0.0, 1.0]),
            model,
        )
        for i, name in enumerate(('left', 'right'))
    }
    loaded = read_calibration(write_calibration(tmp_path, rig, OPTICAL_FRAMES))
    for name, (camera, _, _) in loaded.items():
        assert camera.distortion_model == model
        np.testing.assert_array_equal(camera.D, rig[name].D)
        msg = camera_to_camera_info(camera, 0, OPTICAL_FRAMES[name])
        assert msg.distortion_model == model and len(msg.d) == len(LENSES[model])
        back = camera_info_to_camera(msg)
        assert back.distortion_model == model
        np.testing.assert_array_equal(back.D, camera.D)
    # The rectified pair: rows agree for a point seen by both (either OpenCV function).
    rectification = stereo_rectification(rig['left'], rig['right'])
    point = np.array([[0.05, 0.02, 0.0]])
    rows = []
    for name in ('left', 'right'):
        R, P = rectification[name]
        xy = rig[name].undistort_pixels(rig[name].project(point)[0])
        ray = R @ np.array([*xy[0], 1.0])
        rows.append(P[1, 1] * ray[1] / ray[2] + P[1, 2])
    assert abs(rows[0] - rows[1]) < 1e-6


def test_bad_model_input_is_refused_naming_the_model():
    camera = PinholeCamera(640, 480, K, LENSES['equidistant'], np.eye(4), 'equidistant')
    msg = camera_to_camera_info(camera, 0, 'cam')
    msg.d = msg.d[:3]
    with pytest.raises(InvalidInput, match='equidistant takes 4'):
        camera_info_to_camera(msg)
    msg.distortion_model = 'kannala_brandt'
    with pytest.raises(InvalidInput, match="'kannala_brandt'"):
        camera_info_to_camera(msg)
    with pytest.raises(InvalidInput, match='rational_polynomial model takes 8'):
        PinholeCamera(640, 480, K, [0.1] * 5, np.eye(4), 'rational_polynomial')
    other = PinholeCamera(640, 480, K, LENSES['plumb_bob'], make_transform(np.eye(3), [0.1, 0, 0]))
    with pytest.raises(InvalidInput, match='equidistant left and a plumb_bob right'):
        stereo_rectification(camera, other)


def test_sfs_stereo_rectification_maps_take_an_equidistant_pair():
    """Each rectified pixel's map entry is the raw pixel of its ray (to the map's float32
    precision), so the pair's rows agree as test_calibration_file_and_camera_info_keep_the_model
    checks for the rectification itself; a division camera is refused naming it."""
    from sfs_stereo_node.rectify import rectification_maps

    model = 'equidistant'
    rig = [
        PinholeCamera(
            640,
            480,
            K,
            LENSES[model],
            make_transform(rpy_to_matrix(3.0, 0.0, 0.0), [0.1 * i, 0.0, 1.0]),
            model,
        )
        for i in range(2)
    ]
    rectification = stereo_rectification(*rig)
    (R1, P1), (R2, P2) = rectification['left'], rectification['right']
    pair = rectification_maps(K, rig[0].D, R1, P1, K, rig[1].D, R2, P2, (640, 480), (model, model))
    rng = np.random.default_rng(3)
    u, v = rng.integers(100, 540, 50), rng.integers(100, 380, 50)
    for camera, (R, P), maps in zip(
        rig, (rectification['left'], rectification['right']), (pair.maps_left, pair.maps_right)
    ):
        rays = np.linalg.solve(P[:, :3], np.vstack([u, v, np.ones(50)])).T @ np.asarray(R)
        raw, _ = camera.project(camera.centre_base + rays @ camera.T_base_camera[:3, :3].T)
        mapped = np.column_stack([maps[0][v, u], maps[1][v, u]])
        np.testing.assert_allclose(mapped, raw, atol=0.01)
    with pytest.raises(InvalidInput, match="'division'"):
        rectification_maps(K, [0.1], R1, P1, K, rig[1].D, R2, P2, (640, 480), ('division', model))
