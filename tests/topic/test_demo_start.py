"""Topic level, real processes: with the demo's own settings (scripts/demo.py over the
installed graph.yaml) and no Foxglove viewer connected, pa10_ik_node commands the arm
within 2 s of the start call; its subscriber gate must not wait for a node that
subscribes only on demand (live_view)."""

import socket
import sys
import time
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from test_pa10_ik_node import FakeArm, Probe, path_message, short_path
from trajectory_msgs.msg import JointTrajectory

from harness import REPO_ROOT, SCENARIO_DIR, executable
from sensor_sim.scenario import load_scenario
from vgm_common.qos import DEFAULT_QOS

sys.path.insert(0, str(REPO_ROOT / 'scripts'))
import demo  # noqa: E402

from vgm_common.topics import JOINT_TRAJECTORY_TOPIC

START_TO_MOTION_S = 2.0  # [s] the goal: the arm moves this soon after the call


def free_port():
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return probe.getsockname()[1]


def test_the_demo_arm_moves_within_2_s_of_the_start_call_without_a_viewer(
    spawn, rclpy_node, tmp_path
):
    scenario = load_scenario(SCENARIO_DIR / 'quick.yaml')
    settings = demo.demo_params(scenario, tmp_path / 'bags', 'start', tmp_path, free_port())
    graph = Path(get_package_share_directory('vgm_common')) / 'params' / 'graph.yaml'
    params = tmp_path / 'params.yaml'
    demo.write_params(graph, params, settings)
    for package, name in (('bag_tools', 'recorder'), ('live_view', 'live_view')):
        spawn([executable(package, name), '--ros-args', '--params-file', params])
    arm_node = spawn([executable('pa10_ik_node'), '--ros-args', '--params-file', params])

    probe = Probe(rclpy_node)
    FakeArm(rclpy_node, scenario.robot.initial_joints)
    commands = []  # (time.monotonic() of arrival, message)
    rclpy_node.create_subscription(
        JointTrajectory,
        JOINT_TRAJECTORY_TOPIC,
        lambda msg: commands.append((time.monotonic(), msg)),
        DEFAULT_QOS,
    )
    probe.path_publisher.publish(path_message(short_path(scenario)))
    # Until pa10_ik_node has the path, joint states and pressure it refuses to start.
    deadline = time.monotonic() + 60.0
    while not (response := probe.call('start_tracking', timeout=60)).success:
        assert time.monotonic() < deadline, f'start_tracking refused: {response.message}'
        retry_at = time.monotonic() + 0.2  # spinning meanwhile, so the arm ticks on
        rclpy_node.spin_until(lambda t=retry_at: time.monotonic() > t, 1.0)
    called_at = time.monotonic()
    after_call = lambda: [t for t, _ in commands if t >= called_at]  # noqa: E731
    rclpy_node.spin_until(
        after_call, 35.0, 'a joint command from pa10_ik_node after start_tracking'
    )
    delay = after_call()[0] - called_at
    assert delay < START_TO_MOTION_S, (
        f'first joint command {delay:.1f} s after the start call; '
        f'pa10_ik_node log: {arm_node.output()[-1500:]}'
    )
    assert 'publishing after' not in arm_node.output()
