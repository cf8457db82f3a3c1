"""The graph split across two simulated hosts (network namespaces on a veth), no code
change: host a runs sensor_sim, the recorder and the demo's probe; host b runs
calib_node, sfs_stereo_node, curve_recon_node and pa10_ik_node. DDS discovers across the
link (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET); shared memory is not used between
namespaces, so every image the vision nodes see crossed the veth.

1. The quick closed loop (scripts/demo.py) completes within the demo's tolerances with
   nothing lost between the publishers and the bag.
2. Faults (tests/multihost/fault_scenario.py, run on host a): the link down for 5 s
   mid-stream, then pa10_ik_node killed and restarted on host b."""

import json
import os
import subprocess
import sys

import pytest
from netns import TwoHosts

from harness import REPO_ROOT, SCENARIO_DIR, next_ros_env

DEMO_TIMEOUT = 600.0  # [s]
REMOTE_NODES = ('calib_node', 'sfs_stereo_node', 'curve_recon_node', 'pa10_ik_node')
IMAGE_BYTES = 320 * 240  # one quick-scenario mono8 image
RECOVERY_LIMIT = 2.0  # [s] data again after the link comes back
RESTART_LIMIT = 10.0  # [s] a restarted node back in service


def host_env():
    env = next_ros_env()
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'  # the hosts see each other
    return env


@pytest.fixture
def hosts():
    with TwoHosts(os.getpid()) as hosts:
        yield hosts


@pytest.mark.timeout(DEMO_TIMEOUT + 60)
def test_closed_loop_across_two_hosts(hosts, tmp_path):
    sent_before = hosts.transmitted_bytes('a')
    process = subprocess.run(
        [
            *hosts.prefix('a'),
            sys.executable,
            str(REPO_ROOT / 'scripts' / 'demo.py'),
            '--scenario',
            str(SCENARIO_DIR / 'quick.yaml'),
            '--bags',
            str(tmp_path),
            '--remote-nodes',
            *REMOTE_NODES,
            '--remote-prefix',
            ' '.join(hosts.prefix('b')),
        ],
        env=host_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=DEMO_TIMEOUT,
        start_new_session=True,
    )
    sys.stdout.write(process.stdout[-6000:])
    bag_dirs = [d for d in tmp_path.iterdir() if d.name.startswith('demo-')]
    assert bag_dirs, 'the demo recorded no bag'
    results = json.loads((bag_dirs[0] / 'report' / 'results.json').read_text())
    measured = results['results']
    for camera in ('left', 'right', 'aux'):
        assert measured['calibration'][camera]['image_rms_px'] < 0.5
    assert measured['curve']['rms_m'] < 1.0e-3
    tracking = measured['tracking']
    assert tracking['path_rms_m'] < 1.0e-3 and tracking['force_in_band'] > 0.95
    for topic, _, in_mcap, in_rosbags, lost in results['messages']:
        assert in_mcap == in_rosbags, topic
        assert lost in (None, 0), f'{topic}: {lost} lost between hosts'
    assert process.returncode == 0
    # The images reached host b over the link: at least every chart view, three cameras.
    sent = hosts.transmitted_bytes('a') - sent_before
    images = sum(n for topic, _, n, _, _ in results['messages'] if topic.endswith('image_raw'))
    assert sent > images * IMAGE_BYTES, f'{sent} bytes over the link for {images} images'


@pytest.mark.timeout(300)
def test_link_outage_and_a_restarted_node(hosts, tmp_path):
    result = subprocess.run(
        [
            *hosts.prefix('a'),
            sys.executable,
            str(REPO_ROOT / 'tests' / 'multihost' / 'fault_scenario.py'),
            '--host-b-prefix',
            ' '.join(hosts.prefix('b')),
            '--link',
            hosts.links['a'],
            '--work',
            str(tmp_path),
        ],
        env=host_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=280,
        start_new_session=True,
    )
    sys.stdout.write(result.stdout[-6000:])
    assert result.returncode == 0
    figures = json.loads(result.stdout.strip().splitlines()[-1])
    assert figures['tool_poses_before_outage'] > 10
    assert figures['recovery_s'] < RECOVERY_LIMIT
    # Lost during the outage: at most what the outage lasted times the rate (reported).
    assert figures['lost_tool_poses'] <= figures['outage_s'] * figures['tool_pose_rate'] * 1.2
    assert figures['restart_to_tool_pose_s'] < RESTART_LIMIT
    assert figures['start_tracking_after_restart'] is True
