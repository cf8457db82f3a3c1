"""Topic level, real processes: a node told (by a remap) to use a topic that carries
another type says so in one line naming both types, within 5 s of being up, and never
with a traceback: refused at start-up (exit status 2) when the other type is known by
then, otherwise one error line (and diagnostic) once it appears."""

import re

import pytest
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import JointState

from harness import executable, wait_for
from vgm_common.qos import DEFAULT_QOS

JOINT_STATE = 'sensor_msgs/msg/JointState'
WRENCH = 'geometry_msgs/msg/WrenchStamped'
IMAGE = 'sensor_msgs/msg/Image'
POSE = 'geometry_msgs/msg/PoseStamped'
SAID_WITHIN_S = 5.0  # [s] after the node's first log line
_STAMP = re.compile(r'\[(?:INFO|WARN|ERROR)\] \[(\d+\.\d+)\]')


def said_once(process, *types):
    """The one log line naming every one of ``types``, checked to come within
    SAID_WITHIN_S of the node's first line, with no traceback anywhere."""
    wait_for(
        lambda: all(t in process.output() for t in types),
        30.0,
        f'a line naming {" and ".join(types)}',
    )
    output = process.output()
    lines = [line for line in output.splitlines() if all(t in line for t in types)]
    assert len(lines) == 1 and '[ERROR]' in lines[0], output
    assert 'Traceback' not in output and 'RCLError' not in output, output
    first = float(_STAMP.search(output).group(1))
    assert float(_STAMP.search(lines[0]).group(1)) - first < SAID_WITHIN_S, output
    return lines[0]


def test_a_subscription_remapped_onto_the_node_s_own_topic_of_another_type_is_refused(spawn):
    # pa10_ik_node itself subscribes /joint_states as JointState: rcl used to fail with
    # 'invalid allocator' and a traceback.
    node = spawn([executable('pa10_ik_node'), '--ros-args', '-r', '/tool/pressure:=/joint_states'])
    line = said_once(node, JOINT_STATE, WRENCH)
    assert '/tool/pressure (remapped to /joint_states)' in line and 'start-up error' in line
    wait_for(lambda: not node.alive(), 20.0, 'pa10_ik_node to exit')
    assert node.proc.returncode == 2


@pytest.mark.parametrize(
    'package, remap, published, ours',
    [
        # Waited for images forever without a word.
        ('curve_recon_node', '/stereo/left/image_raw:=/joint_states', JointState, IMAGE),
        # Took every view for handheld and then said 'chart not found'.
        ('calib_node', '/calibration/target_pose:=/tool/pressure', WrenchStamped, POSE),
    ],
)
def test_a_subscription_on_a_topic_another_node_publishes_with_another_type_is_named(
    spawn, rclpy_node, package, remap, published, ours
):
    topic = remap.split(':=')[1]
    rclpy_node.create_publisher(published, topic, DEFAULT_QOS)  # the other type
    node = spawn([executable(package), '--ros-args', '-r', remap])
    other = f'{published.__module__.split(".")[0]}/msg/{published.__name__}'
    wait_for(lambda: node.output(), 60.0, f'{package} to start')
    line = said_once(node, other, ours)
    assert f'(remapped to {topic})' in line
