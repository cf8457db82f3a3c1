"""curve_recon_node's CaptureScheduler without ROS: which captures are reconstructed and
what happens to the ~/reconstruct calls waiting for one, on a clock the test turns."""

from curve_recon_node.report import capture_status
from curve_recon_node.scheduler import AUTO_RETRY_S, MAX_WAITING_CALLS, CaptureScheduler
from harness import ManualClock


def answers():
    """A list of (success, message) and a reply that appends to it."""
    got = []
    return got, lambda success, message: got.append((success, message))


def test_nothing_is_reconstructed_until_the_calibration_or_a_call_asks():
    scheduler = CaptureScheduler(ManualClock(50.0))
    assert scheduler.take(1) is None
    scheduler.calibration_changed()
    job = scheduler.take(2)
    assert job is not None and job.stamp_ns == 2 and job.calls == []


def test_automatic_attempts_are_retried_once_a_second_until_one_succeeds():
    clock = ManualClock(50.0)
    scheduler = CaptureScheduler(clock)
    scheduler.calibration_changed()
    assert scheduler.take(1) is not None
    clock.now += AUTO_RETRY_S / 2
    assert scheduler.take(2) is None  # the first attempt may still be running
    clock.now += AUTO_RETRY_S / 2
    assert scheduler.take(3) is not None  # it failed: try again
    scheduler.succeeded()
    clock.now += 10 * AUTO_RETRY_S
    assert scheduler.take(4) is None
    scheduler.calibration_changed()  # a new calibration: at once
    assert scheduler.take(5) is not None


def test_a_capture_of_the_chart_is_skipped_and_its_calls_wait_for_the_next():
    clock = ManualClock(50.0)
    scheduler = CaptureScheduler(clock)
    got, reply = answers()
    assert scheduler.add_call(reply, timeout=5.0) is None
    scheduler.chart_shown(10)
    assert scheduler.take(10) is None and scheduler.skipped_chart == 1
    assert scheduler.waiting == 1
    # The chart's pose may come after its images: the job finds out before it runs.
    job = scheduler.take(11)
    assert len(job.calls) == 1 and scheduler.waiting == 0
    scheduler.chart_shown(11)
    assert scheduler.is_chart(job) and job.calls == [] and scheduler.waiting == 1
    job = scheduler.take(12)
    assert not scheduler.is_chart(job)
    job.calls[0].reply(True, 'published')
    assert got == [(True, 'published')]


def test_calls_time_out_refuse_beyond_the_limit_and_are_all_answered_on_close():
    clock = ManualClock(50.0)
    scheduler = CaptureScheduler(clock)
    got, reply = answers()
    for _ in range(MAX_WAITING_CALLS):
        assert scheduler.add_call(reply, timeout=2.0) is None
    refusal = scheduler.add_call(reply, timeout=2.0)
    assert refusal == f'{MAX_WAITING_CALLS} reconstruct calls are waiting already'
    late_got, late = answers()
    clock.now += 1.0
    assert scheduler.expired() == []
    clock.now += 1.0
    assert len(scheduler.expired()) == MAX_WAITING_CALLS and scheduler.waiting == 0
    scheduler.add_call(late, timeout=2.0)
    job = scheduler.take(1)
    scheduler.put_back(job)  # dropped before it ran: the call waits again
    assert scheduler.waiting == 1
    calls = scheduler.close()
    assert [call.reply for call in calls] == [late] and scheduler.waiting == 0
    assert got == [] and late_got == []  # the node answers what it is handed


def test_the_cameras_wait_for_aux_until_aux_wait_then_two_views_serve():
    clock = ManualClock(50.0)
    scheduler = CaptureScheduler(clock)
    assert scheduler.cameras_to_use(['left', 'aux'], 3, 2.0) is None  # right missing
    assert scheduler.cameras_to_use(['left', 'right'], 3, 2.0) is None  # aux may come
    clock.now += 1.9
    assert scheduler.cameras_to_use(['left', 'right'], 3, 2.0) is None
    clock.now += 0.2
    assert scheduler.cameras_to_use(['left', 'right'], 3, 2.0) == ('left', 'right')
    assert scheduler.cameras_to_use(['left', 'right', 'aux'], 3, 2.0) == ('left', 'right', 'aux')
    assert scheduler.cameras_to_use(['left', 'right', 'aux'], 2, 2.0) == ('left', 'right')
    # a recalibration of right restarts aux's grace
    assert scheduler.cameras_to_use(['left'], 3, 2.0) is None
    assert scheduler.cameras_to_use(['left', 'right'], 3, 2.0) is None


def test_the_status_names_what_is_missing_then_what_is_wrong():
    assert capture_status(['aux'], 2, 0, False) == ('ok', 'waiting for a capture')
    assert capture_status(['aux'], 3, 5, True) == (
        'warn',
        'no camera info yet: waiting for the calibration of aux',
    )
    level, message = capture_status([], 3, 5, True)
    assert level == 'warn' and message.startswith('images not synchronized: 5 dropped')
    assert capture_status([], 3, 0, True) == ('ok', 'waypoints published')
