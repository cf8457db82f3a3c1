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

import sys
import threading
from typing import Any

from rclpy.duration import Duration
from rclpy.qos import QoSProfile
from rclpy.subscription import Subscription

from bag_tools.bag_writer import QosProfileDict, qos_profile
from bag_tools.recorder import BagSettings, Recorder
from bag_tools.topic_discovery import (
    DiscoveredTopic,
    TopicDiscovery,
    subscription_qos,
    topic_selection_params,
)
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams

DIAGNOSTICS_PERIOD = 2.0  # [s]
HEADER_TYPE = 'std_msgs/Header'


def _duration_dict(duration: Duration) -> dict[str, int]:
    nanoseconds = duration.nanoseconds
    return {'sec': nanoseconds // 1_000_000_000, 'nsec': nanoseconds % 1_000_000_000}


def qos_to_dict(qos: QoSProfile) -> QosProfileDict:
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


BAG = ConfigParams(BagSettings)
PARAMETERS = [
    *BAG.declarations(),
    *topic_selection_params('record', 'recorded', 0.1, ', e.g. [/rosout]'),
]


class RecorderNode(GraphNode):
    """Discovers topics, subscribes to them raw and hands their messages to a Recorder.

    For ``vgm_common.node_main.run_node``: ``exit_requested`` is set when writing fails,
    ``drain()``, ``drained()``, ``close()`` and ``exit_status`` (1 once writing failed).

    Raises:
        ParameterError: invalid parameter value.
        RecorderStartupError: the bag cannot be created.
    """

    node_name = 'recorder'

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(PARAMETERS, **kwargs)
        # None can change while recording.
        self._discovery = TopicDiscovery(self, self.params, 'recording')
        self._use_sim_time = self.get_parameter('use_sim_time').value
        self.exit_requested = threading.Event()
        self._recorder = Recorder(
            BAG.build(self.params),
            self._on_write_failure,
            log_clock_ns=lambda: self.get_clock().now().nanoseconds,
        )
        self.bag_path = self._recorder.bag_path
        self._recording = self._recorder.recording
        self._recorded: dict[str, Subscription] = {}  # topic -> its subscription
        self._discovery_timer = self.create_timer(self.params.discovery_period, self._discover)
        self._diagnostics_timer = self.create_timer(DIAGNOSTICS_PERIOD, self._publish_status)
        wanted, excluded = self._discovery.wanted_topics, self._discovery.excluded
        scope = 'topics ' + ', '.join(sorted(wanted)) if wanted else 'all topics'
        if excluded:
            scope += '; excluding ' + ', '.join(sorted(excluded))
        self.get_logger().info(f'recording to {self.bag_path} ({scope})')
        self._discover()

    @property
    def exit_status(self) -> int:
        """The process exit status: 1 once writing to the bag failed, else 0."""
        return 0 if self._recording.write_error is None else 1

    # -- discovery (executor thread) -----------------------------------------------------

    def _discover(self) -> None:
        if self._recording.closed:
            return
        for topic in self._discovery.poll(self._recorded, self._check_types):
            self._subscribe(topic)

    def _check_types(self, name: str, types: list[str]) -> None:
        reason = self._recorder.new_second_type(name, types)
        if reason:  # recorded with its first type; the others' messages cannot be
            self.diagnostics.reject(name, reason)

    def _subscribe(self, topic: DiscoveredTopic) -> None:
        fields = topic.message_type.get_fields_and_field_types()
        self._recorder.add_topic(
            topic.name,
            topic.type_name,
            [qos_to_dict(p.qos_profile) for p in topic.publishers],
            stamped=next(iter(fields.values()), None) == HEADER_TYPE,
        )
        qos = subscription_qos(p.qos_profile for p in topic.publishers)

        def on_message(data: bytes, info: dict[str, int]) -> None:
            received_ns = 0 if self._use_sim_time else info.get('received_timestamp', 0)
            self._recorder.take(topic.name, data, received_ns, info.get('source_timestamp', 0))

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

    def _on_write_failure(
        self, error: Exception
    ) -> None:  # writer thread; the recording has stopped
        self.get_logger().error(f'writing {self.bag_path} failed: {error}')
        self.exit_requested.set()

    def _publish_status(self) -> None:
        self.diagnostics.publish('bag', *self._recorder.status(self._discovery.skipped))

    # -- shutdown ------------------------------------------------------------------------

    def stop_discovery(self) -> None:
        """Subscribe to no further topics."""
        self._discovery_timer.cancel()

    def drain(self) -> float:
        """Called by run_node once stopping: subscribe to no further topics, but go on
        taking the messages the middleware delivered (see ``drained``), at most the
        returned time [s]."""
        self.stop_discovery()
        return self._recorder.start_drain()

    def drained(self) -> bool:
        """True once no message arrived for a quiet period: the backlog is recorded."""
        return self._recorder.drained()

    def close(self) -> None:
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
        for line in self._recorder.counts():
            self.get_logger().info(line)
        never_seen = self._recorder.never_published(self._discovery.wanted_topics)
        if never_seen:
            self.get_logger().warning(f'never published, not recorded: {", ".join(never_seen)}')


def main(args: list[str] | None = None) -> int:
    """Run the recorder until SIGINT/SIGTERM; returns the exit status: 0 = bag closed,
    1 = writing failed (what reached the disk is kept), 2 = unusable parameter or output
    location at start-up (one log line)."""
    return run_node(RecorderNode, args)


if __name__ == '__main__':
    sys.exit(main())
