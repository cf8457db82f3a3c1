"""bag_tools' ROS-free parts: the player's schedule (PlaybackClock, on a clock the test
moves), the recorder's writer (BagRecording into a real bag, read back) and its state
(Recorder: message times, drain, diagnostics)."""

import re

import pytest
from builtin_interfaces.msg import Time
from rclpy.serialization import serialize_message
from std_msgs.msg import Header

from bag_tools.bag_writer import BagMessage, BagReader, BagReaderError, BagWriter, BagWriterError
from bag_tools.playback import (
    MATCH_POLL,
    MATCH_SETTLE,
    Playback,
    PlaybackClock,
    PlayerSettings,
    bag_span,
    topics_to_play,
)
from bag_tools.recorder import (
    MAX_DRAIN_PERIOD,
    QUIET_PERIOD,
    BagSettings,
    Recorder,
    RecorderStartupError,
    default_bag_name,
)
from bag_tools.recording import BagRecording, MessageQueue
from harness import ManualClock


def test_the_schedule_follows_the_bag_at_its_rate_and_a_rate_change_does_not_jump():
    clock = ManualClock(50.0)
    schedule = PlaybackClock(2.0, clock)
    with pytest.raises(RuntimeError):
        schedule.due_in(0)
    schedule.start(10_000_000_000)  # bag time 10 s plays now
    assert schedule.due_in(10_000_000_000) == 0.0
    assert schedule.due_in(11_000_000_000) == pytest.approx(0.5)  # 1 s of bag at rate 2
    clock.now += 0.25  # bag time 10.5 s reached
    assert schedule.due_in(10_400_000_000) < 0  # already due: published at once
    schedule.set_rate(0.5)
    assert schedule.due_in(10_500_000_000) == pytest.approx(0.0, abs=1e-9)
    assert schedule.due_in(11_000_000_000) == pytest.approx(1.0)  # 0.5 s of bag at rate 0.5


def test_the_queue_drops_the_oldest_beyond_its_size():
    queue = MessageQueue(max_bytes=10)
    for i in range(4):
        queue.put(('/a' if i < 3 else '/b', b'x' * 4, i, i))
    assert queue.dropped == {'/a': 2}
    assert [item[2] for item in queue.take_all(timeout=0)] == [2, 3]
    queue.close()
    assert queue.take_all(timeout=0) is None


def test_the_recording_writes_every_message_and_closes_the_bag(tmp_path):
    failures = []
    recording = BagRecording(
        BagWriter(tmp_path / 'bag'), max_cache_size=0, flush_period=0.1, on_failure=failures.append
    )
    recording.add_topic('/a', 'std_msgs/msg/String', [])
    for i in range(100):
        recording.put('/a', f'message {i}'.encode(), 1_000 + i, 1_000 + i)
    assert recording.close() is None and recording.close() is None  # idempotent
    assert failures == [] and recording.write_error is None
    assert recording.bytes_written == sum(len(f'message {i}') for i in range(100))
    messages = list(BagReader(tmp_path / 'bag').messages())
    assert [m.data for m in messages] == [f'message {i}'.encode() for i in range(100)]
    assert [m.log_time for m in messages] == list(range(1_000, 1_100))


def test_a_write_that_fails_stops_the_recording_and_says_so(tmp_path):
    failures = []
    recording = BagRecording(
        BagWriter(tmp_path / 'bag'), max_cache_size=0, flush_period=0.0, on_failure=failures.append
    )
    recording.put('/never_added', b'data', 1, 1)  # BagWriter refuses an unknown topic
    recording.close()
    assert len(failures) == 1 and isinstance(failures[0], BagWriterError)
    assert recording.write_error is failures[0]


def stamped_message(sec, nanosec, text):
    """A serialized std_msgs/Header (a stamped message's first field) and some text."""
    header = Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=text)
    return bytes(serialize_message(header))


def test_the_recorder_stores_receive_time_and_header_or_send_time(tmp_path):
    node_clock = iter(range(7_000, 8_000))
    failures = []
    recorder = Recorder(
        BagSettings(bag_name='bag', output_dir=str(tmp_path)),
        on_failure=failures.append,
        log_clock_ns=lambda: next(node_clock),
    )
    assert recorder.bag_path == str(tmp_path / 'bag')
    recorder.add_topic('/stamped', 'std_msgs/msg/Header', [], stamped=True)
    recorder.add_topic('/plain', 'std_msgs/msg/Header', [], stamped=False)
    recorder.take('/stamped', stamped_message(3, 500, 'a'), 5_000, 4_000)  # the stamp
    recorder.take('/stamped', stamped_message(0, 0, 'b'), 5_001, 4_001)  # unset: send time
    recorder.take('/plain', stamped_message(3, 500, 'c'), 5_002, 4_002)  # not read
    recorder.take('/plain', stamped_message(3, 500, 'd'), 5_003, 0)  # no send time: log
    recorder.take('/plain', stamped_message(3, 500, 'e'), 0, 0)  # no receive time: clock
    assert recorder.recording.close() is None and failures == []
    times = [(m.log_time, m.publish_time) for m in BagReader(tmp_path / 'bag').messages()]
    assert times == [
        (5_000, 3_000_000_500),
        (5_001, 4_001),
        (5_002, 4_002),
        (5_003, 5_003),
        (7_000, 7_000),
    ]
    assert recorder.never_published({'/plain', '/never'}) == ['/never']
    assert recorder.counts()[1:] == ['  /stamped: 2', '  /plain: 3']


def test_the_recorder_refuses_an_existing_bag_in_one_line(tmp_path):
    (tmp_path / 'bag').mkdir()
    with pytest.raises(RecorderStartupError, match='bag'):
        Recorder(BagSettings(bag_name='bag', output_dir=str(tmp_path)), print)


def test_the_default_bag_name_is_rosbag2_s_with_local_time(tmp_path):
    recorder = Recorder(BagSettings(output_dir=str(tmp_path)), print, now=0.0)
    assert recorder.bag_path == str(tmp_path / default_bag_name(0.0))
    assert re.fullmatch(r'rosbag2_\d{4}_\d\d_\d\d-\d\d_\d\d_\d\d', default_bag_name(0.0))
    recorder.recording.close()


def test_the_drain_ends_after_a_quiet_period_and_a_second_type_is_said_once(tmp_path):
    clock = ManualClock(100.0)
    recorder = Recorder(BagSettings(bag_name='bag', output_dir=str(tmp_path)), print, clock=clock)
    recorder.add_topic('/a', 'std_msgs/msg/String', [], stamped=False)
    assert recorder.start_drain() == MAX_DRAIN_PERIOD
    clock.now += QUIET_PERIOD * 0.8
    recorder.take('/a', b'\x00\x01\x00\x00\x01\x00\x00\x00\x00\x00\x00\x00', 1, 1)
    clock.now += QUIET_PERIOD * 0.8  # the last message came less than the period ago
    assert not recorder.drained()
    clock.now += QUIET_PERIOD * 0.3
    assert recorder.drained()
    assert recorder.new_second_type('/a', ['std_msgs/msg/String']) is None
    reason = recorder.new_second_type('/a', ['std_msgs/msg/String', 'std_msgs/msg/Int32'])
    assert 'only std_msgs/msg/String is recorded' in reason
    assert recorder.new_second_type('/a', ['std_msgs/msg/String', 'std_msgs/msg/Int32']) is None
    level, message, values = recorder.status(skipped={'/b'})
    assert (level, message) == ('warn', 'recording')  # a topic could not be recorded
    assert values['/a'] == '0' and values['not recorded'] == '/b'  # the writer not yet
    recorder.recording.close()
    level, message, values = recorder.status(skipped=set())
    assert (level, message, values['messages'], values['/a']) == ('ok', 'closed', 1, '1')


class ManualStop:
    """A Playback's stop on a manual clock: waiting moves the clock by the timeout, or to
    ``stop_at`` [s] if that comes first (then it is set)."""

    def __init__(self, clock, stop_at=float('inf')):
        self.clock, self.stop_at = clock, stop_at

    def is_set(self):
        return self.clock.now >= self.stop_at

    def wait(self, timeout):
        self.clock.now = min(self.clock.now + timeout, max(self.stop_at, self.clock.now))
        return self.is_set()


def bag_messages(log_times_s, topic='/a'):
    """Messages of ``topic`` at these log times [s], numbered in their data."""
    return [
        BagMessage(topic, 'std_msgs/msg/String', b'%d' % i, round(t * 1e9), 0)
        for i, t in enumerate(log_times_s)
    ]


class Played:
    """A Playback of ``messages`` (an iterable, or a function giving one) on a manual
    clock, with what it published (clock time, topic, data) and logged (level, text);
    ``after_publish(played)`` runs after each message."""

    def __init__(
        self, messages, stop_at=float('inf'), topics=('/a',), after_publish=None, **settings
    ):
        self.clock = ManualClock(100.0)
        self.published, self.log = [], []

        def publish(topic, data):
            self.published.append((self.clock.now, topic, data))
            if after_publish is not None:
                after_publish(self)

        self.playback = Playback(
            PlayerSettings(bag='bag', **settings),
            'bag',
            topics,
            messages if callable(messages) else lambda: iter(messages),
            publish,
            lambda level, text: self.log.append((level, text)),
            ManualStop(self.clock, stop_at),
            self.clock,
        )

    def times(self):
        return [t for t, _, _ in self.published]


def test_playback_publishes_each_message_at_its_recorded_time_over_the_rate():
    played = Played(bag_messages([50.0, 50.1, 50.35, 51.0]), rate=2.0, wait_for_subscribers=0)
    played.playback.run(unheard=lambda: ['/a'])  # no wait asked: plays at once
    assert played.times() == pytest.approx([100.0, 100.05, 100.175, 100.5], abs=1e-9)
    assert [data for _, _, data in played.published] == [b'0', b'1', b'2', b'3']
    assert played.playback.state == 'done' and played.playback.published == {'/a': 4}
    assert played.log == [('info', 'played 4 messages in 0.50 s')]
    level, message, values = played.playback.progress(4, None, None, {}, {})
    assert (level, message) == ('ok', 'done: 4 / 4 messages')
    assert values['bag time [s]'] == '1.000'  # from the first message played


def test_playback_waits_for_subscribers_then_settles_or_gives_up_after_its_wait():
    heard_at = 101.0  # [s] every topic has a subscriber from then on
    played = Played(bag_messages([0.0]), wait_for_subscribers=5.0)
    played.playback.run(unheard=lambda: [] if played.clock.now >= heard_at else ['/a'])
    assert played.times()[0] == pytest.approx(heard_at + MATCH_SETTLE, abs=MATCH_POLL + 1e-9)
    never = Played(bag_messages([0.0]), topics=('/a', '/b'), wait_for_subscribers=5.0)
    never.playback.run(unheard=lambda: ['/b', '/a'])
    assert never.times()[0] == pytest.approx(105.0, abs=MATCH_POLL + 1e-9)
    assert never.log[0] == ('info', 'no subscriber after 5 s on /a, /b; playing anyway')


def test_a_looping_playback_plays_again_until_stopped_and_a_rate_change_re_anchors():
    played = Played(bag_messages([0.0, 1.0]), stop_at=102.5, loop=True, wait_for_subscribers=0)
    played.playback.run(unheard=list)
    assert played.times() == pytest.approx([100.0, 101.0, 101.0, 102.0, 102.0], abs=1e-9)
    assert played.playback.passes == 3 and played.playback.state == 'stopped'
    assert played.playback.progress(2, 0, 10**9, {}, {})[2]['pass'] == 3

    def speed_up_after_the_first(played):
        if len(played.published) == 1:
            played.clock.now += 0.5  # half a second of bag at rate 1 ...
            played.playback.schedule.set_rate(2.0)  # ... then twice as fast

    faster = Played(
        bag_messages([0.0, 1.0, 2.0]),
        after_publish=speed_up_after_the_first,
        wait_for_subscribers=0,
    )
    faster.playback.run(unheard=list)
    assert faster.times() == pytest.approx([100.0, 100.75, 101.25], abs=1e-9)


def test_a_bag_that_fails_while_playing_stops_the_playback_with_its_error():
    def messages():
        yield from bag_messages([0.0, 0.1])
        raise BagReaderError('chunk CRC mismatch', 'bag_0.mcap')

    played = Played(messages, wait_for_subscribers=0)
    played.playback.run(unheard=list)
    assert len(played.published) == 2 and played.playback.state == 'failed'
    assert played.log == [('error', 'playing bag failed: chunk CRC mismatch')]
    level, message, values = played.playback.progress(
        5, 0, None, {'/c': 'not in the bag'}, {'parameter change': 1}
    )
    assert (level, message) == ('error', 'failed: chunk CRC mismatch')
    assert values['not played /c'] == 'not in the bag'
    assert values['rejected parameter change'] == 1


def test_topics_to_play_and_the_bag_span():
    names, missing = topics_to_play(['/a', '/b', '/c'], wanted=['/c', '/x', '/a'], excluded=['/a'])
    assert names == ['/c'] and missing == {'/x': 'not in the bag'}
    assert topics_to_play(['/a', '/rosout'], [], ['/rosout']) == (['/a'], {})
    metadata = {'starting_time': {'nanoseconds_since_epoch': 7}, 'duration': {'nanoseconds': 9}}
    assert bag_span(metadata) == (7, 9)
    assert bag_span(None) == bag_span({}) == (None, None)
