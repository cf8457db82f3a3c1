"""bag_tools' ROS-free parts: the player's schedule (PlaybackClock, on a clock the test
moves) and the recorder's writer (BagRecording into a real bag, read back)."""

import pytest

from bag_tools.bag_writer import BagReader, BagWriter, BagWriterError
from bag_tools.playback import PlaybackClock
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
