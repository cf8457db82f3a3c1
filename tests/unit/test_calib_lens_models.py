"""Calibration of generated rigs with rational_polynomial and equidistant lenses against
their truth, the model chosen by BIC among plumb_bob, rational_polynomial and
equidistant, or forced."""

import numpy as np
import pytest
from vgm_evaluation.rig_generator import draw_rig, true_corners

from calib_node.calibrate import CameraFit, bic, calibrate_rig, select_rig_models
from vgm_common.camera_model import PinholeCamera


def _noisy_observations(rig, noise_px, seed):
    from calib_node.chart_detection import chart_points

    rng = np.random.default_rng(seed)
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    observations = {}
    for name, camera in rig.cameras.items():
        points = np.concatenate([chart @ T[:3, :3].T + T[:3, 3] for T in rig.T_base_chart])
        pixels = np.concatenate([view[name] for view in true_corners(rig)])
        observations[name] = (
            points,
            pixels + rng.normal(0.0, noise_px, pixels.shape),
            (camera.width, camera.height),
        )
    return observations


@pytest.mark.parametrize(
    'model, seed',
    [('plumb_bob', 0), ('rational_polynomial', 0), ('rational_polynomial', 2), ('equidistant', 0)],
)
def test_bic_picks_the_lens_model_and_the_fit_recovers_the_lens(model, seed):
    """Generated rigs (every camera of ``model``: wide lenses for the two new ones),
    corner noise 0.2 px. fx, fy within 4 of their own standard errors (the rational
    model's focal length trades with its radial function: 1e-3..2e-1 relative); the
    noise-free corners predicted within 0.1 px RMS (the lens where the chart was seen;
    beyond it a rational fit extrapolates freely). The rational coefficients are not
    identifiable one by one (numerator and denominator trade: fits of the same lens
    differ by units in k1, k4), so only its p1, p2 are compared (0.5e-3); the
    equidistant coefficients are, within 0.05."""
    rig = draw_rig(seed, lens_model=model)
    observations = _noisy_observations(rig, 0.2, seed)
    result = calibrate_rig(observations, view_size=rig.rows * rig.cols)
    assert {f.model for f in result.fits.values()} == {model}
    truth_pixels = _noisy_observations(rig, 0.0, seed)
    for name, fit in result.fits.items():
        true = rig.cameras[name]
        assert fit.rms_px == pytest.approx(0.2 * np.sqrt(2), rel=0.1)
        for axis in (0, 1):
            error = abs(fit.K[axis, axis] - true.K[axis, axis])
            assert error < 4 * np.sqrt(fit.covariance[6 + axis, 6 + axis]), (name, error)
        estimate = PinholeCamera(
            true.width, true.height, fit.K, fit.D, fit.T_base_camera, fit.model
        )
        points, pixels, _ = truth_pixels[name]
        predicted = np.linalg.norm(estimate.project(points)[0] - pixels, axis=1)
        assert np.sqrt(np.mean(predicted**2)) < 0.1, name
        if model == 'equidistant':
            np.testing.assert_allclose(fit.D, true.D, atol=0.05)
        elif model == 'rational_polynomial':
            np.testing.assert_allclose(fit.D[2:4], true.D[2:4], atol=5e-4)
        else:
            assert fit.D[0] == pytest.approx(true.D[0], abs=0.02)


@pytest.mark.parametrize('model', ['rational_polynomial', 'equidistant'])
def test_a_forced_model_is_fitted_and_beats_plumb_bob_on_its_lens(model):
    rig = draw_rig(0, ('left', 'right'), lens_model=model)
    observations = _noisy_observations(rig, 0.2, 0)
    forced = calibrate_rig(observations, distortion_model=model)
    # rational: k1..k6 and p1, p2 (kept or not by BIC); equidistant: k1..k4
    assert forced.fits['left'].parameters in ((14,) if model == 'equidistant' else (16, 18))
    plumb_bob = calibrate_rig(observations, distortion_model='plumb_bob')
    for name in rig.cameras:
        assert forced.fits[name].model == model
        assert forced.fits[name].rms_px < 0.3
        # plumb_bob follows it worse than its extra coefficients cost (BIC)
        scores = [
            bic(f.rms_px**2 * f.points, 2 * f.points, f.parameters)
            for f in (forced.fits[name], plumb_bob.fits[name])
        ]
        assert scores[0] < scores[1] - 10, scores


def test_the_stereo_pair_shares_the_model_of_the_lowest_summed_bic():
    """left prefers equidistant a little, right rational_polynomial a lot: the pair takes
    rational_polynomial (one model: their rectification needs it); aux chooses alone."""

    def fit(model, rms_px, parameters=14):
        return CameraFit(
            np.eye(3), np.zeros(4), np.eye(4), rms_px, 500, {}, None, model, parameters
        )

    candidates = {
        'left': {'equidistant': fit('equidistant', 0.300), 'rational_polynomial': fit('r', 0.301)},
        'right': {'equidistant': fit('equidistant', 0.40), 'rational_polynomial': fit('r', 0.30)},
        'aux': {'equidistant': fit('equidistant', 0.30), 'rational_polynomial': fit('r', 0.31)},
    }
    chosen = select_rig_models(candidates)
    assert [chosen[n].model for n in ('left', 'right', 'aux')] == ['r', 'r', 'equidistant']
    assert list(chosen) == ['left', 'right', 'aux']
