"""calib_node's rig calibration core (calibrate.py) on the default scenario's true cameras
and chart poses: exact recovery without noise, statistically consistent errors with noise,
the OpenCV reference, the thesis method's plumb_bob conversion, degenerate input."""

import numpy as np
import pytest

from calib_node.calibrate import (
    CalibrationError,
    GAOptions,
    calibrate_camera_lm,
    calibrate_rig,
    degeneracy,
    division_to_plumb_bob,
)
from calib_node.chart_detection import chart_points
from sensor_sim.scenario import load_scenario, resolve_scenario_path
from vgm_common.camera_model import distort_division, distort_normalized

SCENARIO = load_scenario(resolve_scenario_path('default'))
CAMERAS = SCENARIO.cameras
CHART = chart_points(
    SCENARIO.calibration.rows, SCENARIO.calibration.cols, SCENARIO.calibration.spacing
)


def observations(sigma=0.0, seed=0, names=('left', 'right', 'aux')):
    rng = np.random.default_rng(seed)
    out = {}
    for name in names:
        camera = CAMERAS[name]
        points = np.concatenate(
            [CHART @ T[:3, :3].T + T[:3, 3] for T in SCENARIO.calibration.T_base_chart]
        )
        pixels, depth = camera.project(points)
        assert np.all(depth > 0) and np.all((pixels > 0) & (pixels < [640, 480]))
        out[name] = (points, pixels + sigma * rng.standard_normal(pixels.shape), (640, 480))
    return out


def test_noise_free_lm_recovers_every_camera_exactly():
    result = calibrate_rig(observations(), 'lm')
    for name, fit in result.fits.items():
        true = CAMERAS[name]
        np.testing.assert_allclose(fit.K, true.K, rtol=1e-6, err_msg=name)
        np.testing.assert_allclose(fit.D, true.D, atol=1e-6, err_msg=name)
        np.testing.assert_allclose(fit.T_base_camera, true.T_base_camera, atol=1e-7)
        assert fit.rms_px < 1e-6 and fit.points == 540


def test_noisy_lm_is_within_its_standard_errors_and_matches_opencv():
    sigma = 0.5
    data = observations(sigma, seed=3)
    # The same parameter set as OpenCV's (select_model would drop p1, p2 here: the
    # default scenario's lenses have none).
    lm = calibrate_rig(data, 'lm', select_model=False).fits
    reference = calibrate_rig(data, 'opencv').fits
    selected = calibrate_rig(data, 'lm').fits
    assert all(np.all(f.D[2:4] == 0) for f in selected.values())
    for name, fit in lm.items():
        true = CAMERAS[name]
        # residual RMS per point of 2-D noise sigma per coordinate: sqrt(2) sigma
        assert fit.rms_px == pytest.approx(np.sqrt(2) * sigma, rel=0.1)
        for key, (i, j) in {'fx': (0, 0), 'fy': (1, 1), 'cx': (0, 2), 'cy': (1, 2)}.items():
            assert abs(fit.K[i, j] - true.K[i, j]) < 4 * fit.std[key], (name, key)
        assert np.linalg.norm(fit.T_base_camera[:3, 3] - true.T_base_camera[:3, 3]) < 0.005
        # cv2.calibrateCamera minimises the same error from the same start: same optimum
        np.testing.assert_allclose(reference[name].K, fit.K, rtol=1e-4, err_msg=name)
        assert reference[name].rms_px == pytest.approx(fit.rms_px, rel=1e-3)


def test_lm_started_from_the_ga_recovers_the_cameras():
    small = GAOptions(population=60, generations=30, network_epochs=200)
    result = calibrate_rig(
        observations(names=('left', 'right')), 'lm', seed=1, lm_start='ga', ga=small
    )
    for name, fit in result.fits.items():
        np.testing.assert_allclose(fit.K, CAMERAS[name].K, rtol=1e-6, err_msg=name)


def test_thesis_method_runs_and_reports_its_error():
    small = GAOptions(population=40, generations=20, network_epochs=100)
    data = observations(names=('left', 'right'))
    result = calibrate_rig(data, 'lxpm_ga', seed=2, ga=small)
    for name, fit in result.fits.items():
        assert np.all(np.isfinite(fit.K)) and np.all(np.isfinite(fit.D))
        assert np.allclose(fit.T_base_camera[:3, :3] @ fit.T_base_camera[:3, :3].T, np.eye(3))
        # the reported RMS is the RMS of the published (plumb_bob) camera
        K, D, T = fit.K, fit.D, np.linalg.inv(fit.T_base_camera)
        camera_points = data[name][0] @ T[:3, :3].T + T[:3, 3]
        xy = distort_normalized(camera_points[:, :2] / camera_points[:, 2:], D)
        pixels = xy * [K[0, 0], K[1, 1]] + K[:2, 2]
        rms = np.sqrt(np.mean(np.sum((pixels - data[name][1]) ** 2, axis=1)))
        assert fit.rms_px == pytest.approx(rms, rel=1e-6)


# Largest disagreement [px at f = 600] over the image allowed for kappa r_max^2 and k3.
CONVERSION_TOLERANCE = {
    (0.02, False): 0.01,
    (0.1, False): 0.25,
    (0.3, False): 2.5,
    (0.02, True): 0.001,
    (0.1, True): 0.03,
    (0.3, True): 0.5,
}


@pytest.mark.parametrize('kappa_r2, fit_k3', list(CONVERSION_TOLERANCE))
def test_division_model_converted_to_plumb_bob(kappa_r2, fit_k3):
    max_radius = 0.7
    kappa = kappa_r2 / max_radius**2
    D, residual = division_to_plumb_bob(kappa, max_radius, fit_k3)
    assert (D[4] != 0) == fit_k3
    xy = np.random.default_rng(4).uniform(-0.49, 0.49, (500, 2))  # |xy| <= 0.7
    difference = np.abs(distort_normalized(xy, D) - distort_division(xy, kappa)).max()
    assert difference <= residual + 1e-12
    assert 600 * difference < CONVERSION_TOLERANCE[kappa_r2, fit_k3]
    if kappa_r2 <= 0.02:
        assert D[0] == pytest.approx(-kappa, rel=0.05)  # k1 -> -kappa for small kappa r^2


def test_degenerate_and_too_few_points_are_refused():
    coplanar = observations(names=('left',))
    T = SCENARIO.calibration.T_base_chart[0]
    points = np.concatenate(
        [CHART @ T[:3, :3].T + T[:3, 3] + shift * T[:3, 0] for shift in (0.0, 0.01, 0.02)]
    )  # moved within its plane
    assert 'one plane' in degeneracy(points)
    pixels = CAMERAS['left'].project(points)[0]
    with pytest.raises(CalibrationError, match='one plane'):
        calibrate_rig({'left': (points, pixels, (640, 480))}, 'lm')
    assert 'at least' in degeneracy(points[:5])
    assert degeneracy(coplanar['left'][0]) == ''
    with pytest.raises(ValueError, match='method'):
        calibrate_rig(coplanar, 'zhang')


def test_lm_camera_with_fixed_tangential_terms():
    data = observations(names=('aux',))['aux']  # aux has no distortion
    fit = calibrate_camera_lm(*data, fit_tangential=False)
    assert fit.D[2] == fit.D[3] == 0.0
    np.testing.assert_allclose(fit.K, CAMERAS['aux'].K, rtol=1e-6)
