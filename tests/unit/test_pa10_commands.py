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
        arm.set_trajectory(NAMES, [command.horizon], [command.positions], [command.velocities], t)
        for _ in range(2):
            t += PERIOD / 2
            arm.step(t, PERIOD / 2)
        if t > duration / 2:
            trailing.append(np.dot(VELOCITY * t - arm.q, VELOCITY) / np.dot(VELOCITY, VELOCITY))
    return np.array(trailing)


@pytest.mark.parametrize(
    ('speed_scale', 'command_delay'), [(0.5, 0.0), (1.0, 0.02), (0.5, 0.02), (1.0, 0.0)]
)
def test_the_measured_lag_is_the_arms_trailing_time_and_the_lead_removes_it(
    speed_scale, command_delay
):
    """A position loop that closes half its gap every 5 ms (the half-speed arm) and an
    arm whose commands act 20 ms late trail a ramp by a constant time: the estimate
    equals it within 1 ms; commanding one lag ahead leaves under 1 ms of it once
    settled (the estimate forgets over LAG_WINDOW_S)."""
    measuring = SetPointCommands()  # measures, does not lead
    trailing = follow_ramp(measuring, speed_scale, command_delay)
    assert np.ptp(trailing) < 1e-6  # a steady lag, the ground truth
    assert measuring.lag == pytest.approx(np.mean(trailing), abs=1e-3)
    if speed_scale < 1.0 or command_delay > 0:
        assert np.mean(trailing) > 0.015  # a lag worth compensating
    led = follow_ramp(SetPointCommands(compensate_lag=True), speed_scale, command_delay)
    assert np.max(np.abs(led[-100:])) < 1e-3  # the last second: the estimate settled


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
