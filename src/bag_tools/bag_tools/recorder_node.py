"""``recorder``: records every published topic (or a chosen set) to a rosbag2 MCAP directory.

Like ``ros2 bag record -a -s mcap`` on Jazzy: topics are discovered while running, each is
subscribed as serialized bytes (nothing is deserialized or re-serialized), with a QoS
adapted to its publishers, and written to ``<output_dir>/<bag_name>/`` by
``bag_tools.bag_writer.BagWriter``. SIGINT and SIGTERM close the bag cleanly (summary and
``metadata.yaml`` written) and the message counts per topic are logged.

Topics: all published topics except hidden ones (a name token starting with ``_``), exactly
as ``ros2 bag record -a``: this includes ``/rosout`` (the nodes' logs are worth keeping for a
post-mortem) and ``/parameter_events``; list names in ``exclude`` to leave them out. A topic
is recorded once it has a publisher and its type's definition is installed; a topic with
several types is skipped with a warning.

QoS (rosbag2's ``adapt_request_to_offers``): reliable if every publisher is reliable, else
best effort; transient local if every publisher is transient local (so a latched value
published before the recorder started is recorded), else volatile; keep last
``SUBSCRIPTION_DEPTH`` (1000) so a burst is not dropped. The publishers' offered profiles
when the topic is first subscribed are stored in the bag (both ``metadata.yaml`` and the
MCAP channel, which must agree).

Times: log time = the middleware's receive time (the node clock under ``use_sim_time``);
publish time = the message's ``header.stamp`` when its first field is a ``std_msgs/Header``
with a non-zero stamp, else the publisher's send time, else the receive time. (rosbag2
itself always stores the send time.)

The subscription callbacks only time-stamp and enqueue; a writer thread drains the queue
into the bag, and flushes the chunk being filled every ``flush_period`` so a crash loses at
most that long of data. The queue holds at most ``max_cache_size`` bytes; beyond that the
oldest messages are dropped and counted.

/diagnostics, every ``DIAGNOSTICS_PERIOD`` and once more when the bag is closed: topics
recorded, messages written per topic, messages dropped, bytes written; WARN once a message
was dropped or a topic could not be recorded, ERROR once writing failed.
"""

import os
import sys
import threading
import time

from bag_tools.bag_writer import BagError, BagWriter, header_stamp_ns, qos_profile
from bag_tools.recording import BagRecording
from bag_tools.topic_discovery import TopicDiscovery, subscription_qos, topic_selection_params
from vgm_common.errors import VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import Param

# After a stop request, keep taking the messages the middleware already holds until none
# came for QUIET_PERIOD (a recorder behind the publishers must not lose its backlog), at
# most MAX_DRAIN_PERIOD.
QUIET_PERIOD = 0.25  # [s]
MAX_DRAIN_PERIOD = 10.0  # [s]
DIAGNOSTICS_PERIOD = 2.0  # [s]
HEADER_TYPE = 'std_msgs/Header'
_COMPRESSION_ALIASES = {'none': ''}  # rosbag2's spelling -> BagWriter's


class RecorderStartupError(VgmError):
    """The output location is unusable; the message says which and why."""


def default_bag_name(now=None):
    """``rosbag2_YYYY_MM_DD-HH_MM_SS`` in local time, the name ``ros2 bag record`` picks."""
    return time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S', time.localtime(now))


def _plain_directory_name(name):
    """A reason if ``name`` is not usable as one directory name, else None."""
    if '/' in name or name in ('.', '..'):
        return f'must be a plain directory name, got {name!r}'
    return None


def _duration_dict(duration):
    nanoseconds = duration.nanoseconds
    return {'sec': nanoseconds // 1_000_000_000, 'nsec': nanoseconds % 1_000_000_000}


def qos_to_dict(qos):
    """An rclpy ``QoSProfile`` as the offered-profile dict stored in the bag.

    Policy names are rmw's (``keep_last``, ``transient_local``, ``unknown``...: the enum names
    in lower case); an infinite duration becomes ``{sec: 9223372036, nsec: 854775807}`` as in
    a bag recorded by rosbag2.
    """
    return qos_profile(
        history=qos.history.name.lower(),
        depth=qos.depth,
        reliability=qos.reliability.name.lower(),
        durability=qos.durability.name.lower(),
        deadline=_duration_dict(qos.deadline),
        lifespan=_duration_dict(qos.lifespan),
        liveliness=qos.liveliness.name.lower(),
        liveliness_lease_duration=_duration_dict(qos.liveliness_lease_duration),
        avoid_ros_namespace_conventions=qos.avoid_ros_namespace_conventions,
    )


PARAMETERS = [
    Param(
        'bag_name',
        '',
        'Bag directory name; empty = rosbag2_YYYY_MM_DD-HH_MM_SS '
        '(local time). Must not exist yet.',
        check=_plain_directory_name,
        read_only=True,
    ),
    Param(
        'output_dir',
        'bags',
        'Directory the bag directory is created in (relative to the working directory).',
        read_only=True,
    ),
    *topic_selection_params('record', 'recorded', 0.1, ', e.g. [/rosout]'),
    Param(
        'flush_period',
        1.0,
        '[s] The chunk being filled is written at least this '
        'often (bounds what a crash loses); 0 = only when full (768 KiB).',
        range=(0.0, 3600.0),
        read_only=True,
    ),
    Param(
        'max_file_size',
        0,
        '[bytes] Split to <bag_name>_<n+1>.mcap once a file reaches this size; 0 = never.',
        range=(0, 2**62),
        read_only=True,
    ),
    Param(
        'compression',
        'none',
        'Chunk compression of the MCAP files: none '
        '(rosbag2\'s default; "" says the same), zstd or lz4 (mcap\'s chunk '
        'compression: every MCAP reader decompresses it).',
        choices=('none', '', 'zstd', 'lz4'),
        read_only=True,
    ),
    Param(
        'max_cache_size',
        100 * 1024 * 1024,
        '[bytes] Messages waiting to be written; '
        'beyond this the oldest are dropped (counted). 0 = unbounded.',
        range=(0, 2**62),
        read_only=True,
    ),
]


class RecorderNode(GraphNode):
    """Discovers topics, subscribes to them raw and writes them to a bag.

    For ``vgm_common.node_main.run_node``: ``exit_requested`` is set when writing fails,
    ``drain()``, ``close()`` and ``exit_status`` (1 once writing failed).

    Raises:
        ParameterError: invalid parameter value.
        RecorderStartupError: the bag cannot be created.
    """

    node_name = 'recorder'

    def __init__(self, **kwargs):
        super().__init__(PARAMETERS, **kwargs)
        # None can change while recording.
        self._discovery = TopicDiscovery(self, self.params, 'recording')
        self._use_sim_time = self.get_parameter('use_sim_time').value
        self.bag_path = os.path.join(
            self.params.output_dir or '.', self.params.bag_name or default_bag_name()
        )
        try:
            bag = BagWriter(
                self.bag_path,
                max_file_size=self.params.max_file_size,
                compression=_COMPRESSION_ALIASES.get(
                    self.params.compression, self.params.compression
                ),
            )
        except BagError as error:
            raise RecorderStartupError(str(error)) from None
        self.exit_requested = threading.Event()
        self._recording = BagRecording(
            bag, self.params.max_cache_size, self.params.flush_period, self._on_write_failure
        )
        self._recorded = {}  # topic -> subscription
        self._mixed_types = set()  # recorded topics that gained a publisher of another type
        self._last_message_time = time.monotonic()  # [s] for drained()
        self._discovery_timer = self.create_timer(self.params.discovery_period, self._discover)
        self._diagnostics_timer = self.create_timer(DIAGNOSTICS_PERIOD, self._publish_status)
        wanted, excluded = self._discovery.wanted_topics, self._discovery.excluded
        scope = 'topics ' + ', '.join(sorted(wanted)) if wanted else 'all topics'
        if excluded:
            scope += '; excluding ' + ', '.join(sorted(excluded))
        self.get_logger().info(f'recording to {self.bag_path} ({scope})')
        self._discover()

    @property
    def exit_status(self):
        """The process exit status: 1 once writing to the bag failed, else 0."""
        return 0 if self._recording.write_error is None else 1

    # -- discovery (executor thread) -----------------------------------------------------

    def _discover(self):
        if self._recording.closed:
            return
        for topic in self._discovery.poll(self._recorded, self._check_types):
            self._subscribe(topic)

    def _check_types(self, name, types):
        if len(types) > 1 and name not in self._mixed_types:
            # Recorded with its first type; the others' messages cannot be.
            self._mixed_types.add(name)
            self.diagnostics.reject(
                name,
                f'now published with several types {types}: '
                f'only {self._recording.bag.topic_type(name)} is recorded',
            )

    def _subscribe(self, topic):
        offered = [qos_to_dict(p.qos_profile) for p in topic.publishers]
        self._recording.add_topic(topic.name, topic.type_name, offered)
        fields = topic.message_type.get_fields_and_field_types()
        has_header = next(iter(fields.values()), None) == HEADER_TYPE
        qos = subscription_qos(p.qos_profile for p in topic.publishers)

        def on_message(data: bytes, info: dict[str, int]) -> None:
            self._on_message(topic.name, has_header, data, info)

        # rclpy passes the message info to a callback that takes two arguments (it inspects
        # the signature), though it annotates the callback Callable[[message], None].
        self._recorded[topic.name] = self.create_subscription(
            topic.message_type,
            topic.name,
            on_message,  # type: ignore[arg-type]
            qos,
            raw=True,
        )
        self.get_logger().info(
            f'recording {topic.name} [{topic.type_name}] ({qos.reliability.name.lower()}, '
            f'{qos.durability.name.lower()})'
        )

    def _on_message(self, topic, stamped, data, info):
        self._last_message_time = time.monotonic()
        if self._use_sim_time or not info.get('received_timestamp'):
            log_time_ns = self.get_clock().now().nanoseconds
        else:
            log_time_ns = info['received_timestamp']
        publish_time_ns = (
            (header_stamp_ns(data) if stamped else None)
            or info.get('source_timestamp')
            or log_time_ns
        )
        self._recording.put(topic, data, log_time_ns, publish_time_ns)

    def _on_write_failure(self, error):  # writer thread; the recording has stopped
        self.get_logger().error(f'writing {self.bag_path} failed: {error}')
        self.exit_requested.set()

    # -- diagnostics (executor thread, and close) ------------------------------------------

    def _publish_status(self):
        # The counts are ints the writer thread updates: read without the bag lock, which
        # it holds while writing a whole batch.
        recording = self._recording
        topics, dropped = recording.topics, recording.dropped
        if recording.write_error is not None:
            level, message = 'error', f'writing failed: {recording.write_error}'
        else:
            level = 'warn' if sum(dropped.values()) or self._discovery.skipped else 'ok'
            message = 'closed' if recording.closed else 'recording'
        values = {
            'bag': self.bag_path,
            'topics recorded': len(topics),
            'messages': sum(t.message_count for t in topics),
            'dropped': sum(dropped.values()),
            'bytes written': recording.bytes_written,
        }
        for topic in topics:
            values[topic.name] = f'{topic.message_count}' + (
                f' ({dropped[topic.name]} dropped)' if dropped.get(topic.name) else ''
            )
        if self._discovery.skipped:
            values['not recorded'] = ', '.join(sorted(self._discovery.skipped))
        self.diagnostics.publish('bag', level, message, values)

    # -- shutdown ------------------------------------------------------------------------

    def stop_discovery(self):
        """Subscribe to no further topics."""
        self._discovery_timer.cancel()

    def drain(self):
        """Called by run_node once stopping: subscribe to no further topics, but go on
        taking the messages the middleware delivered (see ``drained``), at most the
        returned time [s]."""
        self.stop_discovery()
        self._last_message_time = time.monotonic()
        return MAX_DRAIN_PERIOD

    def drained(self):
        """True once no message arrived for QUIET_PERIOD: the backlog is recorded."""
        return time.monotonic() - self._last_message_time > QUIET_PERIOD

    def close(self):
        """Stop recording, write what is queued, close the bag and log the counts.
        Idempotent; safe after the context was shut down."""
        if self._recording.closed:
            return
        self.stop_discovery()
        self._diagnostics_timer.cancel()
        for subscription in self._recorded.values():
            self.destroy_subscription(subscription)
        error = self._recording.close()
        if error is not None:
            self.get_logger().error(f'closing {self.bag_path} failed: {error}')
        if self.context.ok():
            self._publish_status()
        if error is not None:
            return
        topics = self._recording.topics
        self.get_logger().info(
            f'closed {self.bag_path}: {self._recording.bag.message_count} messages on '
            f'{len(topics)} topics'
        )
        for topic in topics:
            dropped = self._recording.dropped.get(topic.name, 0)
            self.get_logger().info(
                f'  {topic.name}: {topic.message_count}'
                + (f' ({dropped} dropped: writer too slow)' if dropped else '')
            )
        never_seen = sorted(self._discovery.wanted_topics - {t.name for t in topics})
        if never_seen:
            self.get_logger().warning(f'never published, not recorded: {", ".join(never_seen)}')


def main(args=None):
    """Run the recorder until SIGINT/SIGTERM; returns the exit status: 0 = bag closed,
    1 = writing failed (what reached the disk is kept), 2 = unusable parameter or output
    location at start-up (one log line)."""
    return run_node(RecorderNode, args)


if __name__ == '__main__':
    sys.exit(main())
