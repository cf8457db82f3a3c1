"""The simulated arm: velocity- and position-limited tracking of joint trajectories."""

import numpy as np
import pytest

from sensor_sim.arm_sim import SimulatedArm
from vgm_common.errors import InvalidInput

NAMES = tuple(f'pa10_joint{i}' for i in range(1, 8))
UPPER = np.deg2rad([177, 94, 174, 137, 255, 165, 255])
QDOT_MAX = np.array([1.0, 1.0, 2.0, 2.0, 2 * np.pi, 2 * np.pi, 2 * np.pi])  # [rad/s]
DT = 0.01  # [s]


def make_arm(q0=(0.0,) * 7):
    return SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, q0)


def run(arm, t0, t1):
    """Step from t0 to t1 [s]; returns the times and the (steps, 7) positions."""
    times = np.arange(t0, t1, DT) + DT
    return times, np.array([arm.step(t, DT)[0] for t in times])


def test_go_there_now_takes_the_slowest_joints_time():
    arm = make_arm()
    target = np.array([0.5, -0.3, 1.0, 0.2, 3.0, -1.0, 0.1])
    arm.set_trajectory(NAMES, [0.0], [target], start_time=0.0)
    times, qs = run(arm, 0.0, 2.0)
    expected_s = np.max(np.abs(target) / QDOT_MAX)  # joint 1: 0.5 rad at 1 rad/s
    arrived = times[np.argmax(np.all(np.abs(qs - target) < 1e-12, axis=1))]
    assert arrived == pytest.approx(expected_s, abs=DT + 1e-9)
    speeds = np.abs(np.diff(qs, axis=0)) / DT
    assert np.all(speeds <= QDOT_MAX + 1e-9)
    np.testing.assert_allclose(arm.q, target)
    np.testing.assert_allclose(arm.qdot, 0.0)


def test_command_just_beyond_the_limit_clamps():
    arm = make_arm()
    beyond = UPPER + 0.09  # within LIMIT_SLACK_RAD: a commander's rounding
    arm.set_trajectory(NAMES, [0.0], [beyond])
    _, qs = run(arm, 0.0, 5.0)
    assert np.all(qs <= UPPER) and np.all(qs >= -UPPER)
    np.testing.assert_allclose(arm.q, UPPER)


@pytest.mark.parametrize('position', [1e300, -1e300, UPPER[3] + 0.11])
def test_command_far_beyond_the_limits_is_refused_and_the_arm_stays(position):
    arm = make_arm()
    q_start = np.full(7, 0.2)
    arm.set_trajectory(NAMES, [0.0], [q_start])
    run(arm, 0.0, 1.0)
    target = q_start.copy()
    target[3] = position
    with pytest.raises(InvalidInput, match='pa10_joint4 at .* beyond its limits'):
        arm.set_trajectory(NAMES, [0.0, 1.0], [q_start, target])
    _, qs = run(arm, 1.0, 3.0)
    np.testing.assert_allclose(qs, np.tile(q_start, (len(qs), 1)))


def test_shuffled_joint_names_are_mapped():
    arm = make_arm()
    order = np.random.default_rng(0).permutation(7)
    target = np.linspace(0.1, 0.7, 7)  # in model order
    arm.set_trajectory([NAMES[i] for i in order], [0.0], [target[order]])
    run(arm, 0.0, 1.0)
    np.testing.assert_allclose(arm.q, target)


def test_linear_interpolation_mid_trajectory():
    arm = make_arm()
    q_a, q_b = np.full(7, 0.1), np.full(7, 0.3)
    arm.set_trajectory(NAMES, [1.0, 2.0], [q_a, q_b], start_time=10.0)
    np.testing.assert_allclose(arm.desired(5.0), 0.0)  # before start: hold
    np.testing.assert_allclose(arm.desired(10.5), 0.05)  # from the current state
    np.testing.assert_allclose(arm.desired(11.25), 0.15)
    np.testing.assert_allclose(arm.desired(99.0), q_b)  # after the end: hold the last


def test_hermite_interpolation_reproduces_a_cubic():
    arm = make_arm()
    t = np.array([0.0, 0.4, 1.0])
    cubic = lambda s: 0.2 * s**3 - 0.3 * s**2 + 0.1 * s  # noqa: E731
    d_cubic = lambda s: 0.6 * s**2 - 0.6 * s + 0.1  # noqa: E731
    arm.set_trajectory(
        NAMES, t, np.tile(cubic(t)[:, None], 7), np.tile(d_cubic(t)[:, None], 7), start_time=0.0
    )
    for s in [0.1, 0.4, 0.7, 0.95]:
        np.testing.assert_allclose(arm.desired(s), cubic(s), atol=1e-15)


def test_follows_a_feasible_trajectory_exactly():
    arm = make_arm()
    times = np.linspace(0.0, 2.0, 21)
    positions = 0.3 * np.sin(times)[:, None] * np.ones(7)  # <= 0.3 rad/s
    arm.set_trajectory(NAMES, times, positions, start_time=0.0)
    ts, qs = run(arm, 0.0, 2.0)
    np.testing.assert_allclose(qs, [arm.desired(t) for t in ts], atol=1e-12)


GOOD_POINT = np.full(7, 0.5)


@pytest.mark.parametrize(
    'names, times, positions, velocities',
    [
        (NAMES[:6] + ('elbow',), [0.0], [GOOD_POINT], None),  # unknown name
        (NAMES[:6], [0.0], [GOOD_POINT[:6]], None),  # missing joint
        (NAMES[:6] + (NAMES[0],), [0.0], [GOOD_POINT], None),  # duplicate
        (NAMES, [0.0], [GOOD_POINT[:6]], None),  # short point
        (NAMES, [0.0, 1.0], [GOOD_POINT], None),  # fewer points than times
        (NAMES, [0.0], [[0, 0, np.nan, 0, 0, 0, 0]], None),
        (NAMES, [0.0, np.inf], [GOOD_POINT, GOOD_POINT], None),
        (NAMES, [1.0, 1.0], [GOOD_POINT, GOOD_POINT], None),  # not increasing
        (NAMES, [2.0, 1.0], [GOOD_POINT, GOOD_POINT], None),
        (NAMES, [-1.0], [GOOD_POINT], None),
        (NAMES, [], np.empty((0, 7)), None),
        (NAMES, [0.0], [GOOD_POINT], [GOOD_POINT[:5]]),
        (NAMES, [0.0, 1.0], [[0.1] * 7, [0.1] * 6], None),  # ragged
    ],
)
def test_bad_trajectory_is_rejected_and_the_arm_keeps_holding(names, times, positions, velocities):
    q0 = np.full(7, 0.2)
    arm = make_arm(q0)
    with pytest.raises(InvalidInput):
        arm.set_trajectory(names, times, positions, velocities, start_time=0.0)
    run(arm, 0.0, 1.0)
    np.testing.assert_array_equal(arm.q, q0)


def test_rejected_trajectory_keeps_the_previous_command():
    arm = make_arm()
    arm.set_trajectory(NAMES, [0.0], [GOOD_POINT])
    with pytest.raises(InvalidInput, match='unknown joint names'):
        arm.set_trajectory(['nope'] * 7, [0.0], [np.zeros(7)])
    run(arm, 0.0, 1.0)
    np.testing.assert_allclose(arm.q, GOOD_POINT)


def test_hold_stops_where_the_arm_is():
    arm = make_arm()
    arm.set_trajectory(NAMES, [0.0], [GOOD_POINT])
    run(arm, 0.0, 0.2)
    arm.hold()
    q_held = arm.q
    run(arm, 0.2, 1.0)
    np.testing.assert_array_equal(arm.q, q_held)
    np.testing.assert_array_equal(arm.qdot, 0.0)


def test_initial_position_outside_limits_is_rejected():
    with pytest.raises(InvalidInput):
        make_arm(UPPER + 0.1)


def test_follow_velocity_reaches_a_feasible_velocity():
    arm = make_arm()
    qdot = np.array([0.5, -0.2, 1.0, 0.0, 3.0, -1.0, 0.1])  # within QDOT_MAX
    t, positions = 0.0, []
    for _ in range(50):
        t = arm.follow_velocity(NAMES, qdot, t, DT)
        positions.append(arm.q)
    assert t == pytest.approx(50 * DT)
    # from rest the set point starts at zero velocity: after that start, qdot * DT per period
    steps = np.diff(positions, axis=0)[-20:]
    np.testing.assert_allclose(steps, np.tile(qdot * DT, (20, 1)), atol=1e-9)
    lag = (50 * DT * qdot - arm.q)[qdot != 0] / qdot[qdot != 0]  # [s]
    assert np.all((lag >= 0) & (lag < 2 * DT)), lag


def test_velocity_arm_follows_only_the_commanded_velocities():
    arm = SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), mode='velocity')
    qdot = np.array([0.2, -0.1, 0.3, 0.0, 0.5, -0.4, 0.1])
    # Positions that disagree with the velocities: a velocity interface ignores them.
    arm.set_trajectory(NAMES, [0.5], [np.full(7, 1.0)], [qdot], start_time=0.0)
    run(arm, 0.0, 0.3)
    np.testing.assert_allclose(arm.q, 0.3 * qdot, atol=1e-12)
    run(arm, 0.3, 0.7)  # past the last point: zero velocity, it stays
    np.testing.assert_allclose(arm.q, 0.5 * qdot, atol=DT * np.abs(qdot).max() + 1e-12)
    np.testing.assert_allclose(arm.qdot, 0.0)


@pytest.mark.parametrize('mode', ['position', 'velocity'])
def test_slower_arm_makes_a_fraction_of_the_commanded_motion(mode):
    qdot = np.array([0.2, -0.1, 0.3, 0.0, 0.5, -0.4, 0.1])
    full = SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), mode=mode)
    slow = SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), mode=mode, speed_scale=0.5)
    t = 0.0
    for _ in range(50):  # 0.5 s of pa10_ik_node's commands, 100 Hz
        full.follow_velocity(NAMES, qdot, t, DT)
        t = slow.follow_velocity(NAMES, qdot, t, DT)
    np.testing.assert_allclose(full.q, 0.5 * qdot, rtol=0.05)
    ratio = slow.q[qdot != 0] / full.q[qdot != 0]
    if mode == 'velocity':  # exactly the scale
        np.testing.assert_allclose(ratio, 0.5, atol=0.02)
    else:  # a lag behind set points that start from where the arm is: ~the scale, less
        assert np.all((ratio > 0.35) & (ratio < 0.55)), ratio


@pytest.mark.parametrize('mode', ['position', 'velocity'])
def test_a_hold_now_stops_either_arm_within_one_step(mode):
    arm = SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), mode=mode)
    qdot = np.full(7, 0.3)
    t = 0.0
    for _ in range(20):
        t = arm.follow_velocity(NAMES, qdot, t, DT)
    assert np.all(arm.qdot > 0.25)
    q_measured = arm.q
    arm.set_trajectory(NAMES, [0.0], [q_measured], start_time=t)  # pa10_ik_node's hold
    arm.step(t + 0.005, 0.005)
    np.testing.assert_allclose(arm.qdot, 0.0, atol=1e-12)
    np.testing.assert_allclose(arm.q, q_measured, atol=1e-12)


@pytest.mark.parametrize(
    'kwargs',
    [
        {'mode': 'torque'},
        {'speed_scale': 0.0},
        {'speed_scale': 1.5},
        {'speed_scale': float('nan')},
    ],
)
def test_bad_arm_mode_or_scale_is_rejected(kwargs):
    with pytest.raises(InvalidInput):
        SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), **kwargs)


@pytest.mark.parametrize('mode', ['position', 'velocity'])
def test_a_delayed_arm_moves_as_the_prompt_one_did_the_delay_before(mode):
    """command_delay 20 ms: 100 Hz commands (set points and velocities that change every
    period) take effect 2 periods late, so the delayed arm's path is the prompt arm's
    shifted by exactly 20 ms, and it holds still for the first 20 ms."""
    delay = 0.02
    prompt = SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), mode=mode)
    late = SimulatedArm(
        NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), mode=mode, command_delay=delay
    )
    # Set points independent of the arm's state, as a trajectory generator sends them.
    targets = [0.3 * np.sin(0.5 * k + np.arange(7)) for k in range(60)]
    rates = [0.1 + 0.15 * np.cos(0.5 * k + np.arange(7)) for k in range(60)]
    t, prompt_q, late_q = 0.0, [], []
    for target, rate in zip(targets, rates):
        for arm in (prompt, late):
            arm.set_trajectory(NAMES, [0.05], [target], [rate], start_time=t)
        for _ in range(2):  # sensor_sim's 200 Hz beside 100 Hz commands
            t += DT / 2
            prompt.step(t, DT / 2)
            late.step(t, DT / 2)
        prompt_q.append(prompt.q)
        late_q.append(late.q)
    shift = int(round(delay / DT))
    np.testing.assert_allclose(np.array(late_q[:shift]), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.array(late_q[shift:]), np.array(prompt_q[:-shift]), atol=1e-12)
    assert np.max(np.abs(prompt_q[-1])) > 0.05  # it really moved


def test_a_hold_on_a_delayed_arm_drops_the_commands_still_on_their_way():
    arm = SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), command_delay=0.05)
    arm.set_trajectory(NAMES, [0.1], [np.full(7, 0.2)], start_time=0.0)
    arm.hold()
    run(arm, 0.0, 0.3)
    np.testing.assert_allclose(arm.q, 0.0, atol=1e-12)


@pytest.mark.parametrize('delay', [-0.01, float('inf'), float('nan')])
def test_a_bad_command_delay_is_rejected(delay):
    with pytest.raises(InvalidInput, match='command_delay'):
        SimulatedArm(NAMES, -UPPER, UPPER, QDOT_MAX, np.zeros(7), command_delay=delay)


def test_a_command_received_between_steps_starts_from_where_the_arm_then_is():
    """sensor_sim steps its arm every 5 ms and takes commands whenever they arrive: a
    trajectory received 2.5 ms after a step starts from the arm's state at that time (the
    last step's moved on at its velocity), as joint_trajectory_controller reads the state
    when it takes a trajectory. It once started from the last step's position at the
    receipt time, dropping the motion in between from every command (pa10_ik_node's
    ideal arm over topics made 0.66 of its commanded motion, the half-speed one 0.16)."""
    v = np.array([0.2, -0.1, 0.3, 0.0, 0.5, -0.4, 0.1])  # [rad/s]
    step, horizon = 0.005, 0.05  # [s]
    arm = make_arm()
    arm.set_trajectory(NAMES, [0.0, 1.0], [np.zeros(7), v])  # a ramp at v, linear
    for k in range(1, 101):
        arm.step(k * step, step)
    np.testing.assert_allclose(arm.q, v * 0.5, rtol=0, atol=1e-12)
    # The same ramp, as a new trajectory received between the steps at 0.5 and 0.505 s.
    received = 0.5025
    arm.set_trajectory(NAMES, [horizon], [v * (received + horizon)], start_time=received)
    for k in range(101, 111):
        arm.step(k * step, step)
        np.testing.assert_allclose(arm.q, v * k * step, rtol=0, atol=1e-12)


def test_after_a_stall_a_command_starts_one_step_on_at_most():
    """A simulation stalled for 50 ms (its thread starved) does not guess where the arm
    would have gone: a command then starts one step's motion on from the last step."""
    v = np.array([0.2, -0.1, 0.3, 0.0, 0.5, -0.4, 0.1])  # [rad/s]
    step = 0.005  # [s]
    arm = make_arm()
    arm.set_trajectory(NAMES, [0.0, 1.0], [np.zeros(7), v])
    for k in range(1, 101):
        arm.step(k * step, step)
    received = 0.55  # 50 ms after the last step
    arm.set_trajectory(NAMES, [0.05], [arm.q + 0.05 * v], [v], start_time=received)
    np.testing.assert_allclose(arm.desired(received), v * (0.5 + step), rtol=0, atol=1e-12)
