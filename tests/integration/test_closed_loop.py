"""The whole graph as processes on the quick scenario (scripts/demo.py: calibrate,
reconstruct, fuse, track under force control, record), then curve_recon_node and
sfs_stereo_node run again against the recorded bag, with no simulator, and must
reproduce what they published live."""

import json
import subprocess
import sys

import numpy as np
import pytest
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import Image

from harness import REPO_ROOT, SCENARIO_DIR, executable, next_ros_env
from vgm_common.conversions import image_to_numpy, stamp_to_ns
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import (
    CAMERA_INFO_TOPICS,
    FUSED_DEPTH_TOPIC,
    IMAGE_TOPICS,
    POSE_TOPICS,
    TARGET_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)

sys.path.insert(0, str(REPO_ROOT / 'scripts'))
from demo_evaluation import distance_to_polylines  # noqa: E402

DEMO_TIMEOUT = 420.0  # [s] the quick scenario takes about a minute on an idle 2-core machine


@pytest.fixture(scope='module')
def demo_run(tmp_path_factory):
    """One closed-loop run shared by the tests below: (exit status, bag dir, results)."""
    bags = tmp_path_factory.mktemp('bags')
    env = next_ros_env()
    process = subprocess.run(
        [
            sys.executable,
            str(REPO_ROOT / 'scripts' / 'demo.py'),
            '--scenario',
            str(SCENARIO_DIR / 'quick.yaml'),
            '--bags',
            str(bags),
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=DEMO_TIMEOUT,
        start_new_session=True,
    )
    sys.stdout.write(process.stdout[-6000:])
    bag_dirs = [d for d in bags.iterdir() if d.name.startswith('demo-')]
    results_file = bag_dirs[0] / 'report' / 'results.json' if bag_dirs else None
    results = (
        json.loads(results_file.read_text())
        if results_file is not None and results_file.exists()
        else None
    )
    return process.returncode, (bag_dirs[0] if bag_dirs else None), results


@pytest.mark.timeout(DEMO_TIMEOUT + 60)
def test_closed_loop_tracks_the_curve_under_force_control(demo_run):
    status, bag_dir, results = demo_run
    assert results is not None, 'the demo wrote no results'
    measured = results['results']
    # Calibration: calibrated and true cameras project the surface within 0.5 px.
    for camera in ('left', 'right', 'aux'):
        assert measured['calibration'][camera]['image_rms_px'] < 0.5
    # Curve: waypoints within 1 mm RMS of the true curve, and the whole curve covered.
    assert measured['curve']['rms_m'] < 1.0e-3
    assert measured['curve']['coverage_m'] < 5.0e-3
    # Tracking: the tool tip follows the true curve, pressing with 5 N +-10 %.
    tracking = measured['tracking']
    assert tracking['samples'] > 50
    assert tracking['path_rms_m'] < 1.0e-3
    assert tracking['force_in_band'] > 0.95
    # Every message sensor_sim published is in the bag, and both readers agree.
    for topic, _, in_mcap, in_rosbags, lost in results['messages']:
        assert in_mcap == in_rosbags, topic
        assert lost in (None, 0), f'{topic}: {lost} lost'
    assert status == 0


REPLAYED_INPUTS = [
    IMAGE_TOPICS['left'],
    IMAGE_TOPICS['right'],
    IMAGE_TOPICS['aux'],
    CAMERA_INFO_TOPICS['left'],
    CAMERA_INFO_TOPICS['right'],
    CAMERA_INFO_TOPICS['aux'],
    POSE_TOPICS['left'],
    POSE_TOPICS['right'],
    POSE_TOPICS['aux'],
    TARGET_POSE_TOPIC,
]


def _bag_messages(bag_dir, topics):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    messages = {t: [] for t in topics}
    for path in sorted(bag_dir.glob('*.mcap')):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, _, decoded in reader.iter_decoded_messages(topics=topics):
                messages[channel.topic].append(decoded)
    return messages


@pytest.mark.timeout(DEMO_TIMEOUT + 300)
def test_replay_reproduces_the_live_outputs(demo_run, spawn, rclpy_node):
    _, bag_dir, _ = demo_run
    assert bag_dir is not None, 'the demo recorded no bag'
    live = _bag_messages(bag_dir, [WAYPOINTS_TOPIC, FUSED_DEPTH_TOPIC])
    replayed = {WAYPOINTS_TOPIC: [], FUSED_DEPTH_TOPIC: []}
    rclpy_node.create_subscription(
        PathMsg, WAYPOINTS_TOPIC, replayed[WAYPOINTS_TOPIC].append, LATCHED_QOS
    )
    rclpy_node.create_subscription(
        Image, FUSED_DEPTH_TOPIC, replayed[FUSED_DEPTH_TOPIC].append, DEFAULT_QOS
    )
    params = bag_dir / 'params.yaml'  # what the demo ran them with
    for node in ('curve_recon_node', 'sfs_stereo_node'):
        spawn([executable(node), '--ros-args', '--params-file', params])
    spawn(
        [
            executable('bag_tools', 'player'),
            '--ros-args',
            '-p',
            f'bag:={bag_dir}',
            '-p',
            f'topics:={json.dumps(REPLAYED_INPUTS)}',
            '-p',
            'exit_when_done:=false',
        ]
    )
    rclpy_node.spin_until(
        lambda: replayed[WAYPOINTS_TOPIC] and replayed[FUSED_DEPTH_TOPIC],
        120.0,
        'waypoints and fused depth from the replayed bag',
    )

    # The curve: reconstructed from the same capture, the same waypoints bit for bit;
    # from another capture (other image noise), within 0.5 mm.
    live_path, path = live[WAYPOINTS_TOPIC][0], replayed[WAYPOINTS_TOPIC][0]
    points = _positions(path)
    live_points = _positions(live_path)
    if stamp_to_ns(path.header.stamp) == stamp_to_ns(live_path.header.stamp):
        np.testing.assert_array_equal(points, live_points)
    else:
        assert len(points) == pytest.approx(len(live_points), rel=0.05)
        assert np.sqrt(np.mean(distance_to_polylines(points, [live_points]) ** 2)) < 5e-4

    # Fused depth of a capture processed both live and in replay: identical.
    live_by_stamp = {stamp_to_ns(m.header.stamp): m for m in live[FUSED_DEPTH_TOPIC]}
    rclpy_node.spin_until(
        lambda: any(
            stamp_to_ns(m.header.stamp) in live_by_stamp for m in replayed[FUSED_DEPTH_TOPIC]
        ),
        120.0,
        'a replayed fused depth of a capture also fused live',
    )
    for msg in replayed[FUSED_DEPTH_TOPIC]:
        original = live_by_stamp.get(stamp_to_ns(msg.header.stamp))
        if original is not None:
            np.testing.assert_array_equal(image_to_numpy(msg), image_to_numpy(original))


def _positions(path):
    return np.array(
        [[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in path.poses]
    )
