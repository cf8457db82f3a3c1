"""The two QoS profiles of INTERFACES.md, chosen on purpose, in one place.

``DEFAULT_QOS``: reliable, volatile, keep-last 10 (streams: images, joint states, ...).
``LATCHED_QOS``: reliable, transient-local, keep-last 1 (calibrations, waypoints):
late joiners receive the last value.
``NEWEST_QOS``: a subscriber's own depth for streams where each message replaces the
previous (commands, states): reliable, volatile, keep-last 1, compatible with
``DEFAULT_QOS`` publishers. A process that falls behind then acts on the newest message
instead of working through a backlog that only adds latency.
"""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

DEFAULT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

NEWEST_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
