"""``live_view``: the graph's topics served to Foxglove over its WebSocket protocol, as
ROS users get them from foxglove_bridge.

The server is the ``foxglove-sdk`` package's (subprotocol ``foxglove.sdk.v1``, the one
foxglove_bridge 3.x speaks). Every topic the graph publishes (or the chosen ``topics``,
less ``exclude``; found while running, as the recorder finds them) is advertised as a
channel with message encoding ``cdr`` and its ROS 2 schema (``ros2msg``, the full
concatenated definition, as the bags carry it). Subscriptions are raw: the serialized
CDR a publisher sent is forwarded unchanged, so an image costs one copy, no decoding.

A topic is subscribed in ROS only while some client subscribes to its channel (as
foxglove_bridge does): what nobody watches costs the graph nothing. Latched topics
(calibration, poses, waypoints) are subscribed transient-local, so a viewer that
connects late still gets their value (the last one is also kept for a second viewer).

Foxglove's 3D panel places things by frame transforms; tf2_msgs is not in the pip
wheels, so ``/tf`` carries foxglove's own ``FrameTransforms`` schema: base_link to each
camera's optical frame (from calib_node's latched poses, sent again every
``CAMERA_TRANSFORM_PERIOD`` so a late viewer has them) and base_link to ``tool0`` (from
each ``/tool_pose``).

A slow viewer never slows the graph: the subscription callbacks only hand the bytes to
the server, which queues at most ``message_backlog_size`` messages per client and drops
the oldest beyond that (inside foxglove-sdk, which does not report how many).
/diagnostics, every ``DIAGNOSTICS_PERIOD``: the URL, clients, channels, messages
forwarded per topic, transforms sent and rejected inputs (among them a served topic that
gained a publisher of another type: its channel keeps its first type).
"""

import sys
from functools import partial
from typing import Any

import foxglove
from foxglove.channels import FrameTransformsChannel
from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Timestamp, Vector3
from foxglove.websocket import ChannelView, Client, ServerListener
from geometry_msgs.msg import PoseStamped
from rclpy.qos import DurabilityPolicy
from rclpy.subscription import Subscription

from bag_tools.topic_discovery import (
    DiscoveredTopic,
    TopicDiscovery,
    subscription_qos,
    topic_selection_params,
)
from live_view.channels import ChannelTable, Forwarded, ServerSettings
from vgm_common.conversions import pose_to_matrix
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import (
    BASE_FRAME,
    OPTICAL_FRAMES,
    POSE_TOPICS,
    TOOL_FRAME,
    TOOL_POSE_TOPIC,
    TRANSFORMS_TOPIC,
)

CAMERA_TRANSFORM_PERIOD = 1.0  # [s]
DIAGNOSTICS_PERIOD = 2.0  # [s]


class LiveViewStartupError(VgmError):
    """The server cannot listen where asked (address in use, not an address of this
    machine)."""


def frame_transform(pose_stamped: PoseStamped, child_frame_id: str) -> FrameTransform:
    """foxglove ``FrameTransform`` of ``child_frame_id`` in the pose's frame.

    Raises:
        InvalidInput: no frame, or a pose with non-finite values or a non-unit quaternion.
    """
    if not pose_stamped.header.frame_id:
        raise InvalidInput('pose has no header.frame_id', key='frame_id')
    pose_to_matrix(pose_stamped.pose)  # validates
    p, q = pose_stamped.pose.position, pose_stamped.pose.orientation
    stamp = pose_stamped.header.stamp
    return FrameTransform(
        timestamp=Timestamp(sec=stamp.sec, nsec=stamp.nanosec),
        parent_frame_id=pose_stamped.header.frame_id,
        child_frame_id=child_frame_id,
        translation=Vector3(x=p.x, y=p.y, z=p.z),
        rotation=Quaternion(x=q.x, y=q.y, z=q.z, w=q.w),
    )


class _Listener(ServerListener):
    """foxglove-sdk's ServerListener: called on the server's threads (the callbacks not
    defined here are the protocol's no-ops)."""

    def __init__(self, live_view: 'LiveViewNode') -> None:
        self._live_view = live_view

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self._live_view.client_subscribed(client.id, channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self._live_view.client_unsubscribed(client.id, channel.topic)


SERVER = ConfigParams(ServerSettings)
PARAMETERS = [*SERVER.declarations(), *topic_selection_params('serve', 'served', 0.5)]


class LiveViewNode(GraphNode):
    """Discovers topics, subscribes to them raw and forwards them to the Foxglove server
    (a ChannelTable keeps what is served, to whom).

    Raises:
        ParameterError: invalid parameter value.
        LiveViewStartupError: the server cannot listen on ``address``:``port``.
    """

    node_name = 'live_view'

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(PARAMETERS, **kwargs)
        settings = SERVER.build(self.params)
        self._backlog = settings.message_backlog_size
        self._discovery = TopicDiscovery(self, self.params, 'serving')
        self._table = ChannelTable()
        self._wake = self.create_guard_condition(self._update_subscriptions)
        try:
            self._server = foxglove.start_server(
                name='vgm live_view',
                host=settings.address,
                port=settings.port,
                # No Capability.Time: the app then times messages by their log time
                # (the receive time here), as with foxglove_bridge on wall-clock time.
                server_listener=_Listener(self),
                supported_encodings=['cdr'],
                message_backlog_size=settings.message_backlog_size,
            )
        except Exception as error:  # noqa: BLE001 -- the SDK raises a bare RuntimeError
            raise LiveViewStartupError(
                f'cannot serve on {settings.address}:{settings.port}: {error}'
            ) from None
        self.url = f'ws://{settings.address}:{self._server.port}'
        self._transforms = FrameTransformsChannel(TRANSFORMS_TOPIC)
        for name, topic in POSE_TOPICS.items():
            self.create_subscription(
                PoseStamped,
                topic,
                partial(self._on_camera_pose, topic, OPTICAL_FRAMES[name]),
                LATCHED_QOS,
            )
        self.create_subscription(PoseStamped, TOOL_POSE_TOPIC, self._on_tool_pose, DEFAULT_QOS)
        self.create_timer(self.params.discovery_period, self._discover)
        self.create_timer(CAMERA_TRANSFORM_PERIOD, self._send_camera_transforms)
        self.create_timer(DIAGNOSTICS_PERIOD, self._publish_status)
        self.get_logger().info(
            f'serving the graph to Foxglove at {self.url} (open Foxglove, "Open connection", '
            f'Foxglove WebSocket, {self.url})'
        )
        self._discover()

    # -- topics (executor thread) ------------------------------------------------------

    def _discover(self) -> None:
        for topic in self._discovery.poll(self._table, self._check_types):
            self._advertise(topic)

    def _check_types(self, name: str, types: list[str]) -> None:
        reason = self._table.new_second_type(name, types)
        if reason:  # said once per topic, as the recorder does
            self.diagnostics.reject(name, reason)

    def _advertise(self, topic: DiscoveredTopic) -> None:
        encoding, text = topic.definition
        channel = foxglove.Channel(
            topic.name,
            message_encoding='cdr',
            schema=foxglove.Schema(name=topic.type_name, encoding=encoding, data=text.encode()),
        )
        qos = subscription_qos(p.qos_profile for p in topic.publishers)
        latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        self._table.add(
            topic.name, Forwarded(channel, topic.type_name, topic.message_type, qos, latched)
        )
        self.get_logger().info(f'serving {topic.name} [{topic.type_name}]')

    def _update_subscriptions(self) -> None:
        """Executor thread, woken by the server's threads."""
        self._table.update_subscriptions(self._subscribe, self.destroy_subscription)

    def _subscribe(self, topic: str, forwarded: Forwarded) -> Subscription:
        return self.create_subscription(
            forwarded.message_type,
            topic,
            partial(self._on_message, forwarded),
            forwarded.qos,
            raw=True,
        )

    def _on_message(self, forwarded: Forwarded, data: bytes, info: dict[str, int]) -> None:
        self._table.forward(forwarded, data, info.get('received_timestamp', 0))

    # -- clients (server threads) --------------------------------------------------------

    def client_subscribed(self, client_id: int, topic: str) -> None:
        """Client ``client_id`` subscribed to ``topic``: wake the executor to subscribe it
        in ROS; ``/tf`` gets the camera transforms at once. Server thread."""
        self._table.client_subscribed(client_id, topic)
        if topic == TRANSFORMS_TOPIC:
            self._send_camera_transforms()
        self._wake.trigger()

    def client_unsubscribed(self, client_id: int, topic: str) -> None:
        """Client ``client_id`` unsubscribed from ``topic``: wake the executor to drop the
        ROS subscription nobody watches any more. Server thread."""
        self._table.client_unsubscribed(client_id, topic)
        self._wake.trigger()

    # -- frame transforms ----------------------------------------------------------------

    def _on_camera_pose(self, topic: str, frame: str, msg: PoseStamped) -> None:
        try:
            if msg.header.frame_id != BASE_FRAME:
                raise InvalidInput(
                    f'camera pose must be in {BASE_FRAME}, got {msg.header.frame_id!r}',
                    key='frame_id',
                )
            transform = frame_transform(msg, frame)
        except InvalidInput as error:
            self.diagnostics.reject(topic, error)
            return
        self._table.set_camera_transform(frame, transform)
        self._send_camera_transforms()

    def _send_camera_transforms(self) -> None:
        transforms = self._table.camera_transforms()
        if transforms:
            self._transforms.log(FrameTransforms(transforms=transforms))
            self._table.transforms_sent += len(transforms)

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        if not self._transforms.has_sinks():  # nobody watches /tf
            return
        try:
            transform = frame_transform(msg, TOOL_FRAME)
        except InvalidInput as error:
            self.diagnostics.reject(TOOL_POSE_TOPIC, error)
            return
        self._transforms.log(FrameTransforms(transforms=[transform]))
        self._table.transforms_sent += 1

    # -- diagnostics and shutdown ------------------------------------------------------

    def _publish_status(self) -> None:
        rejected = sum(self.diagnostics.rejected.values())
        status = self._table.status(self.url, self._backlog, self._discovery.skipped, rejected)
        self.diagnostics.publish('server', *status)

    def close(self) -> None:
        """Stop the server (clients see the connection close)."""
        self._server.stop()


def main(args: list[str] | None = None) -> int:
    """Run live_view until SIGINT/SIGTERM; exit status 2 when it cannot serve (one line)."""
    return run_node(LiveViewNode, args)


if __name__ == '__main__':
    sys.exit(main())
