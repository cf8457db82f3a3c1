"""Topic level, real processes: live_view + sensor_sim on a private domain, and a
Foxglove WebSocket client (subprotocol foxglove.sdk.v1) as the Foxglove app connects.

Checks the advertised channels (names, schema names and texts, encodings), that an Image
arrives byte for byte as sensor_sim published it and decodes, that a JointState decodes,
that a latched camera pose published before the client connected still reaches it, that
/tf carries base_link -> camera and tool0 transforms equal to the poses, that a bad tool
pose is rejected without stopping the node, and that an unusable port is one line.
"""

import socket

import numpy as np
from foxglove_ws import FoxgloveClient, decode_frame_transforms, live_view_url
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image, JointState

from bag_tools.bag_writer import header_stamp_ns
from bag_tools.message_definitions import full_definition
from harness import executable, publish_rig, wait_for
from vgm_common.conversions import make_header, pose_to_matrix
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import (
    CAMERA_INFO_TOPICS,
    DIAGNOSTICS_TOPIC,
    IMAGE_TOPICS,
    JOINT_STATES_TOPIC,
    OPTICAL_FRAMES,
    POSE_TOPICS,
    PRESSURE_TOPIC,
    TARGET_POSE_TOPIC,
    TOOL_POSE_TOPIC,
    TRANSFORMS_TOPIC,
)

EXPECTED = {  # topic -> schema name
    IMAGE_TOPICS['left']: 'sensor_msgs/msg/Image',
    IMAGE_TOPICS['right']: 'sensor_msgs/msg/Image',
    IMAGE_TOPICS['aux']: 'sensor_msgs/msg/Image',
    JOINT_STATES_TOPIC: 'sensor_msgs/msg/JointState',
    PRESSURE_TOPIC: 'geometry_msgs/msg/WrenchStamped',
    TARGET_POSE_TOPIC: 'geometry_msgs/msg/PoseStamped',
    DIAGNOSTICS_TOPIC: 'diagnostic_msgs/msg/DiagnosticArray',
    POSE_TOPICS['left']: 'geometry_msgs/msg/PoseStamped',
    CAMERA_INFO_TOPICS['left']: 'sensor_msgs/msg/CameraInfo',
    TOOL_POSE_TOPIC: 'geometry_msgs/msg/PoseStamped',
}
LEFT = IMAGE_TOPICS['left']


def _tool_pose(position, quaternion):
    msg = PoseStamped(header=make_header(123_000_000_456, 'base_link'))
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = position
    (
        msg.pose.orientation.x,
        msg.pose.orientation.y,
        msg.pose.orientation.z,
        msg.pose.orientation.w,
    ) = quaternion
    return msg


def test_live_view_serves_the_graph_to_a_foxglove_client(spawn, rclpy_node, tmp_path):
    live_view = spawn(
        [
            executable('live_view'),
            '--ros-args',
            '-p',
            'port:=0',
            '-p',
            'exclude:=[/parameter_events]',
        ]
    )
    url = wait_for(lambda: live_view_url(live_view.output()), 30, 'live_view to listen')
    assert url.startswith('ws://127.0.0.1:')  # loopback unless told otherwise
    truth = tmp_path / 'truth'
    spawn(
        [
            executable('sensor_sim'),
            '--ros-args',
            '-p',
            'scenario:=default',
            '-p',
            'rate:=5.0',
            '-p',
            f'ground_truth_dir:={truth}',
            '-p',
            'calibration_phase:=false',
        ]
    )
    calibration = truth / 'true_calibration' / 'calibration.yaml'
    # the ground truth files are written one after another: wait for the last one
    wait_for(
        lambda: calibration.exists() and (truth / 'depth_aux.npy').exists(),
        60,
        'sensor_sim ground truth',
    )
    # The rig as calib_node publishes it: latched, before any viewer connects.
    rig_publishers, rig = publish_rig(rclpy_node, calibration)
    raw_left = {}  # stamp -> the CDR bytes a plain ROS subscriber receives
    rclpy_node.create_subscription(
        Image,
        LEFT,
        lambda data: raw_left.setdefault(header_stamp_ns(data), data),
        DEFAULT_QOS,
        raw=True,
    )
    tool_pose = rclpy_node.create_publisher(PoseStamped, TOOL_POSE_TOPIC, DEFAULT_QOS)
    rclpy_node.spin_until(lambda: raw_left, 60, 'a left image')

    client = FoxgloveClient(url)
    try:
        assert client.subprotocol == 'foxglove.sdk.v1'
        channels = client.wait_for_channels([*EXPECTED, TRANSFORMS_TOPIC], 60)
        assert client.server_info['name'] == 'vgm live_view'
        for topic, schema_name in EXPECTED.items():
            channel = channels[topic]
            assert (channel['schemaName'], channel['encoding'], channel['schemaEncoding']) == (
                schema_name,
                'cdr',
                'ros2msg',
            ), topic
            assert channel['schema'] == full_definition(schema_name), topic  # as bags carry
        assert (
            channels[TRANSFORMS_TOPIC]['schemaName'],
            channels[TRANSFORMS_TOPIC]['encoding'],
        ) == (
            'foxglove.FrameTransforms',
            'protobuf',
        )
        assert '/parameter_events' not in channels  # exclude

        client.subscribe([LEFT, JOINT_STATES_TOPIC, TRANSFORMS_TOPIC, POSE_TOPICS['left']])
        received = {}
        transforms = {}

        # The camera transforms come on subscribing to /tf (they were latched before).
        def record(topic, log_time_ns, payload):
            received.setdefault(topic, payload)
            if topic == TRANSFORMS_TOPIC:
                transforms.update({t['child']: t for t in decode_frame_transforms(payload)})
            return topic == TRANSFORMS_TOPIC

        client.receive_until(record, 30, 'the camera transforms')
        # Now that /tf is watched: a bad pose is rejected (the node keeps serving), a good
        # one becomes tool0.
        tool_pose.publish(_tool_pose((0.1, 0.2, 0.3), (0.0, 0.0, 0.0, 2.0)))
        wait_for(
            lambda: 'rejected /tool_pose' in live_view.output(),
            30,
            'the bad tool pose to be rejected',
        )
        good_tool = _tool_pose((0.4, -0.2, 0.55), (0.0, 0.0, np.sin(0.3), np.cos(0.3)))
        tool_pose.publish(good_tool)

        def collect(topic, log_time_ns, payload):
            record(topic, log_time_ns, payload)
            return set(received) == {
                LEFT,
                JOINT_STATES_TOPIC,
                TRANSFORMS_TOPIC,
                POSE_TOPICS['left'],
            } and {
                OPTICAL_FRAMES['left'],
                OPTICAL_FRAMES['aux'],
                'tool0',
            } <= set(transforms)

        client.receive_until(collect, 60, 'an image, a joint state, the latched pose and /tf')
    finally:
        client.close()

    image = deserialize_message(received[LEFT], Image)
    assert (image.encoding, image.width, image.height, image.step) == ('mono8', 640, 480, 640)
    assert image.header.frame_id == OPTICAL_FRAMES['left']
    pixels = np.frombuffer(bytes(image.data), np.uint8)
    assert pixels.size == 640 * 480 and pixels.std() > 5.0  # a rendered scene, not a blank
    # Forwarded unchanged: the same bytes a ROS subscriber got for that capture.
    stamp = header_stamp_ns(received[LEFT])
    rclpy_node.spin_until(
        lambda: stamp in raw_left or max(raw_left) > stamp, 30, 'the probe to see the same capture'
    )
    assert bytes(received[LEFT]) == bytes(raw_left[stamp])

    joints = deserialize_message(received[JOINT_STATES_TOPIC], JointState)
    assert list(joints.name) == [f'pa10_joint{i}' for i in range(1, 8)]
    assert len(joints.position) == 7 and np.all(np.isfinite(joints.position))

    pose = deserialize_message(received[POSE_TOPICS['left']], PoseStamped)
    np.testing.assert_allclose(pose_to_matrix(pose.pose), rig['left'][0].T_base_camera, atol=1e-9)
    for name in ('left', 'aux'):
        transform = transforms[OPTICAL_FRAMES[name]]
        assert transform['parent'] == 'base_link'
        np.testing.assert_allclose(
            transform['translation'], rig[name][0].T_base_camera[:3, 3], atol=1e-9
        )
    tool = transforms['tool0']
    assert tool['parent'] == 'base_link'
    np.testing.assert_allclose(tool['translation'], (0.4, -0.2, 0.55), atol=1e-12)
    np.testing.assert_allclose(tool['rotation'], (0.0, 0.0, np.sin(0.3), np.cos(0.3)), atol=1e-12)
    assert live_view.alive()
    assert live_view.stop() == 0
    assert rig_publishers  # kept alive until here: latched values stay offered


def test_live_view_port_in_use_is_one_line(spawn):
    with socket.socket() as taken:
        taken.bind(('127.0.0.1', 0))
        taken.listen()
        port = taken.getsockname()[1]
        live_view = spawn([executable('live_view'), '--ros-args', '-p', f'port:={port}'])
        wait_for(lambda: not live_view.alive(), 30, 'live_view to exit')
    assert live_view.proc.returncode == 2
    errors = [line for line in live_view.output().splitlines() if 'ERROR' in line]
    assert len(errors) == 1 and f'cannot serve on 127.0.0.1:{port}' in errors[0]
    assert 'Traceback' not in live_view.output()
