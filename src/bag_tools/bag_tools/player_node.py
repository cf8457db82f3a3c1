"""``player``: replays a rosbag2 MCAP bag onto its topics with the recorded timing.

The recorded serialized bytes are published unchanged, in log-time order, message ``i`` at
``start + (log_time_i - log_time_0) / rate`` on the monotonic clock (no drift accumulates).
Topics recorded from transient-local publishers only are republished latched
(``LATCHED_QOS``), the others with ``DEFAULT_QOS``; both are reliable, so they reach
reliable and best-effort subscribers alike.

Discovery: a volatile publisher delivers nothing to a subscriber it has not matched yet, so
the first messages of a replay would be lost to discovery. Before playing, the player waits
until every publisher has at least one matched subscription (then 0.2 s more, for the
subscriber's side of the match), at most ``wait_for_subscribers`` seconds (default 5 s:
discovering a newly started process can take a few seconds here; topics nobody listens to
then simply start unheard). Once matched, the reliable middleware retransmits what a
subscriber missed while it is still in the publisher's history (the last 10 messages).
At the end the player waits (bounded) until the subscribers acknowledged everything, so
exiting does not cut off the last messages.

By default ``/rosout``, ``/parameter_events`` and ``/diagnostics`` are recorded but not
replayed (parameter ``exclude``): old log lines, parameter changes and health reports are not
inputs of any node, and would reappear on the live graph as if they were happening now.

A missing or invalid bag or parameter is reported in one log line and the process exits with
status 2 (the project's status for unusable start-up input, as ``vgm_common.node_main``).
A bag found damaged while playing (chunk bytes overwritten: chunk CRCs are checked; a file
cut short, before or while it plays) stops playback with one error line naming the file and the
messages read from it, and the process exits with status 1; nothing of the damaged chunk
is published.

/diagnostics, every ``DIAGNOSTICS_PERIOD`` and when playback ends: state, messages played /
messages of the played topics in the bag, bag time; WARN if a requested topic cannot be
played or a parameter change was refused, ERROR if reading the bag failed.
"""

import sys
import threading
import time

from bag_tools.bag_writer import BagError, BagReader
from bag_tools.message_definitions import DefinitionNotFoundError, type_hash
from bag_tools.playback import PlaybackClock
from bag_tools.topic_discovery import import_message_type
from vgm_common.errors import VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import Param
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import DIAGNOSTICS_TOPIC

_MAX_SLEEP = 0.05  # [s] sleep slices, so a rate change or a stop takes effect promptly
MATCH_SETTLE = 0.2  # [s] after every publisher has matched a subscriber, before playing
DIAGNOSTICS_PERIOD = 1.0  # [s]
MIN_RATE, MAX_RATE = 1e-3, 1e3  # playback speed factors accepted


class PlayerStartupError(VgmError):
    """The bag is unusable or holds nothing to play; the message says which and why."""


def _required(value):
    return None if value else 'is required: the bag directory to play'


def is_latched(topic_info):
    """True if every recorded publisher of the topic offered transient-local durability."""
    profiles = topic_info.offered_qos_profiles
    return bool(profiles) and all(p.get('durability') == 'transient_local' for p in profiles)


PARAMETERS = [
    Param(
        'bag',
        '',
        'Path of the bag directory (the one holding metadata.yaml).',
        check=_required,
        read_only=True,
    ),
    Param(
        'rate',
        1.0,
        'Playback speed factor (2 = twice as fast); may be changed while playing.',
        range=(MIN_RATE, MAX_RATE),
    ),
    Param('loop', False, 'Play the bag again and again.', read_only=True),
    Param(
        'topics',
        [],
        'Topics to play (exact names); empty = every recorded topic.',
        read_only=True,
    ),
    Param(
        'exclude',
        ['/rosout', '/parameter_events', DIAGNOSTICS_TOPIC],
        'Recorded topics not to play (exact names); [] = none.',
        read_only=True,
    ),
    Param(
        'exit_when_done',
        True,
        'Exit once the bag was played; false keeps latched topics available.',
        read_only=True,
    ),
    Param(
        'wait_for_subscribers',
        5.0,
        '[s] Before playing, wait at most this long '
        'for every topic to have a subscriber, so the first messages are not lost '
        'to discovery; 0 = do not wait.',
        range=(0.0, 3600.0),
        read_only=True,
    ),
]


class PlayerNode(GraphNode):
    """Publishes the messages of one bag with the recorded timing.

    ``finished`` is set once playback ended (or failed); ``published`` counts per topic.
    For ``vgm_common.node_main.run_node``: ``exit_requested`` is set once playback ended if
    ``exit_when_done``; ``close()``; ``exit_status`` (1 if reading the bag failed).

    Raises:
        ParameterError: invalid parameter value.
        PlayerStartupError: no/invalid bag, or nothing to play.
    """

    node_name = 'player'

    def __init__(self, **kwargs):
        super().__init__(
            PARAMETERS, on_change={'rate': lambda rate: self._schedule.set_rate(rate)}, **kwargs
        )
        self.exit_when_done = self.params.exit_when_done
        self._loop = self.params.loop
        self._wait_for_subscribers = self.params.wait_for_subscribers
        try:
            self._reader = BagReader(self.params.bag)
        except BagError as error:
            raise PlayerStartupError(f'cannot play {self.params.bag!r}: {error}') from None
        self._not_played = {}  # requested topic -> why it is not played
        self._topic_publishers = self._create_publishers(self.params.topics, self.params.exclude)
        self.published = {name: 0 for name in self._topic_publishers}
        self._total = sum(
            t.message_count for t in self._reader.topics if t.name in self._topic_publishers
        )  # one pass
        # [ns] bag time 0 (the first message played if the metadata does not say) and length
        self._bag_start, self._bag_duration = _bag_span(self._reader)
        self._bag_time = None  # [ns] log time of the last message played
        self._passes = 0
        self._state = 'waiting for subscribers'
        self.finished = threading.Event()
        self.error = None
        self.exit_requested = threading.Event()
        self._stop = threading.Event()
        self._schedule = PlaybackClock(self.params.rate)
        self.create_timer(DIAGNOSTICS_PERIOD, self._publish_progress)
        self._thread = threading.Thread(target=self._run, name='playback', daemon=True)
        self._thread.start()

    @property
    def exit_status(self):
        """The process exit status: 1 if reading the bag failed, else 0."""
        return 0 if self.error is None else 1

    # -- publishers --------------------------------------------------------------------

    def _create_publishers(self, wanted, excluded):
        recorded = {t.name: t for t in self._reader.topics}
        for name in wanted:
            if name not in recorded:
                self._not_played[name] = 'not in the bag'
                self.get_logger().warning(f'topic {name} is not in the bag')
        names = [n for n in recorded if (not wanted or n in wanted) and n not in excluded]
        publishers = {}
        for name in names:
            info = recorded[name]
            try:
                message_type = import_message_type(info.type)
            except (ImportError, AttributeError, ValueError) as error:
                self._not_played[name] = f'type {info.type} is not installed'
                self.get_logger().warning(
                    f'not playing {name}: type {info.type} is not installed ({error})'
                )
                continue
            try:
                local_hash = type_hash(info.type)
            except DefinitionNotFoundError:
                local_hash = ''
            if (
                info.type_description_hash
                and local_hash
                and info.type_description_hash != local_hash
            ):
                self.get_logger().warning(
                    f'{name}: recorded {info.type} differs from the installed definition '
                    f'({info.type_description_hash} != {local_hash}); playing the bytes as is'
                )
            latched = is_latched(info)
            publishers[name] = self.create_publisher(
                message_type, name, LATCHED_QOS if latched else DEFAULT_QOS
            )
            self.get_logger().info(
                f'playing {name} [{info.type}] {info.message_count} messages'
                + (' (latched)' if latched else '')
            )
        if not publishers:
            raise PlayerStartupError(
                f'nothing to play in {self._reader.path}: no recorded topic matches topics/exclude'
            )
        return publishers

    # -- playback (playback thread) --------------------------------------------------------

    def _sleep_until(self, log_time_ns):
        """Sleep until the wall time of ``log_time_ns``; False if stopped meanwhile."""
        while True:
            remaining = self._schedule.due_in(log_time_ns)
            if remaining <= 0:
                return not self._stop.is_set()
            if self._stop.wait(min(remaining, _MAX_SLEEP)):
                return False

    def _await_subscribers(self):
        if self._wait_for_subscribers <= 0:
            return
        deadline = time.monotonic() + self._wait_for_subscribers
        while time.monotonic() < deadline:
            if all(p.get_subscription_count() > 0 for p in self._topic_publishers.values()):
                # Our publishers matched; the subscribers' half of the match can lag a few
                # ms, and a sample sent in that gap arrives late (repaired) or not at all.
                self._stop.wait(MATCH_SETTLE)
                return
            if self._stop.wait(0.02):
                return
        lonely = sorted(
            name
            for name, publisher in self._topic_publishers.items()
            if publisher.get_subscription_count() == 0
        )
        self.get_logger().info(
            f'no subscriber after {self._wait_for_subscribers:g} s on {", ".join(lonely)}; '
            'playing anyway'
        )

    def _play_once(self):
        """Play the bag once; False if stopped or there was nothing to play."""
        first = True
        for message in self._reader.messages(self._topic_publishers):
            if first:
                self._schedule.start(message.log_time)
                if self._bag_start is None:
                    self._bag_start = message.log_time
                first = False
            if not self._sleep_until(message.log_time):
                return False
            self._topic_publishers[message.topic].publish(bytes(message.data))
            self.published[message.topic] += 1
            self._bag_time = message.log_time
        return not first

    def _run(self):
        try:
            self._await_subscribers()
            started = time.monotonic()
            self._state = 'playing'
            while not self._stop.is_set():
                self._passes += 1
                if not self._play_once() or not self._loop:
                    break
            self._state = 'stopped' if self._stop.is_set() else 'done'
            self.get_logger().info(
                f'played {sum(self.published.values())} messages in '
                f'{time.monotonic() - started:.2f} s'
            )
        except (BagError, OSError, ValueError) as error:
            self.error = error
            self._state = 'failed'
            self.get_logger().error(f'playing {self._reader.path} failed: {error}')
        finally:
            self.finished.set()
            if self.exit_when_done:
                self.exit_requested.set()  # run_node's close() joins this thread first
            if self.context.ok():
                self._publish_progress()

    # -- diagnostics -------------------------------------------------------------------------

    def _publish_progress(self):
        played = sum(self.published.values())
        values: dict[str, object] = {
            'messages played': played,
            'messages in bag': self._total,
            'rate': self._schedule.rate,
        }
        if self._loop:
            values['pass'] = self._passes
        if self._bag_time is not None:
            values['bag time [s]'] = f'{(self._bag_time - self._bag_start) / 1e9:.3f}'
        if self._bag_duration is not None:
            values['bag duration [s]'] = f'{self._bag_duration / 1e9:.3f}'
        for name, reason in sorted(self._not_played.items()):
            values[f'not played {name}'] = reason
        rejected = dict(self.diagnostics.rejected)  # updated by the executor thread
        for what, count in rejected.items():
            values[f'rejected {what}'] = count
        if self.error is not None:
            level, message = 'error', f'failed: {self.error}'
        else:
            level = 'warn' if self._not_played or rejected else 'ok'
            message = f'{self._state}: {played} / {self._total} messages'
        self.diagnostics.publish('playback', level, message, values)

    # -- shutdown ------------------------------------------------------------------------

    def stop(self):
        """Stop playback and wait for the playback thread. Idempotent."""
        self._stop.set()
        self._thread.join()

    def close(self):
        """For run_node: stop playback before the node is destroyed."""
        self.stop()


def _bag_span(reader):
    """(start [ns since epoch], duration [ns]) of the bag from its metadata; (None, None)
    for a bag recovered without metadata."""
    try:
        return (
            int(reader.metadata['starting_time']['nanoseconds_since_epoch']),
            int(reader.metadata['duration']['nanoseconds']),
        )
    except (KeyError, TypeError, ValueError):
        return None, None


def main(args=None):
    """Play the bag; returns the exit status: 0 = played (or stopped by SIGINT/SIGTERM),
    1 = the bag failed while reading, 2 = unusable bag or parameter at start-up."""
    return run_node(PlayerNode, args)


if __name__ == '__main__':
    sys.exit(main())
