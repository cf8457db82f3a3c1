"""Exact-time synchronisation: complete sets out, stale halves dropped and counted."""

from vgm_common.sync import ExactTimeSync


def make_sync(**kwargs):
    out = []
    sync = ExactTimeSync(
        ('left', 'right', 'aux'), lambda stamp, msgs: out.append((stamp, msgs)), **kwargs
    )
    return sync, out


def test_complete_sets_in_any_arrival_order():
    sync, out = make_sync()
    sync.add('right', 10, 'r10', now=0.0)
    sync.add('left', 10, 'l10', now=0.0)
    sync.add('left', 20, 'l20', now=0.0)
    assert not out
    sync.add('aux', 10, 'a10', now=0.01)
    assert out == [(10, {'right': 'r10', 'left': 'l10', 'aux': 'a10'})]
    assert sync.pending == 1 and sync.dropped == 0


def test_unmatched_messages_expire_after_max_wait():
    sync, out = make_sync(max_wait=0.5)
    sync.add('left', 10, 'l10', now=0.0)
    sync.add('right', 10, 'r10', now=0.1)
    sync.add('left', 20, 'l20', now=0.7)  # stamp 10 waited 0.7 s > 0.5 s
    assert sync.dropped == 2 and sync.pending == 1 and not out


def test_completed_set_discards_older_incomplete_sets():
    sync, out = make_sync()
    sync.add('left', 10, 'l10', now=0.0)
    for key in ('left', 'right', 'aux'):
        sync.add(key, 20, key, now=0.0)
    assert [stamp for stamp, _ in out] == [20]
    assert sync.dropped == 1 and sync.pending == 0


def test_queue_size_bounds_pending_sets():
    sync, out = make_sync(queue_size=3, max_wait=100.0)
    for stamp in range(10):
        sync.add('left', stamp, stamp, now=0.0)
    assert sync.pending == 3 and sync.dropped == 7


def test_a_topic_that_never_publishes_is_named():
    sync, out = make_sync()
    assert sync.silent(now=100.0, after=10.0) == []  # nothing at all: nothing to blame
    for k in range(12):  # left and right at 1 Hz, aux never
        sync.add('left', k, f'l{k}', now=float(k))
        sync.add('right', k, f'r{k}', now=float(k))
    assert not out
    assert sync.silent(now=9.0, after=10.0) == []  # not yet 10 s since the first message
    assert sync.silent(now=11.0, after=10.0) == ['aux']
    sync.add('aux', 11, 'a11', now=11.5)
    assert sync.silent(now=12.0, after=10.0) == [] and len(out) == 1
    # Every topic quiet (the rig stopped): no one is singled out.
    assert sync.silent(now=40.0, after=10.0) == []
