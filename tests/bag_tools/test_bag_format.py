"""The bag layout of bag_tools.bag_writer, checked with independent readers.

A bag written by BagWriter must open with rosbags' AnyReader (which also checks every
RIHS01 hash against the stored definitions) and with mcap's reader + mcap_ros2 decoding,
hold exactly the written messages, and carry the rosbag2 (Jazzy) metadata. A writer killed
with SIGKILL leaves a file whose flushed chunks are still readable.
"""

import os
import signal
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import CameraInfo, Image, JointState

from bag_tools.bag_writer import (
    INFINITE_DURATION,
    BagReader,
    BagWriter,
    BagWriterError,
    header_stamp_ns,
    qos_profile,
)
from bag_tools.message_definitions import definition, full_definition, type_hash
from harness import wait_for

T0 = 1_700_000_000_000_000_000  # [ns] an arbitrary epoch time
RULE = '=' * 80


def stamp(msg, t_ns):
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
    return msg


def make_image(rng, t_ns):
    pixels = rng.integers(0, 256, size=(480, 640), dtype=np.uint8)
    msg = Image(height=480, width=640, encoding='mono8', step=640, data=pixels.tobytes())
    msg.header.frame_id = 'stereo_left_optical_frame'
    return stamp(msg, t_ns)


def make_camera_info(t_ns):
    msg = CameraInfo(width=640, height=480, distortion_model='plumb_bob')
    msg.k = [500.0, 0.0, 320.0, 0.0, 505.0, 240.0, 0.0, 0.0, 1.0]
    msg.d = [0.1, -0.05, 0.001, 0.002, 0.0]
    msg.header.frame_id = 'stereo_left_optical_frame'
    return stamp(msg, t_ns)


def make_joint_state(i, t_ns):
    msg = JointState(name=[f'pa10_joint{j}' for j in range(1, 8)])
    msg.position = [0.1 * i + j for j in range(7)]
    msg.velocity = [-0.5 * i] * 7
    # Not empty: Fast-CDR pads an empty trailing float64 sequence with 4 bytes, which
    # rosbags' deserializer rejects ("size mismatch"), whoever wrote the bag.
    msg.effort = [0.0] * 7
    return stamp(msg, t_ns)


def make_pose(t_ns):
    msg = PoseStamped()
    msg.header.frame_id = 'base_link'
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = 0.25, -0.5, 1.5
    msg.pose.orientation.w = 1.0
    return stamp(msg, t_ns)


LATCHED = qos_profile(history='unknown', depth=0, durability='transient_local')
STREAM = qos_profile(history='unknown', depth=0)


@pytest.fixture(scope='module')
def sample_bag(tmp_path_factory):
    """A bag with images, camera info, joint states and a latched pose, and what went in."""
    rng = np.random.default_rng(7)
    bag_dir = tmp_path_factory.mktemp('bags') / 'sample'
    topics = {
        '/stereo/left/image_raw': ('sensor_msgs/msg/Image', STREAM),
        '/stereo/left/camera_info': ('sensor_msgs/msg/CameraInfo', LATCHED),
        '/joint_states': ('sensor_msgs/msg/JointState', STREAM),
        '/stereo/left/pose': ('geometry_msgs/msg/PoseStamped', LATCHED),
    }
    written = []  # (topic, message, serialized, log_time, publish_time)
    with BagWriter(bag_dir) as writer:
        for name, (type_name, qos) in topics.items():
            writer.add_topic(name, type_name, [qos])

        def put(topic, msg, log_time, publish_time):
            data = serialize_message(msg)
            writer.write(topic, data, log_time, publish_time)
            written.append((topic, msg, data, log_time, publish_time))

        put('/stereo/left/pose', make_pose(T0), T0 + 1_000, T0)
        put('/stereo/left/camera_info', make_camera_info(T0), T0 + 2_000, T0)
        for i in range(12):
            t = T0 + 10_000_000 * i  # 100 Hz
            put('/joint_states', make_joint_state(i, t), t + 500_000, t)
            if i % 4 == 0:  # 25 Hz images: 3 x 300 kB, more than one chunk
                put('/stereo/left/image_raw', make_image(rng, t), t + 900_000, t)
    return bag_dir, topics, written


def test_full_definition_is_rosbag2s_ros2msg_text():
    text = full_definition('sensor_msgs/msg/CameraInfo')
    assert text.startswith('# This message defines meta information for a camera.')
    # Dependencies in sorted order, depth first, each once, behind 80 '=' and 'MSG: pkg/Type'.
    headers = [line for line in text.splitlines() if line.startswith('MSG: ')]
    assert headers == [
        'MSG: sensor_msgs/RegionOfInterest',
        'MSG: std_msgs/Header',
        'MSG: builtin_interfaces/Time',
    ]
    assert f'\n\n{RULE}\nMSG: std_msgs/Header\n' in text
    assert definition('sensor_msgs/msg/CameraInfo') == ('ros2msg', text)
    assert full_definition('sensor_msgs/Image') == full_definition('sensor_msgs/msg/Image')
    assert 'MSG: ' not in full_definition('std_msgs/msg/String')


@pytest.mark.parametrize(
    'type_name',
    [
        'sensor_msgs/msg/Image',
        'sensor_msgs/msg/CameraInfo',
        'sensor_msgs/msg/JointState',
        'sensor_msgs/msg/PointCloud2',
        'geometry_msgs/msg/PoseStamped',
        'nav_msgs/msg/Path',
        'stereo_msgs/msg/DisparityImage',
        'diagnostic_msgs/msg/DiagnosticArray',
        'trajectory_msgs/msg/JointTrajectory',
        'rcl_interfaces/msg/Log',
    ],
)
def test_definitions_hash_to_the_installed_rihs01(type_name):
    """rosbags parses our text and hashes it to the RIHS01 that rosidl installed."""
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(full_definition(type_name), type_name))
    assert type_hash(type_name).startswith('RIHS01_')
    assert store.hash_rihs01(type_name) == type_hash(type_name)


def test_metadata_yaml_is_rosbag2_jazzy(sample_bag):
    bag_dir, topics, written = sample_bag
    document = yaml.safe_load((bag_dir / 'metadata.yaml').read_text())
    assert list(document) == ['rosbag2_bagfile_information']
    info = document['rosbag2_bagfile_information']
    assert list(info) == [
        'version',
        'storage_identifier',
        'duration',
        'starting_time',
        'message_count',
        'topics_with_message_count',
        'compression_format',
        'compression_mode',
        'relative_file_paths',
        'files',
        'custom_data',
        'ros_distro',
    ]
    assert (info['version'], info['storage_identifier'], info['ros_distro']) == (
        9,
        'mcap',
        'jazzy',
    )
    log_times = [w[3] for w in written]
    assert info['starting_time'] == {'nanoseconds_since_epoch': min(log_times)}
    assert info['duration'] == {'nanoseconds': max(log_times) - min(log_times)}
    assert info['message_count'] == len(written) == 17
    assert info['relative_file_paths'] == ['sample_0.mcap']
    assert info['files'] == [
        {
            'path': 'sample_0.mcap',
            'starting_time': info['starting_time'],
            'duration': info['duration'],
            'message_count': 17,
        }
    ]
    assert (info['compression_format'], info['compression_mode'], info['custom_data']) == (
        '',
        '',
        None,
    )
    counts = {
        t['topic_metadata']['name']: t['message_count'] for t in info['topics_with_message_count']
    }
    assert counts == {
        '/stereo/left/image_raw': 3,
        '/stereo/left/camera_info': 1,
        '/joint_states': 12,
        '/stereo/left/pose': 1,
    }
    for entry in info['topics_with_message_count']:
        meta = entry['topic_metadata']
        type_name, qos = topics[meta['name']]
        assert meta['type'] == type_name and meta['serialization_format'] == 'cdr'
        assert meta['type_description_hash'] == type_hash(type_name)
        assert meta['offered_qos_profiles'] == [qos]  # a YAML list of maps, string policies
    pose_qos = next(
        e
        for e in info['topics_with_message_count']
        if e['topic_metadata']['name'] == '/stereo/left/pose'
    )
    assert pose_qos['topic_metadata']['offered_qos_profiles'][0] == {
        'history': 'unknown',
        'depth': 0,
        'reliability': 'reliable',
        'durability': 'transient_local',
        'deadline': INFINITE_DURATION,
        'lifespan': INFINITE_DURATION,
        'liveliness': 'automatic',
        'liveliness_lease_duration': INFINITE_DURATION,
        'avoid_ros_namespace_conventions': False,
    }


def test_rosbags_anyreader_reads_everything(sample_bag):
    bag_dir, topics, written = sample_bag
    with AnyReader([bag_dir]) as reader:  # also verifies each type's RIHS01 hash
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == {
            '/stereo/left/image_raw': ('sensor_msgs/msg/Image', 3),
            '/stereo/left/camera_info': ('sensor_msgs/msg/CameraInfo', 1),
            '/joint_states': ('sensor_msgs/msg/JointState', 12),
            '/stereo/left/pose': ('geometry_msgs/msg/PoseStamped', 1),
        }
        pose_connection = reader.topics['/stereo/left/pose']
        assert pose_connection.msgtype == 'geometry_msgs/msg/PoseStamped'
        latched = [c for c in reader.connections if c.topic == '/stereo/left/pose'][0]
        assert latched.ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL
        read = [
            (c.topic, t, raw, reader.deserialize(raw, c.msgtype))
            for c, t, raw in reader.messages()
        ]
    expected = sorted(written, key=lambda w: w[3])
    assert [(r[0], r[1], bytes(r[2])) for r in read] == [(w[0], w[3], w[2]) for w in expected]
    images = [(r[3], w[1]) for r, w in zip(read, expected) if r[0] == '/stereo/left/image_raw']
    for decoded, original in images:
        assert (decoded.width, decoded.height, decoded.encoding) == (640, 480, 'mono8')
        assert decoded.data.tobytes() == bytes(original.data)  # byte for byte
    joints = [(r[3], w[1]) for r, w in zip(read, expected) if r[0] == '/joint_states']
    for decoded, original in joints:
        assert list(decoded.name) == list(original.name)
        np.testing.assert_array_equal(decoded.position, original.position)
        assert decoded.header.stamp.nanosec == original.header.stamp.nanosec
    info = [r[3] for r in read if r[0] == '/stereo/left/camera_info'][0]
    np.testing.assert_array_equal(info.k, make_camera_info(T0).k)
    assert info.distortion_model == 'plumb_bob'
    pose = [r[3] for r in read if r[0] == '/stereo/left/pose'][0]
    assert (pose.pose.position.x, pose.pose.position.z, pose.header.frame_id) == (
        0.25,
        1.5,
        'base_link',
    )


def test_mcap_reader_sees_rosbag2_layout(sample_bag):
    bag_dir, topics, written = sample_bag
    with open(bag_dir / 'sample_0.mcap', 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert summary.statistics.message_count == 17
        assert summary.statistics.chunk_count >= 2  # 900 kB of images in 768 KiB chunks
        assert all(c.compression == '' for c in summary.chunk_indexes)
        for schema in summary.schemas.values():
            assert schema.encoding == 'ros2msg'
            assert schema.data.decode() == full_definition(schema.name)
        for channel in summary.channels.values():
            type_name, qos = topics[channel.topic]
            assert summary.schemas[channel.schema_id].name == type_name
            assert channel.message_encoding == 'cdr'
            assert set(channel.metadata) == {'offered_qos_profiles', 'topic_type_hash'}
            assert yaml.safe_load(channel.metadata['offered_qos_profiles']) == [qos]
            assert channel.metadata['topic_type_hash'] == type_hash(type_name)
        decoded = [
            (c.topic, m.log_time, m.publish_time, m.data, d)
            for _, c, m, d in reader.iter_decoded_messages()
        ]
        records = [m for m in reader.iter_metadata() if m.name == 'rosbag2']
    expected = sorted(written, key=lambda w: w[3])
    assert [d[:4] for d in decoded] == [(w[0], w[3], w[4], w[2]) for w in expected]
    for (topic, *_rest, message), original in zip(decoded, expected):
        if topic == '/stereo/left/image_raw':
            assert bytes(message.data) == bytes(original[1].data)
        if topic == '/joint_states':
            assert list(message.position) == list(original[1].position)
    # rosbag2's metadata record: once when the file was opened, complete before closing.
    assert len(records) == 2
    final = yaml.safe_load(records[-1].metadata['serialized_metadata'])
    on_disk = yaml.safe_load((bag_dir / 'metadata.yaml').read_text())
    assert final == on_disk['rosbag2_bagfile_information']


def test_bag_reader_and_header_stamps(sample_bag):
    bag_dir, _, written = sample_bag
    reader = BagReader(bag_dir)
    assert not reader.recovered and reader.message_count == 17
    messages = list(reader.messages())
    expected = sorted(written, key=lambda w: w[3])
    assert [(m.topic, m.data, m.log_time, m.publish_time) for m in messages] == [
        (w[0], w[2], w[3], w[4]) for w in expected
    ]
    assert [m.topic for m in reader.messages(['/stereo/left/pose'])] == ['/stereo/left/pose']
    # The recorder reads header.stamp straight from the CDR bytes.
    t = T0 + 123_456_789
    assert header_stamp_ns(serialize_message(make_joint_state(3, t))) == t
    assert header_stamp_ns(serialize_message(JointState())) is None  # zero stamp
    big_endian = b'\x00\x00\x00\x00' + (5).to_bytes(4, 'big') + (7).to_bytes(4, 'big')
    assert header_stamp_ns(big_endian) == 5_000_000_007
    assert header_stamp_ns(b'\x00\x01\x00\x00') is None


def test_split_files_and_refusals(tmp_path):
    bag_dir = tmp_path / 'split'
    payload = bytes(range(256)) * 40  # 10 kB
    with BagWriter(bag_dir, max_file_size=50_000, chunk_size=16_384) as writer:
        writer.add_topic('/joint_states', 'sensor_msgs/msg/JointState', [STREAM])
        writer.add_topic('/images', 'sensor_msgs/msg/Image', [STREAM])
        for i in range(30):
            image = Image(height=40, width=256, encoding='mono8', step=256, data=payload)
            writer.write('/images', serialize_message(stamp(image, T0 + i)), T0 + 10 * i)
            writer.write(
                '/joint_states', serialize_message(make_joint_state(i, T0)), T0 + 10 * i + 5
            )
        with pytest.raises(BagWriterError):
            writer.write('/unknown', b'', T0)
        with pytest.raises(BagWriterError):
            writer.add_topic('/images', 'sensor_msgs/msg/CameraInfo')
    with pytest.raises(BagWriterError):
        BagWriter(bag_dir)  # rosbag2 never overwrites a bag
    with pytest.raises(BagWriterError):
        writer.write('/images', b'', T0)  # closed
    info = yaml.safe_load((bag_dir / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    names = info['relative_file_paths']
    assert len(names) >= 3 and names == [f'split_{i}.mcap' for i in range(len(names))]
    assert [f['path'] for f in info['files']] == names
    assert sum(f['message_count'] for f in info['files']) == info['message_count'] == 60
    with AnyReader([bag_dir]) as reader:
        assert sum(1 for _ in reader.messages()) == 60
        assert reader.topics['/images'].msgcount == 30
    assert [m.log_time for m in BagReader(bag_dir).messages()] == sorted(
        T0 + 10 * i + k for i in range(30) for k in (0, 5)
    )


CRASHING_WRITER = textwrap.dedent("""
    import sys, time
    from bag_tools.bag_writer import BagWriter
    bag_dir, explicit_flush = sys.argv[1], sys.argv[2] == 'flush'
    writer = BagWriter(bag_dir, chunk_size=16_384)
    writer.add_topic('/joint_states', 'sensor_msgs/msg/JointState')
    payload = b'\\x00\\x01\\x00\\x00' + bytes(996)  # 1000 bytes, 16 per chunk
    for i in range(500):
        writer.write('/joint_states', payload, 1_000 + i)
    if explicit_flush:
        writer.flush()
        for i in range(500, 510):  # 10 kB: left in the chunk being filled
            writer.write('/joint_states', payload, 1_000 + i)
    open(sys.argv[3], 'w').close()  # tell the test, then wait to be killed
    time.sleep(60)
""")


@pytest.mark.parametrize('explicit_flush', [False, True])
def test_killed_writer_keeps_flushed_chunks(tmp_path, explicit_flush):
    bag_dir = tmp_path / 'crashed'
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    ready = tmp_path / 'ready'
    process = subprocess.Popen(
        [
            sys.executable,
            '-c',
            CRASHING_WRITER,
            str(bag_dir),
            'flush' if explicit_flush else 'auto',
            str(ready),
        ],
        env=env,
    )
    try:
        wait_for(
            lambda: ready.exists() or process.poll() is not None,
            30,
            what='the writer to write its messages',
        )
        assert ready.exists(), f'the writer exited with {process.returncode}'
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    mcap_path = bag_dir / 'crashed_0.mcap'
    assert not (bag_dir / 'metadata.yaml').exists()
    with open(mcap_path, 'rb') as stream:  # no summary: read front to back
        log_times = []
        try:
            for _, channel, message in NonSeekingReader(stream).iter_messages(
                log_time_order=False
            ):
                assert channel.topic == '/joint_states' and len(message.data) == 1000
                log_times.append(message.log_time)
        except (McapError, struct.error):
            pass  # the truncated tail; everything before it counts
    if explicit_flush:
        assert log_times == list(range(1_000, 1_500))  # exactly the flushed messages
    else:
        # Chunks went to disk as they filled: at most one chunk (17 messages) is lost.
        assert log_times == list(range(1_000, 1_000 + len(log_times)))
        assert 500 - 17 <= len(log_times) < 500
    recovered = BagReader(bag_dir)  # rebuilds topics from the channels when killed
    assert recovered.recovered
    assert [(t.name, t.type, t.message_count) for t in recovered.topics] == [
        ('/joint_states', 'sensor_msgs/msg/JointState', len(log_times))
    ]
    assert [m.log_time for m in recovered.messages()] == log_times
