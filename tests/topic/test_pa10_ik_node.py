"""Topic level, real processes: pa10_ik_node closes the loop with sensor_sim's arm and
pressure sensor along a piece of the true curve on S3, and rejects bad input."""

import time
import zipfile

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Path
from rcl_interfaces.srv import GetParameters
from rclpy.clock import Clock
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from vgm_evaluation.graph_probe import status_values

from harness import SCENARIO_DIR, executable, wait_for
from pa10_ik_node.path import WaypointPath
from sensor_sim.scenario import load_scenario
from sensor_sim.surfaces import normal_base, surface_points_base
from vgm_common.conversions import make_header, matrices_to_path, pose_to_matrix, stamp_to_ns
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.robot_model import JOINT_NAMES, load_robot
from vgm_common.topics import (
    JOINT_TRAJECTORY_TOPIC,
    PRESSURE_TOPIC,
    TOOL_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)
from vgm_evaluation import task_generator

SCENARIO = SCENARIO_DIR / 'default.yaml'
DESIRED_FORCE = 5.0  # [N]
TRACKING_STATUS = 'pa10_ik_node: tracking'
SPEED = 0.015  # [m/s]


def waypoints_along(points, surface):
    """(N, 4, 4) waypoints: origin on the curve, x along it, z = -(true surface normal)."""
    approach = -normal_base(surface, points)
    poses = []
    for i, (point, z) in enumerate(zip(points, approach)):
        j = min(i + 1, len(points) - 1)
        x = points[j] - points[j - 1]
        x -= z * (z @ x)
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = point
        poses.append(T)
    return np.array(poses)


def lateral_distance(point, curve, approach):
    """Distance [m] from ``point`` to the dense polyline ``curve`` across the approach
    axis ``approach`` at its nearest vertex (the indentation is the force's business)."""
    a, b = curve[:-1], curve[1:]
    t = np.clip(np.einsum('ij,ij->i', point - a, b - a) / np.sum((b - a) ** 2, axis=1), 0, 1)
    nearest = a + t[:, None] * (b - a)
    i = int(np.argmin(np.linalg.norm(nearest - point, axis=1)))
    d = point - nearest[i]
    z = approach[min(i, len(approach) - 1)]
    return float(np.linalg.norm(d - z * (z @ d)))


class Probe:
    """What the test node receives from pa10_ik_node and the simulator (tool poses,
    pressure, commands, the tracking statuses with their stamps, rejections), on the
    graph probe; the waypoints it publishes."""

    def __init__(self, node):
        self.graph = node.graph
        self.graph.watch_diagnostics()
        self.poses = self.graph.record(TOOL_POSE_TOPIC, PoseStamped)
        self.pressures = self.graph.record(PRESSURE_TOPIC, WrenchStamped)
        self.commands = self.graph.record(JOINT_TRAJECTORY_TOPIC, JointTrajectory)
        self.path_publisher = node.create_publisher(Path, WAYPOINTS_TOPIC, LATCHED_QOS)

    @property
    def tracking(self):
        """(stamp_ns, {key: value}, message) of the tracking statuses, oldest first."""
        return [
            (stamp, status_values(status), status.message)
            for stamp, status in zip(self.graph.status_stamps_ns, self.graph.statuses)
            if status.name == TRACKING_STATUS
        ]

    @property
    def rejected(self):
        """(name, message) of the statuses that rejected an input, oldest first."""
        return [(s.name, s.message) for s in self.graph.statuses if 'rejected' in s.name]

    def phase(self):
        status = self.graph.status(TRACKING_STATUS)
        return status_values(status)['phase'] if status is not None else None

    def wait_until_done(self, timeout, also=()):
        """Spin until the phase is done (or one of ``also``); on timeout, say why: the
        node's last status and the longest pause of /tool/pressure as this probe received
        it (the node stops on a pressure stale for 1 s; a pause seen here too was the
        simulator's or the machine's, none here points at the node's own subscription)."""
        phases = ('done', *also)
        try:
            self.graph.wait(lambda: self.phase() in phases, timeout, 'phase done')
        except TimeoutError:
            stamps = np.array([stamp_to_ns(m.header.stamp) for m in self.pressures]) * 1e-9
            pause = np.max(np.diff(stamps)) if len(stamps) > 1 else float('nan')
            last = self.graph.status(TRACKING_STATUS)
            raise AssertionError(
                f'phase not {" or ".join(phases)} after {timeout} s: last status '
                f'{last.message if last else "no tracking status"!r}; '
                f'longest /tool/pressure pause at the probe {pause:.3f} s'
            ) from None

    def first_stamp(self, phase):
        return next(stamp for stamp, values, _ in self.tracking if values['phase'] == phase)

    def call(self, service, timeout=20):
        return self.graph.call(f'/pa10_ik_node/{service}', timeout)


# The tracking tests measure tracking: on the loaded 2-core CI machine the simulator's
# arm thread was once starved for 1.0-1.1 s (the probe saw the same pause on
# /tool/pressure) and the node rightly stopped on its 1 s stale-pressure watchdog, which
# test_stale_pressure_stops_the_arm checks at its default.
TRACKING_ARGS = ('-p', 'pressure_timeout:=3.0')


def start_node(spawn, *extra):
    return spawn(
        [
            executable('pa10_ik_node'),
            '--ros-args',
            '-p',
            'tool_length:=0.1',
            '-p',
            f'desired_force:={DESIRED_FORCE}',
            '-p',
            f'speed:={SPEED}',
            *extra,
        ]
    )


@pytest.mark.parametrize('force_law', ['integral', 'tilt'])
def test_tracks_a_piece_of_the_true_curve_on_s3_with_force(spawn, rclpy_node, tmp_path, force_law):
    scenario = load_scenario(SCENARIO)
    sim = spawn(
        [
            executable('sensor_sim'),
            '--ros-args',
            '-p',
            f'scenario:={SCENARIO}',
            '-p',
            'calibration_phase:=false',
            '-p',
            'rate:=2',
            '-p',
            f'ground_truth_dir:={tmp_path}',
        ]
    )
    # As these force-law runs were measured: adapt_response (on by default) off (with it,
    # the tilt law once pressed 13 % over late in a loaded make test) and the descent at
    # the path's speed (at the default max_tip_speed, twice that, the first markers after
    # touchdown were 8-16 % off the desired force in a loaded make test).
    node = start_node(
        spawn,
        '-p',
        f'force_law:={force_law}',
        '-p',
        'adapt_response:=false',
        '-p',
        f'max_tip_speed:={SPEED}',
        *TRACKING_ARGS,
    )
    probe = Probe(rclpy_node)
    curves = {}

    def curve_written():  # the simulator may still be writing the file
        try:
            with np.load(tmp_path / 'curve_base.npz') as data:
                curves.update({key: data[key] for key in data.files})
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            return False
        return 'arr_0' in curves

    rclpy_node.spin_until(curve_written, 60, 'the ground truth curve')
    curve = curves['arr_0']  # (2000, 3) closed loop [m]
    piece = curve[:120]  # about 4.4 cm of the loop, from its start
    waypoints = waypoints_along(piece[::5], scenario.surface)
    probe.path_publisher.publish(
        matrices_to_path(waypoints, Clock().now().nanoseconds, 'base_link')
    )
    rclpy_node.spin_until(
        lambda: len(probe.poses) > 10 and len(probe.pressures) > 10, 60, 'tool poses and pressure'
    )
    # the latched path reaches the node once discovery matched it (CI: after the poses)
    rclpy_node.spin_until(lambda: 'waypoints' in node.output(), 20, 'the path taken')
    response = probe.call('start_tracking')
    assert response.success, response.message
    probe.wait_until_done(90)

    started, ended = probe.first_stamp('tracking'), probe.first_stamp('done')
    tips = np.array(
        [
            pose_to_matrix(p.pose)[:3, 3]
            for p in probe.poses
            if started <= stamp_to_ns(p.header.stamp) <= ended
        ]
    )
    forces = np.array(
        [
            w.wrench.force.z
            for w in probe.pressures
            if started <= stamp_to_ns(w.header.stamp) <= ended
        ]
    )
    approach = -normal_base(scenario.surface, piece)
    errors = np.array([lateral_distance(tip, piece, approach) for tip in tips])
    rms, worst = np.sqrt(np.mean(errors**2)), errors.max()
    along = np.linalg.norm(tips[-1] - piece[-1])
    print(
        f'{force_law}: {len(tips)} tool poses while tracking: lateral RMS '
        f'{rms * 1e3:.3f} mm, max '
        f'{worst * 1e3:.3f} mm; force {forces.min():.3f}..{forces.max():.3f} N; end '
        f'{along * 1e3:.2f} mm from the last point'
    )
    assert len(tips) > 50 and len(forces) > 100
    assert rms < 1e-3 and worst < 3e-3
    assert np.all(np.abs(forces - DESIRED_FORCE) < 0.1 * DESIRED_FORCE)
    assert along < 5e-3  # it got to the end of the piece (pressed a few mm in)
    log = node.output()
    assert 'tracking done: rms position error' in log
    assert 'Traceback' not in log + sim.output()


class FakeArm:
    """The test node plays the simulator: joint states at the scenario's start pose and,
    while ``pressure_on``, a pressure reading (so the test controls staleness)."""

    def __init__(self, node, q, names=JOINT_NAMES):
        self.node, self.q, self.names = node, list(q), list(names)
        self.pressure_on = True
        self.joint_publisher = node.create_publisher(JointState, '/joint_states', DEFAULT_QOS)
        self.pressure_publisher = node.create_publisher(
            WrenchStamped, '/tool/pressure', DEFAULT_QOS
        )
        node.create_timer(0.01, self._tick)

    def _tick(self):
        stamp_ns = Clock().now().nanoseconds
        self.joint_publisher.publish(
            JointState(header=make_header(stamp_ns, 'base_link'), name=self.names, position=self.q)
        )
        if self.pressure_on:
            self.pressure_publisher.publish(WrenchStamped(header=make_header(stamp_ns, 'tool0')))


@pytest.fixture
def fake_loop(spawn, rclpy_node):
    scenario = load_scenario(SCENARIO)
    node = start_node(spawn)
    probe = Probe(rclpy_node)
    arm = FakeArm(rclpy_node, scenario.robot.initial_joints)
    rclpy_node.spin_until(lambda: len(probe.poses) > 5, 60, 'tool poses')
    return node, probe, arm, scenario


def path_message(waypoints, frame='base_link'):
    return matrices_to_path(waypoints, Clock().now().nanoseconds, frame)


def short_path(scenario, offset=(0.0, 0.0, 0.0)):
    """5 cm along the surface's x from its centre, shifted by ``offset`` [m]."""
    xy = np.column_stack([np.linspace(0.0, 0.125, 11), np.zeros(11)])
    waypoints = waypoints_along(surface_points_base(scenario.surface, xy), scenario.surface)
    waypoints[:, :3, 3] += offset
    return waypoints


def test_bad_paths_and_joint_states_are_rejected(fake_loop, rclpy_node):
    node, probe, arm, scenario = fake_loop
    good = short_path(scenario)
    bad_paths = {
        'empty': Path(header=make_header(0, 'base_link')),
        'non-finite': path_message(good),
        'wrong frame': path_message(good, 'tool0'),
    }
    bad_paths['non-finite'].poses[3].pose.position.y = float('nan')
    for what, msg in bad_paths.items():
        seen = len(probe.rejected)
        probe.path_publisher.publish(msg)
        rclpy_node.spin_until(
            lambda seen=seen: any('/curve/waypoints' in name for name, _ in probe.rejected[seen:]),
            20,
            f'a diagnostic rejecting the {what} path',
        )
    response = probe.call('start_tracking')  # nothing valid to follow
    assert not response.success and 'waypoints' in response.message
    rclpy_node.spin_until(lambda: probe.tracking, 20, 'tracking diagnostics')
    assert probe.phase() == 'idle'

    arm.names = [f'joint_{i}' for i in range(7)]
    rclpy_node.spin_until(
        lambda: any(
            '/joint_states' in name and 'unknown joint' in message
            for name, message in probe.rejected
        ),
        20,
        'a diagnostic rejecting unknown joint names',
    )
    assert node.alive() and 'Traceback' not in node.output()


def test_unreachable_waypoints_fail_clearly_and_the_arm_holds(fake_loop, rclpy_node):
    node, probe, arm, scenario = fake_loop
    probe.path_publisher.publish(path_message(short_path(scenario, offset=(1.5, 0, 0))))
    rclpy_node.spin_until(lambda: 'waypoints' in node.output(), 20, 'the path taken')
    response = probe.call('start_tracking')
    assert not response.success and 'unreachable' in response.message
    rclpy_node.spin_until(lambda: probe.phase() == 'failed', 20, 'phase failed')
    status = probe.tracking[-1]
    assert 'beyond the reach' in status[2]
    # The hold command may arrive just after the diagnostic (another topic).
    rclpy_node.spin_until(
        lambda: probe.commands and not np.any(probe.commands[-1].points[0].velocities),
        10,
        'a zero-velocity hold command',
    )
    hold = probe.commands[-1].points[0]
    np.testing.assert_allclose(hold.positions, scenario.robot.initial_joints, atol=1e-12)
    assert node.alive() and 'Traceback' not in node.output()


def test_stale_pressure_stops_the_arm(fake_loop, rclpy_node):
    node, probe, arm, scenario = fake_loop
    probe.path_publisher.publish(path_message(short_path(scenario)))
    rclpy_node.spin_until(lambda: 'waypoints' in node.output(), 20, 'the path taken')
    response = probe.call('start_tracking')
    assert response.success, response.message
    rclpy_node.spin_until(
        lambda: probe.phase() == 'approach' and len(probe.commands) > 20, 20, 'approach commands'
    )
    moving = probe.commands[-1].points[0]
    assert np.max(np.abs(moving.velocities)) > 1e-3  # it was heading for the surface
    arm.pressure_on = False
    rclpy_node.spin_until(lambda: probe.phase() == 'stopped', 20, 'phase stopped')
    assert 'stale pressure' in probe.tracking[-1][2]
    rclpy_node.spin_until(
        lambda: not np.any(probe.commands[-1].points[0].velocities),
        10,
        'a zero-velocity hold command',
    )
    count = len(probe.commands)
    hold = probe.commands[-1].points[0]
    np.testing.assert_allclose(hold.positions, scenario.robot.initial_joints, atol=1e-12)
    seen = len(probe.tracking)
    rclpy_node.spin_until(lambda: len(probe.tracking) > seen + 1, 10, 'more diagnostics')
    assert probe.phase() == 'stopped' and len(probe.commands) == count  # and it stays so
    assert node.alive() and 'Traceback' not in node.output()


def test_primal_dual_reports_whether_the_literal_fixed_step_rule_would_converge(spawn, rclpy_node):
    """mu and eta do not steer the arm (the node integrates the network exactly): with
    method primal_dual the diagnostics give the spectral radius of the thesis's
    fixed-step rule at them, > 1 at the thesis's rates (A7.4), < 1 at small ones."""
    from pa10_ik_node.thesis import fixed_step_matrix

    scenario = load_scenario(SCENARIO)
    q = scenario.robot.initial_joints
    J = load_robot('pa10', 0.1).jacobian(q)
    probe = Probe(rclpy_node)
    FakeArm(rclpy_node, q)

    def reported():
        values = probe.tracking[-1][1] if probe.tracking else {}
        return float(values.get('fixed_step_radius', 'nan'))

    for mu in (0.02, 1e-4):
        expected = np.max(np.abs(np.linalg.eigvals(fixed_step_matrix(J, np.eye(7), mu=mu))))
        node = start_node(spawn, '-p', 'method:=primal_dual', '-p', f'mu:={mu}')
        rclpy_node.spin_until(
            lambda expected=expected: reported() == pytest.approx(expected, rel=1e-5),
            30,
            f'fixed_step_radius {expected:.6g} in the diagnostics (mu {mu})',
        )
        assert (expected > 1) == (mu == 0.02)
        node.stop()


def get_parameter(rclpy_node, name, timeout=20):
    """The value message of pa10_ik_node's parameter ``name`` (the node still serves)."""
    client = rclpy_node.create_client(GetParameters, '/pa10_ik_node/get_parameters')
    rclpy_node.spin_until(client.service_is_ready, timeout, 'get_parameters')
    future = client.call_async(GetParameters.Request(names=[name]))
    rclpy_node.spin_until(future.done, timeout, 'get_parameters response')
    return future.result().values[0]


def test_failure_stop_start_failure_stop_keeps_serving(spawn, rclpy_node):
    """Both failure kinds (unreachable at start, no progress while running), each after
    a stop: one process reaches 'stopped' and 'failed' several times (a crash
    once: one log call site at two severities killed it)."""
    scenario = load_scenario(SCENARIO)
    node = start_node(spawn, '-p', 'error_timeout:=0.2')
    probe = Probe(rclpy_node)
    FakeArm(rclpy_node, scenario.robot.initial_joints)  # holds still whatever it is told
    rclpy_node.spin_until(lambda: len(probe.poses) > 5, 60, 'tool poses')
    far, near = short_path(scenario, offset=(100.0, 0, 0)), short_path(scenario)
    for attempt in range(2):
        assert probe.call('stop').success
        rclpy_node.spin_until(lambda: probe.phase() == 'stopped', 20, 'phase stopped')
        probe.path_publisher.publish(path_message(far))
        taken = 2 * attempt
        rclpy_node.spin_until(
            lambda n=taken + 1: node.output().count('waypoints: 11 poses') >= n,
            20,
            'the far path taken',
        )
        response = probe.call('start_tracking')
        assert not response.success and 'unreachable' in response.message
        rclpy_node.spin_until(lambda: probe.phase() == 'failed', 20, 'phase failed')
        assert probe.call('stop').success
        probe.path_publisher.publish(path_message(near))
        rclpy_node.spin_until(
            lambda n=taken + 2: node.output().count('waypoints: 11 poses') >= n,
            20,
            'the near path taken',
        )
        response = probe.call('start_tracking')
        assert response.success, response.message
        # The fake arm never moves: no progress towards the pre-contact pose.
        rclpy_node.spin_until(
            lambda: probe.phase() == 'failed' and 'pre-contact' in probe.tracking[-1][2],
            30,
            'phase failed on no progress',
        )
        assert get_parameter(rclpy_node, 'desired_force').double_value == DESIRED_FORCE
    log = node.output()
    assert log.count('phase failed: unreachable') == 2
    assert log.count('phase failed: cannot reach the pre-contact pose') == 2
    assert log.count('phase stopped: stop requested') >= 2
    assert node.alive() and 'Traceback' not in log and 'Logger severity' not in log


def test_path_along_its_approach_axis_is_rejected(fake_loop, rclpy_node):
    """A crash once: 41 poses going down their own approach axis (identity
    orientations) left the tool frame undefined inside the control timer."""
    node, probe, arm, scenario = fake_loop
    waypoints = np.tile(np.eye(4), (41, 1, 1))
    waypoints[:, :3, 3] = [(0.6, 0.0, 0.30 - 0.001 * i) for i in range(41)]
    probe.path_publisher.publish(path_message(waypoints))
    rclpy_node.spin_until(
        lambda: any(
            '/curve/waypoints' in name and 'approach axis' in message
            for name, message in probe.rejected
        ),
        20,
        'a diagnostic rejecting the path',
    )
    response = probe.call('start_tracking')
    assert not response.success and 'waypoints' in response.message
    assert get_parameter(rclpy_node, 'speed').double_value == SPEED
    assert node.alive() and 'Traceback' not in node.output()


def test_implausible_joint_states_and_pressures_are_rejected(fake_loop, rclpy_node):
    """A duplicate joint name, a position of 1e300 rad, a force of +-1e308 N and a wrench
    without its frame are rejected (each one throttled line and a diagnostic), and the
    node goes on with the good readings."""
    node, probe, arm, scenario = fake_loop
    joints = rclpy_node.create_publisher(JointState, '/joint_states', DEFAULT_QOS)
    pressures = rclpy_node.create_publisher(WrenchStamped, '/tool/pressure', DEFAULT_QOS)
    q = list(scenario.robot.initial_joints)
    duplicate = JointState(name=list(JOINT_NAMES[:6]) + [JOINT_NAMES[0]], position=q)
    huge = JointState(name=list(JOINT_NAMES), position=q[:3] + [1e300] + q[4:])
    cases = [
        (joints, duplicate, '/joint_states', 'duplicate joint names'),
        (joints, huge, '/joint_states', 'outside its limits'),
    ]
    for force, frame, text in (
        (1e308, 'tool0', 'sanity bound'),
        (-1e308, 'tool0', 'sanity bound'),
        (5.0, '', 'frame'),
    ):
        wrench = WrenchStamped(header=make_header(0, frame))
        wrench.wrench.force.z = force
        cases.append((pressures, wrench, '/tool/pressure', text))
    for publisher, msg, topic, text in cases:
        seen = len(probe.rejected)
        rclpy_node.spin_until(lambda p=publisher: p.get_subscription_count() > 0, 20, 'matched')
        publisher.publish(msg)
        rclpy_node.spin_until(
            lambda seen=seen, topic=topic, text=text: any(
                topic in name and text in message for name, message in probe.rejected[seen:]
            ),
            20,
            f'a diagnostic rejecting {text} on {topic}',
        )
    # Still the good state: the tool pose of the start joints.
    count = len(probe.poses)
    rclpy_node.spin_until(lambda: len(probe.poses) > count + 5, 20, 'more tool poses')
    tip = pose_to_matrix(probe.poses[-1].pose)[:3, 3]
    expected = load_robot('pa10', 0.1).forward_kinematics(q)[:3, 3]
    np.testing.assert_allclose(tip, expected, atol=1e-9)
    log = node.output()
    assert log.count('rejected /tool/pressure') <= 2  # throttled: one line per 2 s
    assert 'rejected /joint_states: duplicate joint names' in log or 'outside its limits' in log
    assert node.alive() and 'Traceback' not in log


def test_an_exception_in_the_control_step_stops_the_arm_and_the_node_serves(ros_env, monkeypatch):
    """No exception escapes a timer: a solver blowing up mid-task (here a non-finite
    Jacobian raised as a RuntimeError) fails the task, holds the arm, and the next
    start works. In process, calling the real node's callbacks."""
    import rclpy

    from pa10_ik_node.node import Pa10IkNode

    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(key, ros_env[key])
    scenario = load_scenario(SCENARIO)
    context_started = not rclpy.ok()
    if context_started:
        rclpy.init()
    node = Pa10IkNode()
    try:
        session = node.session
        session.q = np.array(scenario.robot.initial_joints, dtype=float)
        session.joint_state_time = session.pressure_time = time.monotonic()
        session.waypoints = short_path(scenario)
        assert session.start()[0]
        sent = node.command_publisher.sent

        def broken_solver(*args, **kwargs):
            raise RuntimeError('non-finite Jacobian')

        monkeypatch.setattr(node.session.controller.solver, 'solve_limited', broken_solver)
        node._control_step()  # must not raise
        assert node.session.controller.phase == 'failed'
        assert 'non-finite Jacobian' in node.session.controller.reason
        assert node.command_publisher.sent > sent  # the hold command went out
        monkeypatch.delattr(node.session.controller.solver, 'solve_limited')
        session.joint_state_time = session.pressure_time = time.monotonic()
        response = node._on_start(Trigger.Request(), Trigger.Response())
        assert response.success, response.message
        node._control_step()
        assert node.session.controller.phase == 'approach'
    finally:
        node.destroy_node()
        if context_started:
            rclpy.shutdown()


def arm_on_a_tilted_plane(tmp_path, arm, tilt_deg, shape, seed, base_placement=(0.0,) * 6):
    """A scenario file (task_generator.plane_scenario: the default one's cameras and light)
    with ``arm`` (a task_generator.GeneratedArm, its URDF beside the file, its base frame
    at ``base_placement``) and a plane tilted by ``tilt_deg`` in front of its tool; the
    scenario, the waypoints of ``shape`` on it and the dense path."""
    spec = task_generator.CaseSpec(
        arm, 'plane', np.radians(tilt_deg), shape, 'position', 1.0, seed, tuple(base_placement)
    )
    built = task_generator.build_case(spec, tmp_path)
    data = task_generator.plane_scenario(
        built, yaml.safe_load(SCENARIO.read_text()), tmp_path / f'{arm.name}.urdf'
    )
    scenario_path = tmp_path / 'scenario.yaml'
    scenario_path.write_text(yaml.safe_dump(data))
    return scenario_path, load_scenario(scenario_path), built.waypoints, built.path_base


def track_over_topics(
    spawn, rclpy_node, scenario_path, scenario, waypoints, sim_args=(), node_args=(), speed=SPEED
):
    """sensor_sim on the scenario and pa10_ik_node on its arm (the URDF and tip frame
    only: no tool parameter, ``speed`` [m/s] along the path, None: the node's default),
    one run to done; returns (tool tips while tracking (K, 3), forces while tracking (F,),
    node, probe)."""
    sim = spawn(
        [
            executable('sensor_sim'),
            '--ros-args',
            '-p',
            f'scenario:={scenario_path}',
            '-p',
            'calibration_phase:=false',
            '-p',
            'rate:=1',
            *sim_args,
        ]
    )
    node = spawn(
        [
            executable('pa10_ik_node'),
            '--ros-args',
            '-p',
            f'robot:={scenario.robot.model}',
            '-p',
            f'tip_frame:={scenario.robot.tip_frame}',
            '-p',
            f"base_frame:='{scenario.robot.base_frame}'",
            '-p',
            f'base_placement:={list(scenario.robot.base_placement)}',
            '-p',
            f'desired_force:={DESIRED_FORCE}',
            *(('-p', f'speed:={speed}') if speed is not None else ()),
            '-p',
            f'contact_stiffness:={scenario.contact_stiffness}',
            *TRACKING_ARGS,
            *node_args,
        ]
    )
    probe = Probe(rclpy_node)
    probe.path_publisher.publish(path_message(waypoints))
    rclpy_node.spin_until(
        lambda: len(probe.poses) > 10
        and len(probe.pressures) > 10
        and 'waypoints:' in node.output(),
        60,
        'tool poses, pressure, path',
    )
    response = probe.call('start_tracking')
    assert response.success, response.message
    probe.wait_until_done(180, also=('failed',))
    assert probe.phase() == 'done', probe.tracking[-1][2]
    started, ended = probe.first_stamp('tracking'), probe.first_stamp('done')
    tips = np.array(
        [
            pose_to_matrix(p.pose)[:3, 3]
            for p in probe.poses
            if started <= stamp_to_ns(p.header.stamp) <= ended
        ]
    )
    forces = np.array(
        [
            w.wrench.force.z
            for w in probe.pressures
            if started <= stamp_to_ns(w.header.stamp) <= ended
        ]
    )
    assert 'Traceback' not in node.output() + sim.output()
    return tips, forces, node, probe


def check_goals(tips, forces, scenario, path_base, what, rms_max, passed_min, p95_max):
    """The generated cases' goal figures over topics (task_generator.goal_figures; the
    goals are RMS 0.05 mm, 99 % passed, force p95 3 %; over topics on a loaded 2-core
    machine the tests allow what it reliably gives: see README): path RMS below
    ``rms_max`` [m], passed fraction above ``passed_min``, force p95 error below
    ``p95_max`` (a fraction of the desired force)."""
    figures = task_generator.goal_figures(tips, forces, scenario.surface, path_base, DESIRED_FORCE)
    print(
        f'{what}: {len(tips)} tool poses while tracking, RMS {figures["rms_mm"]:.4f} mm, '
        f'max {figures["max_mm"]:.4f} mm, passed {figures["passed_fraction"] * 100:.1f} %, '
        f'force p95 error {figures["force_p95_pct"]:.2f} %'
    )
    assert len(tips) > 50 and len(forces) > 100
    assert figures['rms_mm'] < rms_max * 1e3
    assert figures['passed_fraction'] > passed_min
    assert figures['force_p95_pct'] < p95_max * 100


def test_a_urdf_whose_tip_frame_is_the_tool_tip_tracks_with_no_tool_parameter(
    spawn, rclpy_node, tmp_path
):
    """A PA-10-like arm of other link lengths whose URDF's tool0 is the tip of its
    tool, on a 35 deg plane: neither the scenario nor the node names a tool length, and
    the node takes the URDF as it is (a default tool added beyond tool0 once stopped it
    10 cm short of the surface)."""
    arm = task_generator.random_pa10_like_arm(np.random.default_rng(1))
    scenario_path, scenario, waypoints, path_base = arm_on_a_tilted_plane(
        tmp_path, arm, 35.0, 'arc', seed=5
    )
    assert scenario.robot.tool_length == 0.0
    tips, forces, node, _ = track_over_topics(
        spawn, rclpy_node, scenario_path, scenario, waypoints
    )
    assert 'tip tool0 + tool 0 m' in node.output()
    check_goals(
        tips,
        forces,
        scenario,
        path_base,
        arm.description,
        rms_max=0.5e-3,
        passed_min=0.99,
        p95_max=0.05,
    )


def test_a_path_at_the_default_max_tip_speed_completes_in_its_time_within_tolerance(
    spawn, rclpy_node, tmp_path
):
    """At the damped-least-squares peer's pace: with the node's defaults (the path at
    max_tip_speed, 0.03 m/s, slowed where it bends beyond 0.03 m/s^2 of lateral
    acceleration) an arc on a 35 deg plane is tracked within 1.5 x its nominal time (its length /
    max_tip_speed, the bends at their speed) + 3 s (the 0.5 s speed ramp, the end's
    settling, the loaded machine's late commands), the whole task from the start to the
    path's end within that + 15 s (free move, fast descent, contact), within the tracking
    tolerances the topic tests allow (measured RMS 0.04-0.13 mm; with adapt_response off
    0.42-0.74 mm: README)."""
    arm = task_generator.random_pa10_like_arm(np.random.default_rng(1))
    scenario_path, scenario, waypoints, path_base = arm_on_a_tilted_plane(
        tmp_path, arm, 35.0, 'arc', seed=5
    )
    tips, forces, node, probe = track_over_topics(
        spawn, rclpy_node, scenario_path, scenario, waypoints, speed=None
    )
    max_tip_speed, max_lateral_acceleration = 0.03, 0.03  # the node's defaults (README)
    path = WaypointPath(waypoints)
    nominal = path.nominal_duration(max_tip_speed, max_lateral_acceleration)
    tracking_s = (probe.first_stamp('done') - probe.first_stamp('tracking')) * 1e-9
    task_s = (probe.first_stamp('done') - probe.first_stamp('approach')) * 1e-9
    # Pace is the bench's figure (bench_pa10_ik.py --pace: 0.94x the DLS peer); here a gross
    # loss of it, e.g. the old default speed of half max_tip_speed (2x), is caught: a full
    # make test on the loaded machine took 4.64 s where 1.25 x nominal + 1.5 s was 4.25 s.
    bound = 1.5 * nominal + 3.0
    print(
        f'{path.length * 1e3:.0f} mm path: tracking {tracking_s:.2f} s, start to end '
        f'{task_s:.2f} s (nominal {nominal:.2f} s, length / max_tip_speed '
        f'{path.length / max_tip_speed:.2f} s)'
    )
    check_goals(
        tips,
        forces,
        scenario,
        path_base,
        f'{arm.description} at max_tip_speed',
        rms_max=0.5e-3,
        passed_min=0.99,
        p95_max=0.05,
    )
    assert f'max_tip_speed {max_tip_speed:g}' in node.output()
    assert path.length / max_tip_speed < nominal < 3 * path.length / max_tip_speed
    # The whole task: the free move and the descent took 15 s in a loaded make test (2.6 s
    # in process): only a gross loss of pace is a failure here.
    assert tracking_s < bound and task_s < bound + 15.0, (
        f'tracking {tracking_s:.2f} s (bound {bound:.2f} s), the task {task_s:.2f} s'
    )


def test_panda_tracks_on_a_30_degree_plane(spawn, rclpy_node, tmp_path):
    """example-robot-data's panda.urdf as it ships, tip frame panda_hand_tcp in the
    scenario and the node (the simulator stamps the pressure in it). The node's own arm
    mode: with arm_mode velocity the same run failed 2 of 4 times under a load of 4 on
    2 cores (the arm lagging its reference), while offline it finishes every time."""
    arm = task_generator.panda_arm()
    scenario_path, scenario, waypoints, path_base = arm_on_a_tilted_plane(
        tmp_path, arm, 30.0, 'arc', seed=6
    )
    tips, forces, node, _ = track_over_topics(
        spawn, rclpy_node, scenario_path, scenario, waypoints
    )
    check_goals(
        tips,
        forces,
        scenario,
        path_base,
        'Panda',
        rms_max=1e-3,
        passed_min=0.95,
        p95_max=0.1,
    )


def test_tiago_arm_from_its_torso_placed_off_the_origin_tracks_on_a_40_degree_plane(
    spawn, rclpy_node, tmp_path
):
    """example-robot-data's tiago.urdf as it ships: the chain torso_lift_link ->
    arm_tool_link (lift, wheels, head and fingers locked), the torso placed 0.39 m up and
    turned 0.3 rad in base_link by base_placement (the plane then lies where the default
    scenario's cameras look), in the scenario and the node alike."""
    arm = task_generator.robot_data_arm('tiago')
    scenario_path, scenario, waypoints, path_base = arm_on_a_tilted_plane(
        tmp_path, arm, 40.0, 'arc', seed=8, base_placement=(0.15, -0.485, 0.39, 0.0, 0.0, 0.3)
    )
    tips, forces, node, _ = track_over_topics(
        spawn, rclpy_node, scenario_path, scenario, waypoints
    )
    check_goals(
        tips,
        forces,
        scenario,
        path_base,
        arm.description,
        rms_max=0.5e-3,
        passed_min=0.99,
        p95_max=0.05,
    )


def test_a_path_beyond_the_joint_limits_is_refused_before_any_motion(fake_loop, rclpy_node):
    """Inside the workspace sphere, but from its 27th waypoint on the PA-10's elbow would
    bend past its limit: start_tracking fails naming that waypoint, and no command ever
    moved the arm."""
    node, probe, arm, scenario = fake_loop
    robot = load_robot('pa10')
    waypoints = np.tile(robot.forward_kinematics(scenario.robot.initial_joints), (61, 1, 1))
    waypoints[:, 0, 3] = np.linspace(0.6, 0.0, 61)
    waypoints[:, 2, 3] = 0.2
    probe.path_publisher.publish(path_message(waypoints))
    rclpy_node.spin_until(lambda: 'waypoints: 61' in node.output(), 20, 'the path taken')
    response = probe.call('start_tracking')
    assert not response.success and 'unreachable' in response.message
    assert 'waypoint 26 at [0.34 ' in response.message and 'pa10_joint4' in response.message
    assert 'joint limits' in response.message and 'no closer than' in response.message
    rclpy_node.spin_until(lambda: probe.phase() == 'failed', 20, 'phase failed')
    assert all(not np.any(c.points[0].velocities) for c in probe.commands)
    assert node.alive() and 'Traceback' not in node.output()


@pytest.mark.parametrize(
    'edit, message',
    [
        (('tool0', 'flange', 2), "no frame 'tool0'"),
        (
            ('name="pa10_joint7" type="revolute"', 'name="pa10_joint7" type="fixed"'),
            '6 joints move',
        ),
    ],
)
def test_a_urdf_that_is_no_7_dof_arm_with_tool0_is_a_clear_start_up_error(
    spawn, tmp_path, edit, message
):
    from vgm_common.robot_model import pa10_urdf

    urdf = tmp_path / 'arm.urdf'
    urdf.write_text(pa10_urdf('pa10', 0.1).replace(*edit))
    node = spawn([executable('pa10_ik_node'), '--ros-args', '-p', f'robot:={urdf}'])
    wait_for(lambda: not node.alive(), 30, 'pa10_ik_node to exit')
    log = node.output()
    assert node.proc.returncode == 2
    assert message in log and 'start-up error' in log and 'Traceback' not in log
    if 'no frame' in message:  # the frames there are, and what to set
        assert 'parameter tip_frame' in log and 'set tip_frame to one of its frames' in log
        assert 'pa10_link7' in log
