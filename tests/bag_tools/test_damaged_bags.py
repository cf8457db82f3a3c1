"""A damaged bag (real processes, private domain): a bag recorded by the recorder, then
bytes of one of its chunks overwritten, or its file cut short while the player plays it.
The player stops with one error line naming the damaged file and exits with status 1;
it never plays the damaged bytes as messages."""

import re
import shutil

from mcap.reader import SeekingReader
from sensor_msgs.msg import JointState

from harness import executable, wait_for
from vgm_common.qos import DEFAULT_QOS

TOPIC = '/test/joint_states'
PERIOD = 0.01  # [s] 100 Hz
N_MESSAGES = 300  # 3 s of messages
FLUSH_PERIOD = 0.1  # [s] a chunk every 10 messages or so


def record_bag(spawn, rclpy_node, directory):
    """A bag of N_MESSAGES joint states in many chunks, recorded by the recorder."""
    recorder = spawn(
        [
            executable('bag_tools', 'recorder'),
            '--ros-args',
            '-p',
            f'output_dir:={directory}',
            '-p',
            'bag_name:=good',
            '-p',
            f'topics:=[{TOPIC}]',
            '-p',
            f'flush_period:={FLUSH_PERIOD}',
        ],
        name='recorder',
    )
    publisher = rclpy_node.create_publisher(JointState, TOPIC, DEFAULT_QOS)
    rclpy_node.spin_until(
        lambda: publisher.get_subscription_count() > 0, 30, 'the recorder to subscribe'
    )
    sent = []

    def publish_next():
        message = JointState(name=['j1'], position=[0.001 * len(sent)])
        message.header.stamp.sec = len(sent) + 1
        publisher.publish(message)
        sent.append(message)

    timer = rclpy_node.create_timer(PERIOD, publish_next)
    rclpy_node.spin_until(lambda: len(sent) >= N_MESSAGES, 60, 'the joint states')
    rclpy_node.destroy_timer(timer)
    rclpy_node.destroy_publisher(publisher)
    assert recorder.stop() == 0, recorder.output()
    bag = directory / 'good'
    (data_file,) = bag.glob('good_*.mcap')
    with open(data_file, 'rb') as stream:
        chunks = SeekingReader(stream).get_summary().chunk_indexes
    assert len(chunks) >= 10, f'{len(chunks)} chunks: too few to damage one in the middle'
    return bag, chunks


def copy_bag(bag, directory, name):
    copy = directory / name
    shutil.copytree(bag, copy)
    (data_file,) = copy.glob('good_*.mcap')
    return copy, data_file


def start_player(spawn, bag, *extra):
    return spawn(
        [
            executable('bag_tools', 'player'),
            '--ros-args',
            '-p',
            f'bag:={bag}',
            '-p',
            'wait_for_subscribers:=0.0',
            *extra,
        ],
        name=f'player-{bag.name}',
    )


def check_failed_in_one_line(player, data_file):
    wait_for(lambda: not player.alive(), 60, what='the player to exit')
    output = player.output()
    errors = [line for line in output.splitlines() if '[ERROR]' in line]
    assert player.proc.returncode == 1, output
    assert 'Traceback' not in output, output
    assert len(errors) == 1 and f'{data_file} is damaged' in errors[0], output


def test_damaged_bags_end_the_player_in_one_error_line(spawn, rclpy_node, tmp_path):
    bag, chunks = record_bag(spawn, rclpy_node, tmp_path)
    middle = chunks[len(chunks) // 2]
    damages = {
        # inside the chunk's records: message bytes and lengths become garbage
        'records overwritten': (middle.chunk_start_offset + middle.chunk_length // 2, 32),
        # the chunk's own header (its lengths and compression name)
        'chunk header overwritten': (middle.chunk_start_offset + 1, 40),
    }
    players = {}
    for label, (offset, length) in damages.items():
        copy, data_file = copy_bag(bag, tmp_path, label.replace(' ', '_'))
        with open(data_file, 'r+b') as stream:
            stream.seek(offset)
            stream.write(b'\xff' * length)
        players[label] = (start_player(spawn, copy), data_file)
    for label, (player, data_file) in players.items():
        check_failed_in_one_line(player, data_file)
        assert not re.search(r'played \d+ messages', player.output()), label


def test_a_bag_cut_short_while_playing_ends_the_player_in_one_error_line(
    spawn, rclpy_node, tmp_path
):
    bag, chunks = record_bag(spawn, rclpy_node, tmp_path)
    copy, data_file = copy_bag(bag, tmp_path, 'cut')
    received = []
    rclpy_node.create_subscription(JointState, TOPIC, received.append, DEFAULT_QOS)
    player = start_player(spawn, copy, '-p', 'rate:=0.5')  # 6 s of playing
    rclpy_node.spin_until(lambda: received, 30, 'the first played message')
    with open(data_file, 'r+b') as stream:
        stream.truncate(chunks[len(chunks) // 2].chunk_start_offset)
    check_failed_in_one_line(player, data_file)
    assert len(received) < N_MESSAGES
