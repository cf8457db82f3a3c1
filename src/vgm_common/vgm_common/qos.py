"""The two QoS profiles of INTERFACES.md, chosen on purpose, in one place.

``DEFAULT_QOS``: reliable, volatile, keep-last 10 (streams: images, joint states, ...).
``LATCHED_QOS``: reliable, transient-local, keep-last 1 (calibrations, waypoints):
late joiners receive the last value.
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
