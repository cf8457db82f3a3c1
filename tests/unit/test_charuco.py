"""ChArUco charts: the simulator's print (OpenCV's own board image as the chart's texture)
and calib_node's detector, against the true corner pixels; partial and occluded views."""

import dataclasses

import numpy as np
import pytest
import yaml
from vgm_evaluation.rig_generator import ChartRenderer, draw_rig, true_corners

from calib_node.chart_detection import CharucoChart
from sensor_sim.chart import BLACK_ALBEDO, chart_albedo, charuco_albedo
from sensor_sim.render import SceneRenderer
from sensor_sim.scenario import ScenarioError, parse_scenario, resolve_scenario_path

# Measured: 0.02-0.04 px RMS; the worst corner of a view 0.15 px, beside a marker on a
# board slanted to 25 px squares (OpenCV's own corner there is as far off).
RMS_TOLERANCE_PX = 0.1
MAX_TOLERANCE_PX = 0.2


def _errors(detected, truth):
    seen = np.isfinite(detected[:, 0])
    return seen, np.linalg.norm(detected[seen] - truth[seen], axis=1)


def test_print_keeps_the_chessboard_squares_and_adds_markers():
    """Every black square of the chessboard print is black on the ChArUco print (the
    same corners), and markers darken part of the white squares."""
    xy = np.random.default_rng(0).uniform(-0.06, 0.25, (100_000, 2))
    chess, charuco = chart_albedo(xy, 6, 9, 0.025), charuco_albedo(xy, 6, 9, 0.025)
    assert np.array_equal(np.isnan(chess), np.isnan(charuco))
    assert np.all(charuco[chess == BLACK_ALBEDO] == BLACK_ALBEDO)
    marked = np.mean(charuco[chess > BLACK_ALBEDO] == BLACK_ALBEDO)
    assert 0.1 < marked < 0.4, marked


@pytest.mark.parametrize('shift', [0.0, 0.45])
def test_partly_out_of_view_corners_within_a_tenth_of_a_pixel(shift):
    """rig_generator seed 24's first view, the board slid along its x by ``shift`` of its
    width: the corners inside the image are identified, none outside, each within
    MAX_TOLERANCE_PX of the truth, RMS_TOLERANCE_PX over the view."""
    rig = draw_rig(24, views=8)
    camera = rig.cameras['left']
    T = rig.T_base_chart[0].copy()
    # along the camera's x axis: the board slides toward the image's right edge
    T[:3, 3] += camera.T_camera_base[0, :3] * shift * (rig.cols + 1) * rig.spacing
    image = ChartRenderer(rig.rows, rig.cols, rig.spacing, pattern='charuco').render(
        camera, T, np.random.default_rng(1), 1.0
    )
    truth = true_corners(rig._replace(T_base_chart=[T]))[0]['left']
    inside = np.all((truth > 0) & (truth < [camera.width - 1, camera.height - 1]), axis=1)
    if shift:
        assert 0.2 * len(truth) < np.sum(~inside), 'the board should leave the image'
    detection = CharucoChart(rig.rows, rig.cols, rig.spacing).detect(image)
    assert detection.corners is not None, detection.reason
    seen, errors = _errors(detection.corners, truth)
    assert not np.any(seen & ~inside)
    assert np.sum(seen) >= 0.8 * np.sum(inside), (np.sum(seen), np.sum(inside))
    assert np.sqrt(np.mean(errors**2)) < RMS_TOLERANCE_PX and errors.max() < MAX_TOLERANCE_PX, (
        errors
    )


def test_occluded_board_still_gives_identified_corners():
    """A grey block over the middle of the board hides some corners; the others keep
    their ids and accuracy."""
    rig = draw_rig(24, views=8)
    camera = rig.cameras['right']
    T = rig.T_base_chart[1]
    image = ChartRenderer(rig.rows, rig.cols, rig.spacing, pattern='charuco').render(
        camera, T, np.random.default_rng(2), 1.0
    )
    truth = true_corners(rig._replace(T_base_chart=[T]))[0]['right']
    centre = truth.mean(axis=0).astype(int)
    half = (np.ptp(truth, axis=0) / 6).astype(int)
    (u0, v0), (u1, v1) = centre - half, centre + half
    image[v0:v1, u0:u1] = 128
    hidden = np.all(np.abs(truth - centre) < half, axis=1)
    assert np.any(hidden)
    detection = CharucoChart(rig.rows, rig.cols, rig.spacing).detect(image)
    assert detection.corners is not None, detection.reason
    seen, errors = _errors(detection.corners, truth)
    assert not np.any(seen & hidden)
    assert np.sum(seen) >= 0.7 * np.sum(~hidden)
    assert np.sqrt(np.mean(errors**2)) < RMS_TOLERANCE_PX


def test_too_few_corners_and_a_bad_dictionary():
    chart = CharucoChart(5, 8, 0.03, min_corners=6)
    detection = chart.detect(np.full((480, 640), 200, np.uint8))
    assert detection.corners is None and 'min_corners' in detection.reason
    with pytest.raises(ValueError, match='DICT_5X5_100'):  # the valid names are listed
        CharucoChart(5, 8, 0.03, dictionary='DICT_5X5_101')
    with pytest.raises(ValueError, match='needs 54 markers'):
        CharucoChart(8, 11, 0.03, dictionary='DICT_4X4_50')


def _charuco_scenario(**chart):
    with open(resolve_scenario_path('default')) as file:
        data = yaml.safe_load(file)
    data['calibration'].update({'pattern': 'charuco', **chart})
    return parse_scenario(data, resolve_scenario_path('default'))


def test_sensor_sim_renders_a_charuco_scenario_detected_at_the_true_corners():
    """The default scenario with ``pattern: charuco`` (rows + cols even is allowed: the
    markers fix the orientation): calib_node's detector finds sensor_sim's chart views'
    corners at the true cameras' projections of the chart corners."""
    scenario = _charuco_scenario(rows=6, cols=8, dictionary='DICT_4X4_50', marker_size=0.018)
    calibration = scenario.calibration
    renderer = SceneRenderer(scenario)
    detector = CharucoChart(
        calibration.rows, calibration.cols, calibration.spacing, 0.018, 'DICT_4X4_50'
    )
    r, c = np.divmod(np.arange(calibration.rows * calibration.cols), calibration.cols)
    chart = np.column_stack([c, r, 0 * r]) * calibration.spacing
    errors = []
    for name in ('left', 'right'):
        camera = scenario.cameras[name]
        for pose in (0, 3):
            T = calibration.T_base_chart[pose]
            truth, _ = camera.project(chart @ T[:3, :3].T + T[:3, 3])
            detection = detector.detect(renderer.chart_image(name, pose))
            assert detection.corners is not None, (name, pose, detection.reason)
            seen, error = _errors(detection.corners, truth)
            inside = np.all((truth > 0) & (truth < [camera.width, camera.height]), axis=1)
            # (aux's oblique views decode 15-31 of 48: small slanted markers)
            assert np.sum(seen) >= 0.6 * np.sum(inside) and not np.any(seen & ~inside)
            errors.append(error)
    errors = np.concatenate(errors)
    assert np.sqrt(np.mean(errors**2)) < RMS_TOLERANCE_PX and errors.max() < MAX_TOLERANCE_PX


def test_a_bad_charuco_scenario_names_the_valid_dictionaries():
    with pytest.raises(ScenarioError, match='DICT_5X5_100'):
        _charuco_scenario(dictionary='DICT_5x5_100')
    assert dataclasses.replace(_charuco_scenario().calibration).dictionary == 'DICT_5X5_100'
