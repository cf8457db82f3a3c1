"""A recorder killed with SIGKILL (real processes, private domain): its bag streams with
mcap's own readers as it is, losing at most the last flush period, and after `reindex`
every reader opens it (rosbags' AnyReader, mcap's indexed reader with mcap_ros2 decoding,
BagReader) with the same messages. A recorder killed before anything was flushed leaves
a valid, empty bag. Nothing the talker published after the recorder matched is lost at
the start of the recording."""

import signal
import subprocess

from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.duration import Duration
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader
from sensor_msgs.msg import JointState

from bag_tools.bag_writer import METADATA_FILENAME, BagReader
from harness import executable, wait_for
from vgm_common.qos import DEFAULT_QOS

TOPIC = '/test/joint_states'
PERIOD = 0.01  # [s] 100 Hz
FLUSH_PERIOD = 0.5  # [s]
N_BEFORE_KILL = 200  # 2 s of messages


def start_recorder(spawn, tmp_path, name, *extra):
    return spawn(
        [
            executable('bag_tools', 'recorder'),
            '--ros-args',
            '-p',
            f'output_dir:={tmp_path}',
            '-p',
            f'bag_name:={name}',
            '-p',
            f'topics:=[{TOPIC}]',
            '-p',
            f'flush_period:={FLUSH_PERIOD}',
            *extra,
        ],
        name=f'recorder-{name}',
    )


def sequence_numbers(messages):
    """The talker's index of each message (its header.stamp.sec), in order."""
    return [deserialize_message(data, JointState).header.stamp.sec for data in messages]


def stream_all(path):
    """Messages of one MCAP file read front to back in log-time order (mcap's default)."""
    with open(path, 'rb') as stream:
        return [message.data for _, _, message in NonSeekingReader(stream).iter_messages()]


def streamed_numbers(bag):
    return sequence_numbers(
        [data for path in sorted(bag.glob(f'{bag.name}_*.mcap')) for data in stream_all(path)]
    )


def test_a_killed_recorder_leaves_a_bag_every_reader_opens(spawn, rclpy_node, tmp_path):
    node = rclpy_node
    publisher = node.create_publisher(JointState, TOPIC, DEFAULT_QOS)
    recorder = start_recorder(spawn, tmp_path, 'killed', '-p', 'compression:=zstd')
    node.spin_until(
        lambda: publisher.get_subscription_count() > 0, 30, 'the recorder to subscribe'
    )
    sent = []

    def publish_next():
        message = JointState(name=['j1'], position=[0.001 * len(sent)])
        message.header.stamp.sec = len(sent) + 1  # 1-based: a zero stamp means "none"
        publisher.publish(message)
        sent.append(message)

    timer = node.create_timer(PERIOD, publish_next)
    node.spin_until(lambda: len(sent) >= N_BEFORE_KILL, 60, 'the joint states')
    node.destroy_timer(timer)
    assert publisher.wait_for_all_acked(Duration(seconds=10))
    bag = tmp_path / 'killed'
    # Within a flush period or two the recorder has flushed all it received; a streaming
    # reader reads it while the recorder still runs.
    wait_for(
        lambda: len(streamed_numbers(bag)) == N_BEFORE_KILL,
        10 + 4 * FLUSH_PERIOD,
        'every message flushed',
    )
    recorder.stop(signal.SIGKILL)
    assert not (bag / METADATA_FILENAME).exists()

    # As it is: a streaming reader reads every flushed chunk, from the very first message.
    streamed = streamed_numbers(bag)
    assert streamed == list(range(1, N_BEFORE_KILL + 1))  # nothing lost at the start

    result = subprocess.run(
        [executable('bag_tools', 'reindex'), str(bag)], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert f'{len(streamed)} messages' in result.stdout

    # Indexed: mcap's seeking reader with its summary, decoding with mcap_ros2.
    with open(sorted(bag.glob('killed_*.mcap'))[0], 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        chunks = reader.get_summary().chunk_indexes
        assert chunks and all(chunk.compression == 'zstd' for chunk in chunks)
        decoded = [m.header.stamp.sec for _, _, _, m in reader.iter_decoded_messages()]
    assert decoded == streamed
    with AnyReader([bag]) as reader:
        assert reader.message_count == len(streamed)
        (connection,) = [c for c in reader.connections if c.topic == TOPIC]
        stamps = [
            reader.deserialize(raw, connection.msgtype).header.stamp.sec
            for _, _, raw in reader.messages(connections=[connection])
        ]
    assert stamps == streamed
    reindexed = BagReader(bag)
    assert not reindexed.recovered and reindexed.topic(TOPIC).message_count == len(streamed)
    assert reindexed.topic(TOPIC).offered_qos_profiles[0]['reliability'] == 'reliable'


def test_a_recorder_killed_at_once_leaves_a_valid_empty_bag(spawn, rclpy_node, tmp_path):
    recorder = start_recorder(spawn, tmp_path, 'early')
    wait_for(lambda: 'recording to' in recorder.output(), 30, 'the recorder to start')
    recorder.stop(signal.SIGKILL)
    bag = tmp_path / 'early'
    for path in bag.glob('early_*.mcap'):
        assert stream_all(path) == []
    result = subprocess.run(
        [executable('bag_tools', 'reindex'), str(bag)], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and '0 messages' in result.stdout, result
    with AnyReader([bag]) as reader:
        assert reader.message_count == 0


def test_reindex_refuses_what_is_no_bag(tmp_path):
    result = subprocess.run(
        [executable('bag_tools', 'reindex'), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    assert result.stderr.count('\n') == 1 and 'is not a bag' in result.stderr
