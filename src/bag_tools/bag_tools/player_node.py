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

By default ``/rosout`` and ``/parameter_events`` are recorded but not replayed (parameter
``exclude``): old log lines and parameter changes are not inputs of any node, and would
reappear on the live graph as if they were happening now.

A missing or invalid bag or parameter is reported in one log line and the process exits with
status 2 (the project's status for unusable start-up input, as ``vgm_common.node_tools``).
"""
import signal
import sys
import threading
import time

import rclpy
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from bag_tools.bag_writer import BagError, BagReader
from bag_tools.message_definitions import DefinitionNotFoundError, type_hash
from bag_tools.recorder_node import import_message_type
from vgm_common.node_tools import init_rclpy
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS

NODE_NAME = 'player'
ACK_TIMEOUT = 2.0  # [s] at most this long waiting for subscribers to acknowledge at the end
_MAX_SLEEP = 0.05  # [s] sleep slices, so a rate change or a stop takes effect promptly
MATCH_SETTLE = 0.2  # [s] after every publisher has matched a subscriber, before playing


class PlayerStartupError(Exception):
    """The bag or a parameter is unusable; the message says which and why."""


MIN_RATE, MAX_RATE = 1e-3, 1e3  # playback speed factors accepted


def rate_value(value):
    """``(rate, '')`` if ``value`` is a usable playback rate (ints accepted), else
    ``(None, reason)``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None, f'parameter rate must be a number, got {value!r}'
    if not MIN_RATE <= value <= MAX_RATE:
        return None, f'parameter rate must be in [{MIN_RATE:g}, {MAX_RATE:g}], got {value}'
    return float(value), ''


def is_latched(topic_info):
    """True if every recorded publisher of the topic offered transient-local durability."""
    profiles = topic_info.offered_qos_profiles
    return bool(profiles) and all(p.get('durability') == 'transient_local' for p in profiles)


class PlayerNode(Node):
    """Publishes the messages of one bag with the recorded timing.

    ``finished`` is set once playback ended (or failed); ``published`` counts per topic.

    Raises:
        PlayerStartupError: no/invalid bag, invalid parameter, or nothing to play.
    """

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self._declare_parameters()
        settings = self._read_settings()
        self.exit_when_done = settings['exit_when_done']
        self._loop = settings['loop']
        self._wait_for_subscribers = settings['wait_for_subscribers']
        try:
            self._reader = BagReader(settings['bag'])
        except BagError as error:
            raise PlayerStartupError(f'cannot play {settings["bag"]!r}: {error}') from None
        self._topic_publishers = self._create_publishers(settings['topics'], settings['exclude'])
        self.published = {name: 0 for name in self._topic_publishers}
        self.finished = threading.Event()
        self.error = None
        self._stop = threading.Event()
        # Playback clock: bag time _anchor_bag [ns] is played at monotonic _anchor_wall [s].
        self._clock_lock = threading.Lock()
        self._rate = settings['rate']
        self._anchor_wall = None
        self._anchor_bag = None
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._thread = threading.Thread(target=self._run, name='playback', daemon=True)
        self._thread.start()

    # -- parameters --------------------------------------------------------------------

    def _declare_parameters(self):
        def describe(text, read_only=True, **extra):
            return ParameterDescriptor(description=text, read_only=read_only, **extra)

        self.declare_parameter('bag', '', describe(
            'Path of the bag directory (the one holding metadata.yaml).'))
        self.declare_parameter('rate', 1.0, describe(
            'Playback speed factor (2 = twice as fast); may be changed while playing.',
            read_only=False, dynamic_typing=True,
            floating_point_range=[FloatingPointRange(from_value=MIN_RATE, to_value=MAX_RATE)]))
        self.declare_parameter('loop', False, describe('Play the bag again and again.'))
        self.declare_parameter('topics', Parameter.Type.STRING_ARRAY, describe(
            'Topics to play (exact names); empty = every recorded topic.'))
        self.declare_parameter('exclude', ['/rosout', '/parameter_events'], describe(
            'Recorded topics not to play (exact names); [] = none.'))
        self.declare_parameter('exit_when_done', True, describe(
            'Exit once the bag was played; false keeps latched topics available.'))
        self.declare_parameter('wait_for_subscribers', 5.0, describe(
            '[s] Before playing, wait at most this long for every topic to have a '
            'subscriber, so the first messages are not lost to discovery; 0 = do not wait.',
            dynamic_typing=True,
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=3600.0)]))

    def _value(self, name):
        """A parameter's value; None while unset (an empty list given on the command line)."""
        try:
            return self.get_parameter(name).value
        except ParameterUninitializedException:
            return None

    def _read_settings(self):
        bag = self.get_parameter('bag').value
        if not bag:
            raise PlayerStartupError('parameter bag is required: the bag directory to play')
        rate, reason = rate_value(self.get_parameter('rate').value)
        if rate is None:
            raise PlayerStartupError(reason)
        wait = self.get_parameter('wait_for_subscribers').value
        if isinstance(wait, bool) or not isinstance(wait, (int, float)) or wait < 0:
            raise PlayerStartupError(
                f'parameter wait_for_subscribers must be a number >= 0, got {wait!r}')
        return {
            'bag': bag,
            'rate': rate,
            'loop': self.get_parameter('loop').value,
            'topics': self._value('topics') or [],  # `topics:=[]` arrives unset
            'exclude': self._value('exclude') or [],
            'exit_when_done': self.get_parameter('exit_when_done').value,
            'wait_for_subscribers': float(wait),
        }

    def _on_set_parameters(self, parameters):
        for parameter in parameters:
            if parameter.name == 'rate':
                rate, reason = rate_value(parameter.value)
                if rate is None:
                    return SetParametersResult(successful=False, reason=reason)
        for parameter in parameters:
            if parameter.name == 'rate':
                self._set_rate(float(parameter.value))
        return SetParametersResult(successful=True)

    # -- publishers --------------------------------------------------------------------

    def _create_publishers(self, wanted, excluded):
        recorded = {t.name: t for t in self._reader.topics}
        for name in wanted:
            if name not in recorded:
                self.get_logger().warning(f'topic {name} is not in the bag')
        names = [n for n in recorded
                 if (not wanted or n in wanted) and n not in excluded]
        publishers = {}
        for name in names:
            info = recorded[name]
            try:
                message_type = import_message_type(info.type)
            except (ImportError, AttributeError, ValueError) as error:
                self.get_logger().warning(
                    f'not playing {name}: type {info.type} is not installed ({error})')
                continue
            try:
                local_hash = type_hash(info.type)
            except DefinitionNotFoundError:
                local_hash = ''
            if info.type_description_hash and local_hash and \
                    info.type_description_hash != local_hash:
                self.get_logger().warning(
                    f'{name}: recorded {info.type} differs from the installed definition '
                    f'({info.type_description_hash} != {local_hash}); playing the bytes as is')
            latched = is_latched(info)
            publishers[name] = self.create_publisher(
                message_type, name, LATCHED_QOS if latched else DEFAULT_QOS)
            self.get_logger().info(
                f'playing {name} [{info.type}] {info.message_count} messages'
                + (' (latched)' if latched else ''))
        if not publishers:
            raise PlayerStartupError(f'nothing to play in {self._reader.path}: no recorded '
                                     'topic matches topics/exclude')
        return publishers

    # -- playback (playback thread) --------------------------------------------------------

    def _set_rate(self, rate):
        with self._clock_lock:
            if self._anchor_wall is not None:
                # Re-anchor at the current bag time so a rate change does not jump.
                now = time.monotonic()
                self._anchor_bag += int((now - self._anchor_wall) * self._rate * 1e9)
                self._anchor_wall = now
            self._rate = rate

    def _wall_time(self, log_time_ns):
        with self._clock_lock:
            return self._anchor_wall + (log_time_ns - self._anchor_bag) / 1e9 / self._rate

    def _sleep_until(self, log_time_ns):
        """Sleep until the wall time of ``log_time_ns``; False if stopped meanwhile."""
        while True:
            remaining = self._wall_time(log_time_ns) - time.monotonic()
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
        lonely = sorted(name for name, publisher in self._topic_publishers.items()
                        if publisher.get_subscription_count() == 0)
        self.get_logger().info(
            f'no subscriber after {self._wait_for_subscribers:g} s on {", ".join(lonely)}; '
            'playing anyway')

    def _play_once(self):
        """Play the bag once; False if stopped or there was nothing to play."""
        first = True
        for message in self._reader.messages(self._topic_publishers):
            if first:
                with self._clock_lock:
                    self._anchor_wall = time.monotonic()
                    self._anchor_bag = message.log_time
                first = False
            if not self._sleep_until(message.log_time):
                return False
            self._topic_publishers[message.topic].publish(bytes(message.data))
            self.published[message.topic] += 1
        return not first

    def _run(self):
        try:
            self._await_subscribers()
            started = time.monotonic()
            while not self._stop.is_set():
                if not self._play_once() or not self._loop:
                    break
            self.get_logger().info(
                f'played {sum(self.published.values())} messages in '
                f'{time.monotonic() - started:.2f} s')
        except (BagError, OSError, ValueError) as error:
            self.error = error
            self.get_logger().error(f'playing {self._reader.path} failed: {error}')
        finally:
            self.finished.set()

    # -- shutdown ------------------------------------------------------------------------

    def wait_for_acknowledgements(self, timeout=ACK_TIMEOUT):
        """Wait (at most ``timeout`` [s] overall) until subscribers acknowledged every
        published message, so exiting does not cut the last ones off."""
        deadline = time.monotonic() + timeout
        for publisher in self._topic_publishers.values():
            remaining = max(0.0, deadline - time.monotonic())
            publisher.wait_for_all_acked(Duration(seconds=remaining))

    def stop(self):
        """Stop playback and wait for the playback thread. Idempotent."""
        self._stop.set()
        self._thread.join()


def main(args=None):
    """Play the bag; returns the exit status: 0 = played (or stopped by SIGINT/SIGTERM),
    1 = the bag failed while reading, 2 = unusable bag or parameter at start-up."""
    init_rclpy(args)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda _signum, _frame: stop.set())
    node = None
    status = 0
    try:
        node = PlayerNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok() and \
                not (node.exit_when_done and node.finished.is_set()):
            executor.spin_once(timeout_sec=0.1)
        if node.error is not None:
            status = 1
        elif node.finished.is_set() and not stop.is_set():
            node.wait_for_acknowledgements()
    except (PlayerStartupError, ParameterException) as error:
        rclpy.logging.get_logger(NODE_NAME).error(str(error))
        status = 2
    except ExternalShutdownException:
        pass
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
