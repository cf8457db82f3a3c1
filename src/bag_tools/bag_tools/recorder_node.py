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
published before the recorder started is recorded), else volatile; keep last 100 so a burst
is not dropped. The publishers' offered profiles when the topic is first subscribed are
stored in the bag (both ``metadata.yaml`` and the MCAP channel, which must agree).

Times: log time = the middleware's receive time (the node clock under ``use_sim_time``);
publish time = the message's ``header.stamp`` when its first field is a ``std_msgs/Header``
with a non-zero stamp, else the publisher's send time, else the receive time. (rosbag2
itself always stores the send time.)

The subscription callbacks only time-stamp and enqueue; a writer thread drains the queue
into the bag, and flushes the chunk being filled every ``flush_period`` so a crash loses at
most that long of data. The queue holds at most ``max_cache_size`` bytes; beyond that the
oldest messages are dropped and counted.
"""
import collections
import importlib
import os
import signal
import sys
import threading
import time

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from bag_tools.bag_writer import BagError, BagWriter, header_stamp_ns, qos_profile
from bag_tools.message_definitions import DefinitionNotFoundError, definition
from vgm_common.node_tools import init_rclpy

NODE_NAME = 'recorder'
SUBSCRIPTION_DEPTH = 100  # keep-last depth of every recording subscription
DRAIN_PERIOD = 0.25  # [s] after a stop request, keep taking already delivered messages
HEADER_TYPE = 'std_msgs/Header'


class RecorderStartupError(Exception):
    """A parameter or the output location is unusable; the message says which and why."""


def default_bag_name(now=None):
    """``rosbag2_YYYY_MM_DD-HH_MM_SS`` in local time, the name ``ros2 bag record`` picks."""
    return time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S', time.localtime(now))


def import_message_type(type_name):
    """The Python class of ``pkg/msg/Type``. Raises ImportError/AttributeError if absent."""
    package, interface, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.{interface}'), name)


def topic_is_hidden(name):
    """rclpy's rule (and rosbag2's): any name token starting with ``_``."""
    return any(token.startswith('_') for token in name.split('/'))


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
        history=qos.history.name.lower(), depth=qos.depth,
        reliability=qos.reliability.name.lower(), durability=qos.durability.name.lower(),
        deadline=_duration_dict(qos.deadline), lifespan=_duration_dict(qos.lifespan),
        liveliness=qos.liveliness.name.lower(),
        liveliness_lease_duration=_duration_dict(qos.liveliness_lease_duration),
        avoid_ros_namespace_conventions=qos.avoid_ros_namespace_conventions)


def subscription_qos(publisher_qos_profiles):
    """The QoS that receives from all the given publishers (rosbag2's adapt_request_to_offers).

    Latched values are only received if every publisher is transient local (a transient
    local subscription does not match a volatile publisher).
    """
    profiles = list(publisher_qos_profiles)
    reliable = bool(profiles) and all(
        p.reliability == ReliabilityPolicy.RELIABLE for p in profiles)
    transient_local = bool(profiles) and all(
        p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in profiles)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=SUBSCRIPTION_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if transient_local
                    else DurabilityPolicy.VOLATILE))


class _MessageQueue:
    """FIFO of (topic, data, log_time_ns, publish_time_ns) bounded in bytes; when full, the
    oldest messages are dropped and counted per topic. Thread-safe."""

    def __init__(self, max_bytes):
        self._items = collections.deque()
        self._bytes = 0
        self._max_bytes = max_bytes
        self._condition = threading.Condition()
        self._closed = False
        self.dropped = collections.Counter()

    def put(self, item):
        with self._condition:
            self._items.append(item)
            self._bytes += len(item[1])
            while self._max_bytes and self._bytes > self._max_bytes and len(self._items) > 1:
                old = self._items.popleft()
                self._bytes -= len(old[1])
                self.dropped[old[0]] += 1
            self._condition.notify()

    def take_all(self, timeout):
        """All queued items (possibly none after ``timeout`` [s]); None once closed and empty."""
        with self._condition:
            if not self._items and not self._closed:
                self._condition.wait(timeout)
            if not self._items and self._closed:
                return None
            items = list(self._items)
            self._items.clear()
            self._bytes = 0
            return items

    def close(self):
        with self._condition:
            self._closed = True
            self._condition.notify_all()


class RecorderNode(Node):
    """Discovers topics, subscribes to them raw and writes them to a bag.

    Raises:
        RecorderStartupError: invalid parameter value or the bag cannot be created.
    """

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self._declare_parameters()
        settings = self._read_settings()
        self._topics_wanted = set(settings['topics'])
        self._excluded = set(settings['exclude'])
        self._include_hidden = settings['include_hidden_topics']
        self._flush_period = settings['flush_period']  # [s]
        self._use_sim_time = self.get_parameter('use_sim_time').value
        self.bag_path = os.path.join(settings['output_dir'], settings['bag_name'])
        try:
            self._bag = BagWriter(self.bag_path, max_file_size=settings['max_file_size'])
        except BagError as error:
            raise RecorderStartupError(str(error)) from None
        self._bag_lock = threading.Lock()  # BagWriter is used by the executor and writer threads
        self._queue = _MessageQueue(settings['max_cache_size'])
        self._recorded = {}  # topic -> subscription
        self._skipped = set()  # topics warned about once and not recorded
        self.write_error = None
        self._writer_thread = threading.Thread(
            target=self._write_loop, name='bag_writer', daemon=True)
        self._writer_thread.start()
        self._closed = False
        self._discovery_timer = self.create_timer(settings['discovery_period'], self._discover)
        scope = ('topics ' + ', '.join(sorted(self._topics_wanted)) if self._topics_wanted
                 else 'all topics')
        if self._excluded:
            scope += '; excluding ' + ', '.join(sorted(self._excluded))
        self.get_logger().info(f'recording to {self.bag_path} ({scope})')
        self._discover()

    # -- parameters --------------------------------------------------------------------

    def _declare_parameters(self):
        def describe(text, **extra):
            return ParameterDescriptor(description=text, read_only=True, **extra)

        self.declare_parameter('bag_name', '', describe(
            'Bag directory name; empty = rosbag2_YYYY_MM_DD-HH_MM_SS (local time). '
            'Must not exist yet.'))
        self.declare_parameter('output_dir', 'bags', describe(
            'Directory the bag directory is created in (relative to the working directory).'))
        self.declare_parameter('topics', Parameter.Type.STRING_ARRAY, describe(
            'Topics to record (exact names); empty = every published topic.'))
        self.declare_parameter('exclude', Parameter.Type.STRING_ARRAY, describe(
            'Topics never recorded (exact names), e.g. [/rosout].'))
        self.declare_parameter('include_hidden_topics', False, describe(
            'Also record hidden topics (a name token starting with _).'))
        self.declare_parameter('discovery_period', 0.1, describe(
            '[s] How often the graph is polled for new topics.', dynamic_typing=True,
            floating_point_range=[FloatingPointRange(from_value=0.01, to_value=60.0)]))
        self.declare_parameter('flush_period', 1.0, describe(
            '[s] The chunk being filled is written at least this often (bounds what a crash '
            'loses); 0 = only when full (768 KiB).', dynamic_typing=True,
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=3600.0)]))
        self.declare_parameter('max_file_size', 0, describe(
            '[bytes] Split to <bag_name>_<n+1>.mcap once a file reaches this size; 0 = never.',
            integer_range=[IntegerRange(from_value=0, to_value=2**62)]))
        self.declare_parameter('max_cache_size', 100 * 1024 * 1024, describe(
            '[bytes] Messages waiting to be written; beyond this the oldest are dropped '
            '(counted). 0 = unbounded.',
            integer_range=[IntegerRange(from_value=0, to_value=2**62)]))

    def _value(self, name):
        """A parameter's value; None while unset (an empty list given on the command line)."""
        try:
            return self.get_parameter(name).value
        except ParameterUninitializedException:
            return None

    def _read_settings(self):
        def number(name, minimum, maximum):
            value = self.get_parameter(name).value
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise RecorderStartupError(
                    f'parameter {name} must be a number, got {value!r}')
            if not minimum <= value <= maximum:
                raise RecorderStartupError(
                    f'parameter {name} must be in [{minimum}, {maximum}], got {value}')
            return float(value)

        def names(name):
            value = self._value(name) or []  # `topics:=[]` arrives unset
            bad = [n for n in value if not n.startswith('/')]
            if bad:
                raise RecorderStartupError(
                    f'parameter {name} must hold absolute topic names, got {bad}')
            return value

        bag_name = self.get_parameter('bag_name').value or default_bag_name()
        if '/' in bag_name or bag_name in ('.', '..'):
            raise RecorderStartupError(
                f'parameter bag_name must be a plain directory name, got {bag_name!r}')
        return {
            'bag_name': bag_name,
            'output_dir': self.get_parameter('output_dir').value or '.',
            'topics': names('topics'),
            'exclude': names('exclude'),
            'include_hidden_topics': self.get_parameter('include_hidden_topics').value,
            'discovery_period': number('discovery_period', 0.01, 60.0),
            'flush_period': number('flush_period', 0.0, 3600.0),
            'max_file_size': self.get_parameter('max_file_size').value,
            'max_cache_size': self.get_parameter('max_cache_size').value,
        }

    # -- discovery (executor thread) -----------------------------------------------------

    def _wanted(self, name):
        if name in self._excluded:
            return False
        if self._topics_wanted:
            return name in self._topics_wanted
        return self._include_hidden or not topic_is_hidden(name)

    def _skip(self, name, reason):
        self._skipped.add(name)
        self.get_logger().warning(f'not recording {name}: {reason}')

    def _discover(self):
        if self._closed:
            return
        for name, types in self.get_topic_names_and_types():
            if name in self._recorded or name in self._skipped or not self._wanted(name):
                continue
            if len(types) != 1:
                self._skip(name, f'published with several types {types}')
                continue
            publishers = self.get_publishers_info_by_topic(name)
            if not publishers:
                continue  # only subscribed so far: nothing to record (as rosbag2)
            self._subscribe(name, types[0], publishers)

    def _subscribe(self, name, type_name, publishers):
        try:
            message_type = import_message_type(type_name)
            definition(type_name)
        except (ImportError, AttributeError, ValueError, DefinitionNotFoundError) as error:
            self._skip(name, f'type {type_name} is not installed ({error})')
            return
        offered = [qos_to_dict(p.qos_profile) for p in publishers]
        with self._bag_lock:
            self._bag.add_topic(name, type_name, offered)
        fields = message_type.get_fields_and_field_types()
        has_header = next(iter(fields.values()), None) == HEADER_TYPE
        qos = subscription_qos(p.qos_profile for p in publishers)
        self._recorded[name] = self.create_subscription(
            message_type, name,
            lambda data, info, topic=name, stamped=has_header:
                self._on_message(topic, stamped, data, info),
            qos, raw=True)
        self.get_logger().info(
            f'recording {name} [{type_name}] ({qos.reliability.name.lower()}, '
            f'{qos.durability.name.lower()})')

    def _on_message(self, topic, stamped, data, info):
        if self._use_sim_time or not info.get('received_timestamp'):
            log_time_ns = self.get_clock().now().nanoseconds
        else:
            log_time_ns = info['received_timestamp']
        publish_time_ns = (header_stamp_ns(data) if stamped else None) \
            or info.get('source_timestamp') or log_time_ns
        self._queue.put((topic, data, log_time_ns, publish_time_ns))

    # -- writing (writer thread) ---------------------------------------------------------

    def _write_loop(self):
        last_flush = time.monotonic()
        wait = self._flush_period if self._flush_period > 0 else 1.0
        while True:
            items = self._queue.take_all(timeout=wait)
            if items is None:
                return
            try:
                with self._bag_lock:
                    for topic, data, log_time_ns, publish_time_ns in items:
                        self._bag.write(topic, data, log_time_ns, publish_time_ns)
                    if self._flush_period > 0 and \
                            time.monotonic() - last_flush >= self._flush_period:
                        self._bag.flush()
                        last_flush = time.monotonic()
            except (OSError, BagError) as error:
                # Disk full or similar: stop recording, keep what is on disk, and tell main.
                self.write_error = error  # main stops spinning and closes
                self.get_logger().error(f'writing {self.bag_path} failed: {error}')
                self._queue.close()
                return

    # -- shutdown ------------------------------------------------------------------------

    def stop_discovery(self):
        """Subscribe to no further topics."""
        self._discovery_timer.cancel()

    def close(self):
        """Stop recording, write what is queued, close the bag and log the counts.
        Idempotent; safe after the context was shut down."""
        if self._closed:
            return
        self._closed = True
        self.stop_discovery()
        for subscription in self._recorded.values():
            self.destroy_subscription(subscription)
        self._queue.close()
        self._writer_thread.join()
        with self._bag_lock:
            try:
                self._bag.close()
            except (OSError, BagError) as error:
                self.write_error = self.write_error or error
                self.get_logger().error(f'closing {self.bag_path} failed: {error}')
                return
        topics = self._bag.topics
        self.get_logger().info(
            f'closed {self.bag_path}: {self._bag.message_count} messages on '
            f'{len(topics)} topics')
        for topic in topics:
            dropped = self._queue.dropped.get(topic.name, 0)
            self.get_logger().info(
                f'  {topic.name}: {topic.message_count}'
                + (f' ({dropped} dropped: writer too slow)' if dropped else ''))
        never_seen = sorted(self._topics_wanted - {t.name for t in topics})
        if never_seen:
            self.get_logger().warning(f'never published, not recorded: {", ".join(never_seen)}')


def main(args=None):
    """Run the recorder until SIGINT/SIGTERM; returns the exit status: 0 = bag closed,
    1 = writing failed (what reached the disk is kept), 2 = unusable parameter or output
    location at start-up (one log line)."""
    # Our own handlers, not rclpy's: rclpy's shut the context down at once, after which the
    # bag could still be closed but nothing could be logged to /rosout any more.
    init_rclpy(args)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda _signum, _frame: stop.set())
    node = None
    status = 0
    try:
        node = RecorderNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and node.write_error is None and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        # Messages the middleware delivered before the signal are still waiting to be taken:
        # record them too (no new topics meanwhile).
        node.stop_discovery()
        drain_until = time.monotonic() + DRAIN_PERIOD
        while node.write_error is None and rclpy.ok() and time.monotonic() < drain_until:
            executor.spin_once(timeout_sec=0.02)
    except (RecorderStartupError, ParameterException) as error:
        rclpy.logging.get_logger(NODE_NAME).error(str(error))
        status = 2
    except ExternalShutdownException:
        pass
    finally:
        if node is not None:
            node.close()
            if node.write_error is not None:
                status = 1
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
