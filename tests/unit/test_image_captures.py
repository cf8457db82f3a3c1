"""ImageCaptures pairing streams that are not camera images (the stereo coding encoder's
image and DisparityImage) by stamp: in this process, on the test's private domain."""

import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import Image
from stereo_msgs.msg import DisparityImage

from vgm_common.camera_topics import ImageCaptures
from vgm_common.conversions import numpy_to_image
from vgm_common.qos import DEFAULT_QOS

STREAMS = {'image': (Image, '/probe/image'), 'disparity': (DisparityImage, '/probe/disparity')}


@pytest.fixture
def context(ros_env, monkeypatch):
    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(key, ros_env[key])
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.shutdown(context=context)


def disparity_message(stamp_ns):
    msg = DisparityImage(f=500.0, t=0.1)
    msg.image = numpy_to_image(np.zeros((2, 3), np.float32), '32FC1', stamp_ns, 'frame')
    msg.header = msg.image.header
    return msg


def test_streams_of_other_types_are_paired_by_identical_stamp(context):
    node = Node('captures', context=context)
    captures, unpaired = [], []
    inputs = ImageCaptures(
        node,
        tuple(STREAMS),
        lambda stamp_ns, messages: captures.append((stamp_ns, messages)),
        max_wait=60.0,
        streams=STREAMS,
        on_unpaired=unpaired.append,
    )
    image_pub = node.create_publisher(Image, '/probe/image', DEFAULT_QOS)
    disparity_pub = node.create_publisher(DisparityImage, '/probe/disparity', DEFAULT_QOS)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def spin_until(condition, what):
        deadline = time.monotonic() + 10.0
        while not condition():
            assert time.monotonic() < deadline, f'timed out waiting for {what}'
            executor.spin_once(timeout_sec=0.05)

    spin_until(
        lambda: image_pub.get_subscription_count() and disparity_pub.get_subscription_count(),
        'the subscriptions to match',
    )
    image = np.arange(6, dtype=np.uint8).reshape(2, 3)
    disparity_pub.publish(disparity_message(2_000))
    image_pub.publish(numpy_to_image(image, 'mono8', 1_000, 'frame'))  # no partner yet
    image_pub.publish(numpy_to_image(image, 'mono8', 2_000, 'frame'))
    spin_until(lambda: captures, 'the pair of stamp 2000 ns')
    ((stamp_ns, messages),) = captures
    assert stamp_ns == 2_000 and set(messages) == {'image', 'disparity'}
    assert isinstance(messages['disparity'], DisparityImage) and messages['disparity'].f == 500.0
    assert bytes(messages['image'].data) == image.tobytes()
    # The image of 1000 ns is older than the pair completed: dropped without its partner.
    assert inputs.counts() == {'matched': 1, 'dropped': 1, 'pending': 0}
    assert unpaired == [1]
    executor.shutdown()
    node.destroy_node()
