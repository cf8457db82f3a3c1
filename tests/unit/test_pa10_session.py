"""pa10_ik_node's TrackingSession without ROS: the checks on its inputs, the watchdog on
stale pressure and joint states, and the commands it returns, on a clock the test turns."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from harness import ManualClock
from pa10_ik_node.commands import MAX_COMMAND_LEAD_S, MAX_LAG_S
from pa10_ik_node.ik import RateSolver
from pa10_ik_node.session import JOINT_LIMIT_SLACK_RAD, TrackingSession
from pa10_ik_node.settings import ArmSettings, LoopSettings, SolverSettings
from pa10_ik_node.thesis import fixed_step_matrix
from pa10_ik_node.tracking import TrackingConfig, TrackingController
from sensor_sim.scenario import load_scenario
from sensor_sim.surfaces import normal_base, surface_points_base
from vgm_common.errors import InvalidInput
from vgm_common.robot_model import load_robot
from vgm_common.topics import JOINT_STATES_TOPIC, PRESSURE_TOPIC, WAYPOINTS_TOPIC

SCENARIOS = Path(__file__).resolve().parents[2] / 'src' / 'sensor_sim' / 'scenarios'
URDF = Path(__file__).resolve().parents[2] / 'src' / 'vgm_common' / 'urdf' / 'pa10.urdf'
PERIOD = 0.01  # [s]
TIMEOUT = 1.0  # [s] pressure_timeout
HORIZON = 0.05  # [s]


@pytest.fixture(scope='module')
def scenario():
    return load_scenario(SCENARIOS / 'default.yaml')


@pytest.fixture()
def session(scenario):
    robot = load_robot(scenario.robot.model, scenario.robot.tool_length)
    controller = TrackingController(robot, RateSolver('ours', [1.0] * 7), TrackingConfig())
    settings = LoopSettings(rate=1.0 / PERIOD, pressure_timeout=TIMEOUT, command_horizon=HORIZON)
    return TrackingSession(controller, 'tool0', settings, clock=ManualClock(100.0))


def waypoints_on(surface, count=12):
    """A short line of waypoints on the surface, z along the inward normal."""
    points = surface_points_base(surface, np.linspace([-0.05, 0.0], [0.05, 0.0], count))
    z = -normal_base(surface, points)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for pose, point, axis in zip(poses, points, z):
        x = np.cross([0.0, 1.0, 0.0], axis)
        x /= np.linalg.norm(x)
        pose[:3, :3] = np.column_stack([x, np.cross(axis, x), axis])
        pose[:3, 3] = point
    return poses


def feed(session, scenario, force=0.0):
    """Joint states at the scenario's start and a pressure reading, now."""
    session.take_joint_state(session.robot.joint_names, scenario.robot.initial_joints)
    session.take_pressure('tool0', force)


def test_inputs_that_cannot_be_the_arms_are_refused_and_nothing_is_kept(session, scenario):
    names = list(session.robot.joint_names)
    q0 = np.asarray(scenario.robot.initial_joints, dtype=float)
    bad = {
        'duplicate': (names[:-1] + names[:1], q0),
        'unknown': (names[:-1] + ['elbow'], q0),
        'missing': (names[:-1], q0[:-1]),
        'outside its limits': (
            names,
            np.where(
                np.arange(7) == 2, session.robot.upper_limits + 2 * JOINT_LIMIT_SLACK_RAD, q0
            ),
        ),
    }
    for what, (joint_names, positions) in bad.items():
        with pytest.raises(InvalidInput, match=what):
            session.take_joint_state(joint_names, positions)
    assert session.q is None
    with pytest.raises(InvalidInput, match="expected the tip frame 'tool0'"):
        session.take_pressure('panda_hand_tcp', 5.0)
    with pytest.raises(InvalidInput, match='sanity bound'):
        session.take_pressure('tool0', float('nan'))
    assert session.pressure_time is None
    with pytest.raises(InvalidInput, match="expected 'base_link'"):
        session.take_waypoints('map', waypoints_on(scenario.surface))
    assert session.waypoints is None
    # In the robot's own order or any other: the same joints.
    session.take_joint_state(names[::-1], q0[::-1])
    np.testing.assert_array_equal(session.q, q0)


def test_start_names_what_is_missing_and_nothing_moves_before_joint_states(session, scenario):
    assert session.control_step() is None  # no joint state yet
    ok, message, hold = session.start()
    assert not ok and hold is None
    for topic in (WAYPOINTS_TOPIC, JOINT_STATES_TOPIC, PRESSURE_TOPIC):
        assert topic in message
    feed(session, scenario)
    output = session.control_step()
    assert output.command is None  # idle: the pose only
    np.testing.assert_allclose(
        output.T_base_tool, session.robot.forward_kinematics(session.q), atol=1e-12
    )


def test_stale_pressure_stops_the_arm_with_a_hold_at_the_measured_joints(session, scenario):
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    ok, message, _ = session.start()
    assert ok, message
    output = session.control_step()
    assert output.command.horizon == HORIZON and np.any(output.command.velocities != 0)
    # Joint states keep coming, the pressure does not: stopped once it is older than
    # pressure_timeout, at a step that follows a regular one (not after a stall).
    output = run_without_pressure(session, TIMEOUT + 5 * PERIOD)
    assert session.controller.phase == 'stopped'
    assert 'stale pressure: no /tool/pressure for more than 1.0 s' in session.controller.reason
    assert session.clock.now - session.pressure_time == pytest.approx(TIMEOUT + PERIOD, abs=PERIOD)
    np.testing.assert_array_equal(output.command.positions, session.q)
    assert output.command.horizon == 0.0 and not np.any(output.command.velocities)


def run_without_pressure(session, seconds):
    """Control steps every PERIOD with joint states and no pressure, for ``seconds`` or
    until the task stops; returns the last output."""
    for _ in range(int(round(seconds / PERIOD))):
        session.clock.now += PERIOD
        session.take_joint_state(session.robot.joint_names, session.q)
        output = session.control_step()
        if session.controller.phase == 'stopped':
            break
    return output


def test_a_changed_pressure_timeout_and_command_horizon_apply_at_the_next_step(session, scenario):
    """set_parameters while the task runs: the node gives the session its new settings,
    read at every step (they were copied once, and a new pressure_timeout or
    command_horizon was ignored until a restart)."""
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    assert session.start()[0]
    assert session.control_step().command.horizon == HORIZON
    session.settings = replace(session.settings, command_horizon=0.02, pressure_timeout=1.5)
    session.take_pressure('tool0', 0.0)
    command = session.control_step().command
    assert command.horizon == 0.02 and np.any(command.velocities != 0)
    np.testing.assert_allclose(
        command.positions, session.q + 0.02 * command.velocities, rtol=0, atol=1e-15
    )
    # Without pressure for 1.3 s, beyond the old timeout: still running; stopped past
    # 1.5 s (the arm stands still here: before the task's own 2 s no-progress failure).
    run_without_pressure(session, 1.3)
    assert session.controller.phase == 'approach', session.controller.reason
    run_without_pressure(session, 0.2 + 5 * PERIOD)
    assert session.controller.phase == 'stopped'
    assert 'no /tool/pressure for more than 1.5 s' in session.controller.reason
    assert session.clock.now - session.pressure_time == pytest.approx(1.5 + PERIOD, abs=PERIOD)


def test_a_stall_of_the_loop_itself_is_not_taken_for_stale_inputs(session, scenario):
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    assert session.start()[0]
    session.control_step()
    # The loop was not run for 2 s (its executor starved); the newest messages are still
    # queued behind it: this step must not stop the task on their age.
    session.clock.now += 2.0
    session.control_step()
    assert session.controller.phase == 'approach'
    # The next step, without new messages, does.
    session.clock.now += PERIOD
    session.control_step()
    assert session.controller.phase == 'stopped'
    assert 'stale pressure' in session.controller.reason


def test_stop_and_an_internal_error_return_a_hold(session, scenario):
    assert session.stop('stop requested') is None  # no joints yet: nothing to hold
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    assert session.start()[0]
    hold = session.fail('control step: RuntimeError: boom')
    assert session.controller.phase == 'failed'
    np.testing.assert_array_equal(hold.positions, session.q)
    assert hold.horizon == 0.0


def test_a_session_is_made_from_the_settings_and_a_wrong_one_names_its_parameter():
    arm = ArmSettings()
    session = TrackingSession.create(
        arm, SolverSettings(method='dls'), TrackingConfig(), LoopSettings()
    )
    assert session.tip_frame == 'tool0' and session.control_period == 0.01
    assert arm.tool_length_m == 0.1  # the built-in model's own tool
    T = session.robot.forward_kinematics(np.zeros(7))
    bare = replace(arm, tool_length=0.0).load().forward_kinematics(np.zeros(7))
    # The tool adds 0.1 m along the tip's z axis.
    np.testing.assert_allclose(T[:3, 3] - bare[:3, 3], 0.1 * bare[:3, 2], atol=1e-12)
    assert session.controller.solver.method == 'dls'
    assert session.controller.velocity_limits.max() <= arm.max_joint_velocity
    with pytest.raises(InvalidInput, match="'weights' needs 7 values, got 6"):
        TrackingSession.create(
            arm, SolverSettings(weights=(1.0,) * 6), TrackingConfig(), LoopSettings()
        )
    with pytest.raises(InvalidInput, match='parameter tip_frame') as error:
        replace(arm, robot=str(URDF), tip_frame='no_such_frame').load()
    assert error.value.key == 'tip_frame'
    with pytest.raises(InvalidInput, match='parameter robot'):
        replace(arm, robot='pa11').load()


def test_phase_changes_are_told_once_at_their_level_and_the_status_follows(session, scenario):
    assert session.phase_change() is None  # idle, as it started
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    assert session.start()[0]
    assert session.phase_change() == ('info', 'phase approach', '')
    assert session.phase_change() is None
    session.control_step()
    status = session.status()
    assert status.level == 'ok' and status.message == 'approach'
    assert status.values['phase'] == 'approach' and status.values['method'] == 'ours'
    assert 'fixed_step_radius' not in status.values
    session.stop('stop requested')
    assert session.phase_change() == ('warn', 'phase stopped: stop requested', '')
    assert session.status().level == 'warn'
    assert session.start()[0] and session.phase_change().message == 'phase approach'
    session.fail('control step: RuntimeError: boom')
    assert session.internal_errors == 1
    change = session.phase_change()
    assert change.level == 'error' and 'boom' in change.message
    assert session.status().level == 'error'


def test_a_new_solver_applies_and_primal_dual_reports_its_fixed_step_radius(session, scenario):
    feed(session, scenario)
    weights = (1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0)
    settings = SolverSettings(method='primal_dual', weights=weights, mu=0.02, eta=0.02)
    session.configure_solver(settings)
    assert session.controller.solver.method == 'primal_dual'
    values = session.status().values
    J = session.robot.jacobian(session.q)
    expected = np.max(
        np.abs(np.linalg.eigvals(fixed_step_matrix(J, np.diag(weights), 100.0, 0.02, 0.02)))
    )
    assert float(values['fixed_step_radius']) == pytest.approx(expected, rel=1e-5)
    assert values['failure_condition'] == 'none detected'


def test_a_command_continues_the_previous_set_point_within_its_lead_of_the_joints(
    session, scenario
):
    """Each moving command starts where the previous one's set point is now, not at the
    measured joints (older than the arm; and an arm lagging its set point restarted from
    its own position made 0.16-0.24 of its commands over topics), leading the measured
    joints by at most MAX_COMMAND_LEAD_S of its joint speeds; a hold and a new start
    begin again from the measured joints."""
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    assert session.start()[0]
    q = session.q.copy()
    first = session.control_step().command
    np.testing.assert_allclose(first.positions, q + HORIZON * first.velocities, atol=1e-15)
    # A period later with the same joint state (the arm's newer one not yet here).
    session.clock.now += PERIOD
    feed(session, scenario)
    second = session.control_step().command
    anchor = second.positions - HORIZON * second.velocities
    np.testing.assert_allclose(anchor, q + PERIOD * first.velocities, rtol=0, atol=1e-12)
    # An arm that does not move: the set point runs ahead up to the bound, no further.
    for _ in range(30):
        session.clock.now += PERIOD
        feed(session, scenario)
        previous = session.commands.nominal[1]
        session.control_step()
        command = session.commands.nominal[1]  # as sent less the arm's lag (its own test)
        lead = np.abs(command.positions - HORIZON * command.velocities - q)
        assert np.all(lead <= MAX_COMMAND_LEAD_S * np.abs(previous.velocities) + 1e-12)
    assert session.controller.phase == 'approach', session.controller.reason
    assert np.any(lead > 0.9 * MAX_COMMAND_LEAD_S * np.abs(previous.velocities))
    session.stop('stop requested')
    assert session.start()[0]
    session.control_step()
    command = session.commands.nominal[1]
    np.testing.assert_allclose(command.positions, q + HORIZON * command.velocities, atol=1e-15)


def test_lead_arm_lag_sends_the_set_point_one_measured_lag_ahead(session, scenario):
    """An arm that does not follow at all measures about the largest lag (MAX_LAG_S): with
    lead_arm_lag the command goes that far ahead of the continued set point along the
    joint speeds, without it the command is the set point itself."""
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    assert session.start()[0]
    for lead_on in (False, True):
        session.settings = replace(session.settings, lead_arm_lag=lead_on)
        for _ in range(40):
            session.clock.now += PERIOD
            feed(session, scenario)
            sent = session.control_step().command
        nominal = session.commands.nominal[1]
        assert session.controller.phase == 'approach', session.controller.reason
        lag = session.commands.lag
        # (0.089 s since the gains fall with the lag: the commands' speeds change more)
        assert 0.8 * MAX_LAG_S < lag <= MAX_LAG_S
        ahead = sent.positions - nominal.positions
        if lead_on:  # along the (smoothed) joint speeds, which hardly change here
            np.testing.assert_allclose(ahead, lag * sent.velocities, rtol=0.05, atol=1e-6)
            assert np.max(np.abs(ahead)) > 1e-3
        else:
            assert np.array_equal(ahead, np.zeros_like(ahead))


def test_a_simulator_starved_for_two_seconds_is_no_arm_that_cannot_progress(scenario):
    """The simulator's joint states and pressure stop for 2.5 s (a starved process)
    while the loop runs on, within a pressure_timeout of 3 s: the task's no-progress
    check (2 error_timeouts: 2 s) judged the last, unchanged reading and failed the
    approach ('cannot reach the pre-contact pose ... no progress for 2.0 s', over topics
    on Talos's arm at half speed); it waits for a new reading instead, and the watchdog
    still stops the task once the inputs are older than the timeout."""
    robot = load_robot(scenario.robot.model, scenario.robot.tool_length)
    controller = TrackingController(robot, RateSolver('ours', [1.0] * 7), TrackingConfig())
    settings = LoopSettings(rate=1.0 / PERIOD, pressure_timeout=3.0, command_horizon=HORIZON)
    session = TrackingSession(controller, 'tool0', settings, clock=ManualClock(100.0))
    feed(session, scenario)
    session.take_waypoints('base_link', waypoints_on(scenario.surface))
    assert session.start()[0]
    for _ in range(250):  # 2.5 s without a message
        session.clock.now += PERIOD
        output = session.control_step()
    assert controller.phase == 'approach', controller.reason
    assert output.command is None  # nothing new to command on a reading this old
    feed(session, scenario)  # the simulator is back
    session.clock.now += PERIOD
    assert session.control_step().command is not None
    for _ in range(310):
        session.clock.now += PERIOD
        session.control_step()
    assert controller.phase == 'stopped' and 'stale' in controller.reason
