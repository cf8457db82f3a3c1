"""calib_node's CalibrationSession on a ChArUco chart (chart.pattern charuco), without
ROS: a drawn rig's views, half of them slid partly out of the images, rendered with
OpenCV's board print; stage and handheld calibrations against the rig's truth."""

import dataclasses

import numpy as np
import pytest
from vgm_evaluation.rig_generator import draw_rig, render_rig, score_rig, with_edge_views

from calib_node.session import CalibrationSession, SessionSettings
from harness import ManualClock
from vgm_common.errors import InvalidInput

CAMERAS = ('left', 'right')
# As the chessboard's session tests (rendered images): 0.3 % in focal length and baseline.
FOCAL_TOLERANCE = 3e-3
BASELINE_TOLERANCE = 3e-3


@pytest.fixture(scope='module')
def partial_rig_and_images():
    """rig_generator seed 5 (8 views, whole boards) plus four of them slid along the left
    camera's x until the board's centre is 5 % of the width from an image edge
    (alternately left and right): boards cut by the edge, where distortion is largest."""
    rig = with_edge_views(draw_rig(5, CAMERAS, views=8)._replace(pattern='charuco'))
    return rig, render_rig(rig, 5)


def _session(rig, **changes):
    settings = dataclasses.replace(
        SessionSettings(
            cameras=CAMERAS,
            chart_pattern='charuco',
            chart_rows=rig.rows,
            chart_cols=rig.cols,
            chart_spacing=rig.spacing,
            chart_source='stage',
            min_views=4,
        ),
        **changes,
    )
    return CalibrationSession(lambda: settings, ManualClock(100.0))


def _feed(session, rig, images, posed):
    outcomes = []
    for stamp, (T_base_chart, view) in enumerate(zip(rig.T_base_chart, images)):
        if posed:
            session.add_target(stamp, T_base_chart)
        for name, grey in view.items():
            session.check_image_size(name, (grey.shape[1], grey.shape[0]))
        outcomes.append(session.add_view(session.chart_pose_of(stamp, 0.0), view, []))
    return outcomes


@pytest.mark.parametrize('source', ['stage', 'handheld'])
def test_partial_charuco_views_calibrate_to_the_truth(partial_rig_and_images, source):
    rig, images = partial_rig_and_images
    session = _session(rig, chart_source=source, min_coverage=0.0, select_views=False)
    outcomes = _feed(session, rig, images, posed=source == 'stage')
    # One slid view (seed 5's) shows neither camera a marker: no view, and said so.
    missed = [o for o in outcomes if o.status != 'kept']
    assert len(missed) <= 1 and all('ChArUco corners' in o.message for o in missed), missed
    partial = [
        np.isnan(corners[:, 0]).any() for _, view in session.views for corners in view.values()
    ]
    assert sum(partial) >= 4, 'the slid boards must be seen in part'
    calibration = session.calibrate()
    score = score_rig(rig.cameras, calibration.cameras, absolute=source == 'stage')
    assert score['fx'] < FOCAL_TOLERANCE and score['fy'] < FOCAL_TOLERANCE, score
    assert score['baseline'] < BASELINE_TOLERANCE, score
    for name, fit in calibration.fits.items():
        assert fit.rms_px < 0.2, (name, fit.rms_px)
        seen = sum(
            np.isfinite(view[name][:, 0]).sum() for _, view in session.views if name in view
        )
        assert fit.points == seen  # only the corners seen are residuals


def test_an_unknown_dictionary_is_a_start_up_error_naming_the_valid_ones():
    rig = draw_rig(5, CAMERAS, views=8)
    with pytest.raises(InvalidInput, match='chart.dictionary.*DICT_5X5_100'):
        _session(rig, chart_dictionary='DICT_5X5_99')
