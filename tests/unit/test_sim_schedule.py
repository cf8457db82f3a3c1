"""sensor_sim's state without ROS: the capture schedule, the images of a capture, the arm
step with its pressure sensor, and the arm thread's tick schedule on a manual clock."""

from dataclasses import replace

import numpy as np
import pytest

from harness import SCENARIO_DIR, ManualClock
from sensor_sim.arm_loop import ArmLoop, ArmSettings, TickSchedule
from sensor_sim.capture import CaptureSchedule, capture_images
from sensor_sim.scenario import CAMERA_NAMES, Noise, Surface, load_scenario
from vgm_common.errors import InvalidInput
from vgm_common.geometry import make_transform
from vgm_common.robot_model import load_robot

PERIOD = 0.005  # [s] the arm's tick at the default 200 Hz


@pytest.fixture(scope='module')
def quick():
    return load_scenario(SCENARIO_DIR / 'quick.yaml')


def test_the_chart_is_shown_at_every_pose_then_the_scene_for_good(quick):
    calibration = replace(quick.calibration, captures_per_pose=2)
    poses = len(calibration.T_base_chart)
    schedule = CaptureSchedule(calibration, calibration_phase=True)
    assert schedule.chart_frames == 2 * poses and schedule.phase == 'calibration'
    captures = [schedule.next() for _ in range(2 * poses + 3)]
    assert [c.frame_index for c in captures] == list(range(2 * poses + 3))
    assert [c.pose_index for c in captures] == [k // 2 for k in range(2 * poses)] + [None] * 3
    for capture in captures[: 2 * poses]:  # a stage's pose is measured: published
        np.testing.assert_array_equal(
            capture.T_base_target, calibration.T_base_chart[capture.pose_index]
        )
    assert all(c.T_base_target is None for c in captures[2 * poses :])
    assert [c.ends_calibration for c in captures].index(True) == 2 * poses - 1
    assert sum(c.ends_calibration for c in captures) == 1
    assert schedule.phase == 'scene'


def test_a_hand_s_poses_are_shown_but_not_published(quick):
    schedule = CaptureSchedule(replace(quick.calibration, motion='handheld'), True)
    captures = [schedule.next() for _ in range(schedule.chart_frames)]
    assert [c.pose_index for c in captures] == list(range(len(quick.calibration.T_base_chart)))
    assert all(c.T_base_target is None for c in captures)


@pytest.mark.parametrize('calibration_phase', [False, True])
def test_without_a_calibration_phase_the_scene_comes_first(quick, calibration_phase):
    calibration = quick.calibration if not calibration_phase else None
    schedule = CaptureSchedule(calibration, calibration_phase)
    assert schedule.chart_frames == 0 and schedule.phase == 'scene'
    capture = schedule.next()
    assert capture.pose_index is None and capture.T_base_target is None
    assert not capture.ends_calibration


class ConstantRenderer:
    """A renderer whose clean images are known: grey 100 for the scene, 50 + pose for the
    chart (the noise is what is under test)."""

    def scene_image(self, name):
        return np.full((120, 160), 100.0)

    def chart_image(self, name, pose_index):
        return np.full((120, 160), 50.0 + pose_index)


def test_a_capture_s_noise_is_its_own_and_repeats_bit_for_bit(quick):
    scenario = replace(quick, noise=Noise(image_sigma=4.0, pressure_sigma=0.0))
    schedule = CaptureSchedule(scenario.calibration, True)
    first, second = schedule.next(), schedule.next()
    images = capture_images(ConstantRenderer(), scenario, first)
    again = capture_images(ConstantRenderer(), scenario, first)
    other = capture_images(ConstantRenderer(), scenario, second)
    assert list(images) == list(CAMERA_NAMES)
    for name in CAMERA_NAMES:
        assert images[name].dtype == np.uint8 and images[name].shape == (120, 160)
        np.testing.assert_array_equal(images[name], again[name])
        noise = images[name].astype(float) - (50.0 + first.pose_index)
        assert abs(noise.mean()) < 0.1  # 19200 samples: standard error 0.03
        assert noise.std() == pytest.approx(4.0, rel=0.03)
        assert not np.array_equal(images[name] - 50, other[name] - 51)  # its own noise
    assert not np.array_equal(images['left'], images['right'])  # each camera its own


@pytest.fixture(scope='module')
def robot(quick):
    r = quick.robot
    return load_robot(r.model, r.tool_length, r.tip_frame, base_frame=r.base_frame)


def pressed_scenario(quick, robot, depth, sigma):
    """``quick`` with a horizontal plane ``depth`` [m] above the tool tip at its start."""
    tip = robot.forward_kinematics(quick.robot.initial_joints)[:3, 3]
    plane = Surface(
        kind='plane',
        T_base_surface=make_transform(np.eye(3), tip + [0.0, 0.0, depth]),
        scale=1.0,
        extent=((-1.0, 1.0), (-1.0, 1.0)),
        albedo=0.8,
        roughness=0.0,
    )
    return replace(quick, surface=plane, noise=Noise(image_sigma=0.0, pressure_sigma=sigma))


def test_the_pressure_sensor_reads_the_spring_force_with_its_noise(quick, robot):
    scenario = pressed_scenario(quick, robot, depth=0.004, sigma=0.2)
    loop = ArmLoop(robot, scenario, ArmSettings(), PERIOD)
    samples = [loop.step(k * PERIOD) for k in range(2000)]
    expected = scenario.contact_stiffness * 0.004  # [N] 4 mm into the spring
    forces = np.array([s.force for s in samples])
    assert forces.mean() == pytest.approx(expected, abs=0.02)  # standard error 0.0045 N
    assert forces.std() == pytest.approx(0.2, rel=0.05)
    np.testing.assert_allclose(samples[-1].q, quick.robot.initial_joints, atol=1e-12)
    assert samples[3].stamp_ns == round(3 * PERIOD * 1e9)


def test_out_of_contact_the_sensor_reads_exactly_zero(quick, robot):
    scenario = pressed_scenario(quick, robot, depth=-0.01, sigma=0.2)  # plane below the tip
    loop = ArmLoop(robot, scenario, ArmSettings(), PERIOD)
    assert all(loop.step(k * PERIOD).force == 0.0 for k in range(50))


def test_the_arm_follows_a_command_by_the_time_since_the_last_step(quick, robot):
    loop = ArmLoop(robot, quick, ArmSettings(), PERIOD)
    q0 = quick.robot.initial_joints
    target = q0 + 0.01  # [rad]
    loop.command(robot.joint_names, [0.0], [list(target)], [[]], start_time=0.0)
    # The first step moves by one period: the slowest joint by its limit times that.
    slowest = int(np.argmin(robot.velocity_limits))
    moved = loop.step(1.0).q - q0
    assert moved[slowest] == pytest.approx(PERIOD * robot.velocity_limits[slowest], rel=1e-9)
    np.testing.assert_allclose(loop.step(2.0).q, target, atol=1e-12)  # 1 s later: there


def test_a_malformed_command_is_refused_and_the_arm_holds(quick, robot):
    loop = ArmLoop(robot, quick, ArmSettings(), PERIOD)
    q0 = quick.robot.initial_joints
    loop.command(robot.joint_names, [10.0], [list(q0 + 0.5)], [[]], start_time=0.0)
    moving = loop.step(0.5).q
    with pytest.raises(InvalidInput, match='differ in length'):
        loop.command(robot.joint_names, [1.0], [list(q0)], [[0.0, 0.0]], start_time=0.5)
    np.testing.assert_allclose(loop.step(1.0).q, moving, atol=1e-12)  # held where it was


def test_ticks_keep_an_absolute_schedule_and_never_burst_to_catch_up():
    clock = ManualClock(10.0)
    ticks = TickSchedule(PERIOD, clock)
    clock.now += 0.001  # a tick that took 1 ms
    assert ticks.wait_after_tick() == pytest.approx(0.004, abs=1e-12)
    clock.now = 10.005 + 0.002  # woke 2 ms late: the next tick is still at 10.010
    assert ticks.wait_after_tick() == pytest.approx(0.003, abs=1e-12)
    clock.now = 10.030  # stalled 20 ms: tick at once, then a period from here
    assert ticks.wait_after_tick() == 0.0
    assert ticks.wait_after_tick() == pytest.approx(PERIOD, abs=1e-12)
