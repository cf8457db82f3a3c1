"""sfs_stereo_node's DepthSession without ROS: pairs taken by stamp slots, throttled
warnings and INFO lines on a clock the test moves, and the status's level and message."""

import numpy as np
import pytest

from harness import ManualClock
from sfs_stereo_node.pipeline import DepthResult
from sfs_stereo_node.session import WARN_EVERY_S, DepthSession
from vgm_common.camera_model import PinholeCamera
from vgm_common.camera_topics import CalibratedCamera
from vgm_common.errors import InvalidInput


def result(warnings=()):
    depth = np.zeros((2, 2), np.float32)
    return DepthResult(
        disparity=depth,
        depth_stereo=depth,
        depth_sfs=None,
        depth_fused=depth,
        surface=np.ones((2, 2), bool),
        focal_px=500.0,
        baseline_m=0.1,
        P=np.eye(3, 4),
        valid_window=(0, 0, 2, 2),
        density=0.5,
        timings={'total': 0.02},
        left_rect=np.zeros((2, 2), np.uint8),
        warnings=tuple(warnings),
        fusion='shading_refine',
    )


def test_max_rate_takes_the_first_pair_of_each_slot_of_stamps():
    session = DepthSession(ManualClock())
    stamps = [0, 100_000_000, 600_000_000, 1_000_000_000, 1_900_000_000, 2_100_000_000]
    taken = [s for s in stamps if session.take(s, max_rate=1.0)]  # one per second of stamps
    assert taken == [0, 1_000_000_000, 2_100_000_000] and session.throttled == 3
    assert all(session.take(s, max_rate=0.0) for s in stamps)  # 0: every pair


def test_warnings_and_info_lines_are_throttled():
    clock = ManualClock()
    session = DepthSession(clock)
    assert session.record(result(['no match: texture-less']), log_every=5.0) == (
        ['no match: texture-less'],
        True,  # the first frame is always logged
    )
    clock.now = 1.0
    assert session.record(result(['no match: again', 'fusion: fell back']), 5.0) == (
        ['fusion: fell back'],
        False,
    )
    clock.now = WARN_EVERY_S
    assert session.record(result(['no match: later']), 5.0) == (['no match: later'], True)
    level, message, values = session.status([], {'dropped': 2, 'rejected stereo pair': 1})
    assert (level, message) == ('warn', 'no match: later')
    assert values['frames processed'] == 3 and values['frames dropped (busy)'] == 2
    assert values['rejected stereo pair'] == 1 and values['fused by'] == 'shading_refine'
    session.record(result(), 5.0)
    assert session.status([], {})[:2] == ('ok', '4 pairs processed')
    assert session.status(['right'], {})[:2] == ('warn', 'no calibration for right')
    assert DepthSession().status([], {})[:2] == ('warn', 'no pair processed yet')
    assert session.waiting_for_calibration() and not session.waiting_for_calibration()


def test_the_rectification_is_made_once_per_calibration_and_image_size():
    K = np.array([[500.0, 0, 160], [0, 500, 120], [0, 0, 1]])
    P_left, P_right = np.hstack([K, np.zeros((3, 1))]), np.hstack([K, [[-50.0], [0], [0]]])
    T = np.eye(4)
    left = CalibratedCamera(PinholeCamera(320, 240, K, np.zeros(5), T), np.eye(3), P_left)
    right = CalibratedCamera(PinholeCamera(320, 240, K, np.zeros(5), T), np.eye(3), P_right)
    session = DepthSession()
    tables = session.rectification(1, left, right, (240, 320))
    assert tables.baseline_m == pytest.approx(0.1)  # P_right[0, 3] = -f * baseline
    assert session.rectification(1, left, right, (240, 320)) is tables
    assert session.rectification(2, left, right, (240, 320)) is not tables  # recalibrated
    with pytest.raises(
        InvalidInput, match='left camera_info is 320x240 but the images are 640x480'
    ):
        session.rectification(2, left, right, (480, 640))
