"""pa10_ik_node's joint commands (commands.SetPointCommands) against sensor_sim's
simulated arm: the lag it measures is the arm's true trailing time, and leading the set
point by it puts the arm on the path."""

import numpy as np
import pytest

from pa10_ik_node.commands import MAX_LAG_S, SetPointCommands
from sensor_sim.arm_sim import SimulatedArm

NAMES = ('a', 'b', 'c')
VELOCITY = np.array([0.2, -0.1, 0.05])  # [rad/s] the path's joint speeds
PERIOD, HORIZON = 0.01, 0.05  # [s] control, as pa10_ik_node's defaults


def follow_ramp(commands, speed_scale, command_delay, duration=3.0):
    """The arm (200 Hz, position mode) commanded every PERIOD along q = VELOCITY t, the
    joints measured at each command; returns the arm's trailing time behind the ramp
    [s] (its distance behind along VELOCITY over the speed) over the last half."""
    arm = SimulatedArm(
        NAMES, [-3.0] * 3, [3.0] * 3, [2.0] * 3, [0.0] * 3, 'position', speed_scale, command_delay
    )
    t, trailing = 0.0, []
    while t < duration:
        q = arm.q
        commands.measure(q, t)
        command = commands.command(q, VELOCITY, t, HORIZON)
        times, positions, velocities = zip(*command.points())
        arm.set_trajectory(NAMES, times, positions, velocities, t)
        for _ in range(2):
            t += PERIOD / 2
            arm.step(t, PERIOD / 2)
        if t > duration / 2:
            trailing.append(np.dot(VELOCITY * t - arm.q, VELOCITY) / np.dot(VELOCITY, VELOCITY))
    return np.array(trailing)


ARM_STEP = PERIOD / 2  # [s] the simulated arm's step


def follow_ramp_restarted(speed_scale, duration=3.0):
    """follow_ramp with each command sent as one point at the horizon (no set point at
    time 0): the arm's trajectory then starts from the arm's own state every PERIOD."""
    commands = SetPointCommands()
    arm = SimulatedArm(NAMES, [-3.0] * 3, [3.0] * 3, [2.0] * 3, [0.0] * 3, 'position', speed_scale)
    t, trailing = 0.0, []
    while t < duration:
        q = arm.q
        commands.measure(q, t)
        command = commands.command(q, VELOCITY, t, HORIZON)
        arm.set_trajectory(NAMES, [command.horizon], [command.positions], [command.velocities], t)
        for _ in range(2):
            t += ARM_STEP
            arm.step(t, ARM_STEP)
        if t > duration / 2:
            trailing.append(np.dot(VELOCITY * t - arm.q, VELOCITY) / np.dot(VELOCITY, VELOCITY))
    return np.mean(trailing), commands.lag


@pytest.mark.parametrize(
    ('speed_scale', 'command_delay'), [(0.5, 0.0), (1.0, 0.02), (0.5, 0.02), (1.0, 0.0)]
)
def test_the_measured_lag_is_the_arms_trailing_time_and_the_lead_removes_it(
    speed_scale, command_delay
):
    """On the set point continued (a point at time 0), a position loop closing the
    fraction s of its gap every step trails a ramp by (1 - s) / s steps (the half-speed
    arm: 5 ms), an arm whose commands act late by that delay too: the trailing time is
    that, the estimate equals it within 1 ms, and commanding one lag ahead leaves under
    1 ms of it once settled (the estimate forgets over LAG_WINDOW_S)."""
    measuring = SetPointCommands(send_set_point=True)  # measures, does not lead
    trailing = follow_ramp(measuring, speed_scale, command_delay)
    expected = command_delay + (1.0 - speed_scale) / speed_scale * ARM_STEP
    assert np.mean(trailing) == pytest.approx(expected, abs=1e-9)
    assert np.ptp(trailing) < 1e-6  # steady
    assert measuring.lag == pytest.approx(expected, abs=1e-3)
    led = follow_ramp(SetPointCommands(True, send_set_point=True), speed_scale, command_delay)
    assert np.max(np.abs(led[-100:])) < 1e-3  # the last second: the estimate settled


def test_a_trajectory_restarted_from_the_arms_state_makes_the_half_speed_arm_lag_ninefold():
    """Why the commands carry the set point at time 0: sent as one point at the horizon,
    each trajectory starts from where the half-speed arm lags (joint_trajectory_controller
    interpolates from its state), and the arm trails the ramp by nine times one step's
    5 ms (over topics the node measured 57-86 ms this way)."""
    trailing, lag = follow_ramp_restarted(0.5)
    assert trailing > 8.5 * ARM_STEP  # 44 ms
    assert lag == pytest.approx(trailing, abs=1e-3)


def test_the_lag_is_bounded_and_a_restart_begins_at_the_measured_joints():
    """An arm that does not move at all is no lag to lead by: the estimate stops at
    MAX_LAG_S; after a restart the next command starts from the measured joints again
    (plus the lead), and readings older than the command in force are not counted."""
    commands = SetPointCommands(compensate_lag=True)
    q = np.zeros(3)
    for k in range(100):
        commands.measure(q, k * PERIOD)
        commands.command(q, VELOCITY, k * PERIOD, HORIZON)
    assert commands.lag == MAX_LAG_S
    commands.restart()
    command = commands.command(q, VELOCITY, 1.0, HORIZON)
    np.testing.assert_allclose(
        command.positions, q + (HORIZON + MAX_LAG_S) * VELOCITY, rtol=0, atol=1e-15
    )
    before = commands.lag, commands._sums.copy()
    commands.measure(q + 1.0, 0.99)  # measured before that command was sent
    assert (commands.lag, *commands._sums) == (before[0], *before[1])
