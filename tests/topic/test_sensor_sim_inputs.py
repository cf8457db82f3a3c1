"""Topic level, real processes: sensor_sim's arm and pressure sensor over topics, and
its handling of bad input (malformed scenario, bad parameter, bad joint commands)."""

import numpy as np
import pytest
import yaml
from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from harness import SCENARIO_DIR, executable
from sensor_sim.contact import joint_vector_pressing
from sensor_sim.scenario import load_scenario
from vgm_common.conversions import stamp_to_ns
from vgm_common.qos import DEFAULT_QOS
from vgm_common.robot_model import JOINT_NAMES, load_robot

SCENARIO = SCENARIO_DIR / 'default.yaml'
# From the default scenario's initial pose, this joint step lowers the tool into the surface.
LOWERING_JOINT_STEP = np.array([0.0, 0.25, 0.0, 0.25, 0.0, 0.15, 0.0])  # [rad]


def trajectory(names, q, seconds=0.0):
    point = JointTrajectoryPoint(
        positions=[float(x) for x in q],
        time_from_start=Duration(sec=int(seconds), nanosec=int(seconds % 1 * 1e9)),
    )
    return JointTrajectory(joint_names=list(names), points=[point])


def pressing_configuration(scenario, penetration):
    """A joint vector whose tool tip is ``penetration`` [m] below the surface."""
    robot = load_robot(scenario.robot.model, scenario.robot.tool_length)
    q_start = scenario.robot.initial_joints
    return joint_vector_pressing(
        robot, scenario.surface, q_start, q_start + LOWERING_JOINT_STEP, penetration
    )


@pytest.fixture
def sim(spawn, rclpy_node):
    return start_sim(spawn, rclpy_node)


def start_sim(spawn, rclpy_node, *extra):
    """sensor_sim on the default scenario (``extra``: more arguments) and the test node's
    subscriptions and command publisher, once joint states flow."""
    process = spawn(
        [
            executable('sensor_sim'),
            '--ros-args',
            '-p',
            f'scenario:={SCENARIO}',
            '-p',
            'calibration_phase:=false',
            '-p',
            'rate:=2',
            *extra,
        ]
    )
    states, wrenches, diagnostics = [], [], []
    rclpy_node.create_subscription(JointState, '/joint_states', states.append, DEFAULT_QOS)
    rclpy_node.create_subscription(WrenchStamped, '/tool/pressure', wrenches.append, DEFAULT_QOS)
    rclpy_node.create_subscription(
        DiagnosticArray, '/diagnostics', diagnostics.append, DEFAULT_QOS
    )
    publisher = rclpy_node.create_publisher(
        JointTrajectory, '/pa10_controller/joint_trajectory', DEFAULT_QOS
    )
    rclpy_node.spin_until(
        lambda: len(states) > 10 and publisher.get_subscription_count(),
        60,
        'sensor_sim joint states',
    )
    return process, publisher, states, wrenches, diagnostics


def test_arm_moves_to_a_pressing_pose_and_the_sensor_reads_the_force(sim, rclpy_node):
    process, publisher, states, wrenches, _ = sim
    scenario = load_scenario(SCENARIO)
    penetration = 0.004  # [m]
    q_goal = pressing_configuration(scenario, penetration)
    assert wrenches[-1].wrench.force.z == 0.0  # not in contact at the start
    # Joint order shuffled: the sim maps names, as joint_trajectory_controller does.
    order = [6, 2, 0, 4, 1, 5, 3]
    publisher.publish(trajectory([JOINT_NAMES[i] for i in order], q_goal[order], 1.0))
    rclpy_node.spin_until(
        lambda: np.allclose(states[-1].position, q_goal, atol=1e-9), 30, 'the arm to arrive'
    )
    arrived_ns = stamp_to_ns(states[-1].header.stamp)
    rclpy_node.spin_until(
        lambda: len(wrenches) > 200 and stamp_to_ns(wrenches[-200].header.stamp) > arrived_ns,
        30,
        '200 pressure readings in place',
    )
    forces = np.array(
        [w.wrench.force.z for w in wrenches if stamp_to_ns(w.header.stamp) > arrived_ns]
    )
    sigma = scenario.noise.pressure_sigma
    expected = scenario.contact_stiffness * penetration  # [N]
    assert forces.mean() == pytest.approx(expected, abs=4 * sigma / np.sqrt(len(forces)) + 1e-3)
    assert forces.std() == pytest.approx(sigma, rel=0.25)


def test_a_delayed_arm_follows_a_trajectory_only_its_delay_after_the_stamp(spawn, rclpy_node):
    """arm_command_delay 0.3 s: a trajectory stamped T0 (a straight joint move to a
    pressing pose in 1 s) is followed as if stamped T0 + 0.3 s. The position arm (speed
    scale 1, well within its velocity limits) is on that line at its own clock on every
    joint state, however late the loaded machine runs its steps: still up to T0 + 0.3 s,
    at fraction (t - T0 - 0.3 s) / 1 s of the move after that, at the goal from T0 + 1.3 s.
    So the test reads the delay from positions and stamps, not from when the steps fell
    (under load a step can land microseconds before T0 + 1.3 s or 100 ms after it)."""
    from vgm_common.conversions import make_header

    delay, duration = 0.3, 1.0  # [s]
    process, publisher, states, _, _ = start_sim(
        spawn, rclpy_node, '-p', f'arm_command_delay:={delay}'
    )
    scenario = load_scenario(SCENARIO)
    robot = load_robot(scenario.robot.model, scenario.robot.tool_length)
    q_start = np.array(states[-1].position)
    q_goal = pressing_configuration(scenario, 0.004)
    step = q_goal - q_start
    # The line's speed stays below the limits: every step can reach its set point.
    assert np.all(np.abs(step) / duration < 0.5 * robot.velocity_limits)
    command = trajectory(JOINT_NAMES, q_goal, duration)
    # 0.5 s ahead of the last state seen: the command is there before it takes effect
    # (T0 + 0.8 s) even with the test process and the simulator's executor starved.
    t0_ns = stamp_to_ns(states[-1].header.stamp) + 500_000_000
    command.header = make_header(t0_ns, 'base_link')
    publisher.publish(command)
    settled = delay + duration + 0.1  # [s] after T0
    rclpy_node.spin_until(
        lambda: stamp_to_ns(states[-1].header.stamp) > t0_ns + settled * 1e9,
        30,
        'joint states past the end of the delayed move',
    )
    t = np.array([(stamp_to_ns(m.header.stamp) - t0_ns) * 1e-9 for m in states])
    q = np.array([m.position for m in states])
    # A step follows the command in force at its start (the previous state's stamp); a
    # state dropped on the way only makes the previous stamp seen earlier (conservative).
    in_force = np.concatenate([[False], t[:-1] >= delay])
    still = t <= delay
    fraction = np.clip((t - delay) / duration, 0.0, 1.0)
    expected = q_start + fraction[:, np.newaxis] * step
    # Stamps are doubles of ~1.8e9 s (0.24 us apart) on both sides: positions agree to
    # the line's speed times a few microseconds; 5 us of time, 1e-6 rad here.
    atol = 5e-6 * np.max(np.abs(step)) / duration
    checked = still | in_force
    errors = np.max(np.abs(q[checked] - expected[checked]), axis=1)
    moving = in_force & (fraction > 0) & (fraction < 1)
    counts = {
        'held after T0': int(np.sum(still & (t > 0))),
        'moving': int(np.sum(moving)),
        'arrived': int(np.sum(in_force & (fraction == 1))),
    }
    # The delay each moving state implies: its stamp less the time its position is at.
    implied = t[moving] - duration * ((q[moving] - q_start) @ step) / np.dot(step, step)
    print(
        f'states {counts}; delay read from positions {implied.min():.7f}..'
        f'{implied.max():.7f} s; max error {np.max(errors):.2e} rad (tolerance {atol:.1e})'
    )
    assert np.max(errors) < atol
    # 200 Hz states: 60 in the hold after T0, 200 moving, 20 arrived when unloaded; a
    # tenth of that still shows each phase.
    assert counts['held after T0'] >= 10 and counts['moving'] >= 20 and counts['arrived'] >= 2
    assert np.all(np.abs(implied - delay) < 5e-6)
    assert 'Traceback' not in process.output()


@pytest.mark.parametrize(
    'problem, names, q',
    [
        ('unknown names', [f'joint_{i}' for i in range(7)], np.zeros(7)),
        ('wrong length', list(JOINT_NAMES), np.zeros(6)),
        ('NaN', list(JOINT_NAMES), np.array([0, 0, np.nan, 0, 0, 0, 0.0])),
    ],
)
def test_bad_joint_commands_are_rejected_and_the_arm_holds(sim, rclpy_node, problem, names, q):
    process, publisher, states, _, diagnostics = sim
    before = np.array(states[-1].position)
    publisher.publish(trajectory(names, q, 0.5))
    rclpy_node.spin_until(
        lambda: any(
            'rejected /pa10_controller/joint_trajectory' in s.name
            for d in diagnostics
            for s in d.status
        ),
        20,
        f'a diagnostic rejecting the {problem} command',
    )
    seen = len(states)
    rclpy_node.spin_until(lambda: len(states) > seen + 100, 20, 'more joint states')
    np.testing.assert_array_equal(states[-1].position, before)
    assert process.alive()
    assert 'Traceback' not in process.output()


def run_to_exit(spawn, argv, timeout=60):
    process = spawn(argv)
    process.proc.wait(timeout)
    return process.proc.returncode, process.output()


@pytest.mark.parametrize(
    'edit, key',
    [
        (lambda d: d['cameras']['left'].update(fx='abc'), 'cameras.left.fx'),
        (lambda d: d['contact'].pop('stiffness'), 'contact.stiffness'),
        (lambda d: d['surface'].update(type='torus'), 'surface.type'),
        (lambda d: d['lighting'].update(intensity=float('nan')), 'lighting.intensity'),
        (
            lambda d: d['cameras']['aux']['pose'].update(look_at=[0.4, 0.45, 2.0]),
            'cameras.aux.pose',
        ),
    ],
)
def test_malformed_scenario_fails_at_start_with_one_line_naming_the_key(
    spawn, tmp_path, edit, key
):
    data = yaml.safe_load(SCENARIO.read_text())
    edit(data)
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump(data))
    status, output = run_to_exit(
        spawn, [executable('sensor_sim'), '--ros-args', '-p', f'scenario:={path}']
    )
    assert status == 2
    errors = [line for line in output.splitlines() if 'error' in line]
    assert len(errors) == 1 and key in errors[0], output
    assert 'Traceback' not in output


def test_parameter_of_the_wrong_kind_is_reported_in_one_line(spawn):
    status, output = run_to_exit(
        spawn, [executable('sensor_sim'), '--ros-args', '-p', 'rate:=fast']
    )
    assert status == 2 and "'rate'" in output and 'Traceback' not in output
