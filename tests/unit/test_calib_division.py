"""The closed-form start for the seed's division model
(``seed_calibration.division_init``, ``seed_calibration.radial_division_init``) and ours =
that start + LM (``calibrate_seed_stereo``) on the thesis's setting: Tables 4.1 / 4.2
cameras, the 512 control points of §3.6."""

import numpy as np
import pytest

from calib_node.seed_calibration import (
    calibrate_seed_stereo,
    division_init,
    radial_division_init,
    refine_seed_lm,
)
from calib_node.seed_camera import LEFT_TRUTH, RIGHT_TRUTH, identifiable, seed_stereo_observations

POINTS_WORLD, PIXELS = seed_stereo_observations()  # (512, 3), (2, 512, 2) noise-free
TRUTH = (LEFT_TRUTH, RIGHT_TRUTH)


def relative_errors(params, truth):
    """Largest relative error of fx, fy, kappa, |T| and absolute of u0, v0 [px], R [rad]."""
    got, want = identifiable(params), identifiable(truth)
    relative = max(abs(getattr(got, q) / getattr(want, q) - 1) for q in ('fx', 'fy', 'kappa'))
    relative = max(relative, np.linalg.norm(got.T - want.T) / np.linalg.norm(want.T))
    pixels = max(abs(got.u0 - want.u0), abs(got.v0 - want.v0))
    angle = np.arccos(np.clip((np.trace(got.R @ want.R.T) - 1) / 2, -1, 1))
    return relative, pixels, angle


@pytest.mark.parametrize('camera', [0, 1])
def test_closed_form_start_is_exact_without_noise(camera):
    # Radial alignment + linear (t3, lambda, lambda t3, fx): exact on noise-free data.
    relative, pixels, angle = relative_errors(
        radial_division_init(POINTS_WORLD, PIXELS[camera]), TRUTH[camera]
    )
    assert relative < 1e-6 and pixels < 1e-6 and angle < 1e-8
    # The searched start: the best candidate is within the grid's resolution.
    best = division_init(POINTS_WORLD, PIXELS[camera])[0]
    relative, pixels, angle = relative_errors(best, TRUTH[camera])
    assert relative < 0.1 and angle < 0.05


def test_ours_recovers_noise_free_parameters_to_1e_6():
    left, right, info = calibrate_seed_stereo(POINTS_WORLD, *PIXELS)
    for params, truth in ((left, LEFT_TRUTH), (right, RIGHT_TRUTH)):
        relative, pixels, angle = relative_errors(params, truth)
        assert relative < 1e-6 and pixels < 1e-6 and angle < 1e-9
    assert max(info.rms_left, info.rms_right) < 1e-6


@pytest.mark.parametrize('sigma', [0.5, 3.0])
def test_noisy_ours_reaches_the_optimum_of_lm_started_at_the_truth(sigma):
    # The old DLT / GA starts stopped in wrong minima (1000s of px off) on these data.
    # Ours must reach the same optimum as LM started at the true cameras (the global one
    # as far as we can tell), so its errors are the statistical floor of one nearly affine
    # view: the predicted standard errors of fx are about 3 % at 0.5 px.
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        pixels = PIXELS + sigma * rng.standard_normal(PIXELS.shape)
        left, right, info = calibrate_seed_stereo(POINTS_WORLD, *pixels)
        *_, best = refine_seed_lm(*TRUTH, POINTS_WORLD, *pixels)
        assert info.rms_left == pytest.approx(best.rms_left, rel=1e-6)
        assert info.rms_right == pytest.approx(best.rms_right, rel=1e-6)
        # RMS of a 2D residual with sigma per coordinate: about sqrt(2) sigma
        assert max(info.rms_left, info.rms_right) < 1.6 * sigma
        for params, truth, std in (
            (left, LEFT_TRUTH, info.std[0]),
            (right, RIGHT_TRUTH, info.std[1]),
        ):
            got, want = identifiable(params), identifiable(truth)
            assert abs(got.fx - want.fx) < 5 * std[2] + 1e-9  # within 5 standard errors
            assert abs(got.u0 - want.u0) < 5 * std[0] + 1e-9


def test_bad_input_raises():
    with pytest.raises(ValueError):
        radial_division_init(POINTS_WORLD[:5], PIXELS[0][:5])
    with pytest.raises(ValueError):
        division_init(POINTS_WORLD, PIXELS[0][:10])
