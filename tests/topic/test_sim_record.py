"""Topic level, real processes: sensor_sim + recorder on a private domain.

Checks topics, types, stamps and rates as a subscriber sees them, then that the bag
holds exactly what sensor_sim says it published, readable by two independent readers,
with images byte-identical to the published ones.
"""

from collections import defaultdict

import numpy as np
from geometry_msgs.msg import PoseStamped, WrenchStamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from sensor_msgs.msg import Image, JointState

from bag_tools.bag_writer import header_stamp_ns
from harness import SCENARIO_DIR, executable
from sensor_sim.scenario import load_scenario
from vgm_common.conversions import stamp_to_ns
from vgm_common.diagnostics import parse_published_counts
from vgm_common.qos import DEFAULT_QOS

IMAGE_TOPICS = {
    '/stereo/left/image_raw': 'stereo_left_optical_frame',
    '/stereo/right/image_raw': 'stereo_right_optical_frame',
    '/aux/image_raw': 'aux_optical_frame',
}
RATE_HZ = 10.0


def test_sensor_sim_topics_and_recorded_bag(spawn, rclpy_node, tmp_path):
    scenario = load_scenario(SCENARIO_DIR / 'default.yaml')
    chart_captures = (
        len(scenario.calibration.T_base_chart) * scenario.calibration.captures_per_pose
    )
    received = defaultdict(list)
    for topic, kind in [
        *[(t, Image) for t in IMAGE_TOPICS],
        ('/calibration/target_pose', PoseStamped),
        ('/joint_states', JointState),
        ('/tool/pressure', WrenchStamped),
    ]:
        rclpy_node.create_subscription(
            kind, topic, lambda m, t=topic: received[t].append(m), DEFAULT_QOS
        )

    # Publishing waits until this probe matched every camera and the recorder every
    # stream. The recorder starts last, once the count alone is met: in CI a count met by
    # the pipeline before the recorder had started lost the first joint states and images.
    sim = spawn(
        [
            executable('sensor_sim'),
            '--ros-args',
            '-p',
            'scenario:=default',
            '-p',
            'min_subscribers:=1',
            '-p',
            'wait_for_nodes:=[recorder]',
            '-p',
            f'rate:={RATE_HZ}',
            '-p',
            f'ground_truth_dir:={tmp_path / "truth"}',
        ]
    )
    rclpy_node.spin_until(
        lambda: all(rclpy_node.count_publishers(t) for t in IMAGE_TOPICS),
        30,
        'sensor_sim to advertise the cameras',
    )
    recorder = spawn(
        [
            executable('bag_tools', 'recorder'),
            '--ros-args',
            '-p',
            f'output_dir:={tmp_path}',
            '-p',
            'bag_name:=sim',
        ]
    )
    wanted = chart_captures + 10
    rclpy_node.spin_until(
        lambda: len(received['/aux/image_raw']) >= wanted, 90, f'{wanted} captures'
    )

    # One stamp per capture: the three images share it.
    stamps = {t: [stamp_to_ns(m.header.stamp) for m in received[t]] for t in IMAGE_TOPICS}
    common = set.intersection(*map(set, stamps.values()))
    assert len(common) >= wanted - 2  # the last capture may be in flight on one topic
    for topic, frame_id in IMAGE_TOPICS.items():
        for msg in received[topic][:3]:
            assert (msg.encoding, msg.width, msg.height) == ('mono8', 640, 480)
            assert msg.header.frame_id == frame_id and msg.step == 640
    # The chart pose is stamped like the images it appears in, for the chart captures only.
    pose_stamps = [stamp_to_ns(m.header.stamp) for m in received['/calibration/target_pose']]
    assert pose_stamps == sorted(common)[:chart_captures]
    assert all(m.header.frame_id == 'base_link' for m in received['/calibration/target_pose'])
    # The `rate` parameter is honoured: never faster than asked, and not grossly slower
    # (how close it gets on a busy 2-core VM is measured by bench/, not asserted here).
    capture_periods = np.diff(np.array(sorted(common)) * 1e-9)
    assert 0.95 / RATE_HZ <= np.median(capture_periods) <= 1.5 / RATE_HZ
    # The contract's joint names; pressure in tool0. (Rates are checked on the bag: this
    # probe's keep-last-10 reader may drop messages when the machine is busy.)
    assert list(received['/joint_states'][-1].name) == [f'pa10_joint{i}' for i in range(1, 8)]
    np.testing.assert_allclose(
        received['/joint_states'][-1].position, scenario.robot.initial_joints, atol=1e-12
    )
    assert received['/tool/pressure'][-1].header.frame_id == 'tool0'

    assert sim.stop() == 0
    counts = parse_published_counts(sim.output())
    assert recorder.stop() == 0
    bag_dir = tmp_path / 'sim'
    assert (bag_dir / 'metadata.yaml').exists() and (bag_dir / 'sim_0.mcap').exists()

    assert set(counts) == {
        *IMAGE_TOPICS,
        '/calibration/target_pose',
        '/joint_states',
        '/tool/pressure',
        '/diagnostics',
    }
    # The recorder publishes diagnostics too: that topic's total is not sensor_sim's alone.
    expected = {topic: n for topic, n in counts.items() if topic != '/diagnostics'}
    assert expected['/calibration/target_pose'] == chart_captures
    with AnyReader([bag_dir]) as reader:
        in_bag = defaultdict(int)
        joint_stamps = []
        for connection, _, rawdata in reader.messages():
            in_bag[connection.topic] += 1
            if connection.topic == '/joint_states':
                joint_stamps.append(header_stamp_ns(rawdata))
        assert reader.topics['/stereo/left/image_raw'].msgtype == 'sensor_msgs/msg/Image'
    assert {t: in_bag[t] for t in expected} == expected
    # Joint states at >= 100 Hz, from their header stamps. The median period: a VM whose
    # host steals the CPU stalls every process now and then, not the simulator's schedule.
    joint_periods = np.diff(np.array(sorted(joint_stamps)) * 1e-9)
    assert np.median(joint_periods) <= 1 / 100.0

    published_left = {
        stamp_to_ns(m.header.stamp): bytes(m.data) for m in received['/stereo/left/image_raw']
    }
    decoded_counts = defaultdict(int)
    compared = 0
    with open(bag_dir / 'sim_0.mcap', 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == 'ros2'
        for schema, channel, _, decoded in reader.iter_decoded_messages():
            decoded_counts[channel.topic] += 1
            if channel.topic == '/stereo/left/image_raw':
                assert schema.encoding == 'ros2msg' and channel.message_encoding == 'cdr'
                stamp = decoded.header.stamp.sec * 1_000_000_000 + decoded.header.stamp.nanosec
                if stamp in published_left:
                    assert bytes(decoded.data) == published_left[stamp]
                    compared += 1
    assert {t: decoded_counts[t] for t in expected} == expected
    assert compared >= wanted - 2

    # Ground truth went to files, not topics.
    for name in ('cameras.yaml', 'curve_base.npz', 'depth_left.npy'):
        assert (tmp_path / 'truth' / name).exists()
