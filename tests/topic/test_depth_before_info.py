"""Topic level, real processes: sfs_stereo_node publishes a frame's fused depth just
before its /depth/camera_info; curve_recon_node uses that first depth once its
camera_info comes, instead of rejecting it with a warning."""

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import CameraInfo, Image

from harness import executable
from vgm_common.conversions import make_header, numpy_to_image
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import DEPTH_INFO_TOPIC, DIAGNOSTICS_TOPIC, FUSED_DEPTH_TOPIC

WIDTH, HEIGHT, FOCAL_PX = 320, 240, 300.0
STAMP_NS = 5_000_000_000
FRAME = 'left_camera_optical_frame'


def test_a_depth_image_before_its_camera_info_is_used_once_the_info_comes(spawn, rclpy_node):
    depth_states = []  # the node's 'depth' status value, in order
    problems = []
    rclpy_node.create_subscription(
        DiagnosticArray, DIAGNOSTICS_TOPIC, lambda msg: _collect(msg, depth_states, problems), 10
    )
    depth_pub = rclpy_node.create_publisher(Image, FUSED_DEPTH_TOPIC, DEFAULT_QOS)
    info_pub = rclpy_node.create_publisher(CameraInfo, DEPTH_INFO_TOPIC, DEFAULT_QOS)
    node = spawn([executable('curve_recon_node')])
    rclpy_node.spin_until(
        lambda: depth_pub.get_subscription_count() and info_pub.get_subscription_count(),
        60.0,
        'curve_recon_node subscribing the depth',
    )
    plane_m = np.full((HEIGHT, WIDTH), 0.5, np.float32)
    depth_pub.publish(numpy_to_image(plane_m, '32FC1', STAMP_NS, FRAME))
    K = [FOCAL_PX, 0.0, WIDTH / 2, 0.0, FOCAL_PX, HEIGHT / 2, 0.0, 0.0, 1.0]
    info_pub.publish(
        CameraInfo(
            header=make_header(STAMP_NS, FRAME),
            width=WIDTH,
            height=HEIGHT,
            distortion_model='plumb_bob',
            d=[0.0] * 5,
            k=K,
            r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p=K[:3] + [0.0] + K[3:6] + [0.0] + K[6:] + [0.0],
        )
    )
    rclpy_node.spin_until(lambda: 'yes' in depth_states, 30.0, "the node's depth status yes")
    assert not problems, problems
    assert 'rejected /depth/fused' not in node.output(), node.output()


def _collect(msg, depth_states, problems):
    for status in msg.status:
        if not status.name.startswith('curve_recon_node: '):
            continue
        if 'rejected' in status.name:
            problems.append((status.name, status.message))
        depth_states += [kv.value for kv in status.values if kv.key == 'depth']
