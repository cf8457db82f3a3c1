#!/usr/bin/env python3
"""Faults between two hosts, run on host a by tests/multihost/test_two_hosts.py.

Host a: sensor_sim (the quick scenario, joint states and pressure at 200 Hz) and this
probe, which publishes latched waypoints (the true curve) and watches /tool_pose; host b:
pa10_ik_node, whose /tool_pose is the forward kinematics of the joint states it receives
from host a, so every tool pose is a round trip over the link.

1. The link goes down for OUTAGE s mid-stream, then up: how long until tool poses arrive
   again, and how many the gap cost.
2. pa10_ik_node is killed (SIGKILL) and started again on host b: how long until its first
   tool pose, and whether it took the latched waypoints again (start_tracking accepted).

Prints progress, then one JSON line of figures; exit status 1 if a step timed out."""

import argparse
import functools
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / 'tests'))

from harness import SCENARIO_DIR, executable  # noqa: E402
from vgm_common.launcher import stop_process_group  # noqa: E402

OUTAGE = 5.0  # [s]


def waypoints_of_true_curve(truth_dir):
    """The true curve's first piece as waypoints: x along the tangent, z down the base's
    -z made orthogonal to it (INTERFACES.md's fallback without depth)."""
    pieces = np.load(truth_dir / 'curve_base.npz')
    points = pieces[pieces.files[0]][::4]
    tangents = np.gradient(points, axis=0)
    poses = []
    for point, tangent in zip(points, tangents):
        x = tangent / np.linalg.norm(tangent)
        z = np.array([0.0, 0.0, -1.0]) - x * -x[2]
        z /= np.linalg.norm(z)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = point
        poses.append(T)
    return np.array(poses)


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--host-b-prefix', required=True)
    parser.add_argument('--link', required=True, help="host a's end of the veth")
    parser.add_argument('--work', type=Path, required=True)
    return parser.parse_args()


class Processes:
    """The processes this script starts, each in its own session logging into ``work``."""

    def __init__(self, work):
        self.work, self.started = work, []

    def start(self, argv, name):
        log = open(self.work / f'{name}-{len(self.started)}.log', 'w')
        self.started.append(
            subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        )
        return self.started[-1]

    def stop_all(self):
        """SIGINT to each process group, newest first; SIGKILL after 10 s."""
        for process in reversed(self.started):
            stop_process_group(process)


def spin_until(spin, condition, timeout, what):
    """``spin()`` until ``condition()``; TimeoutError after ``timeout`` [s]."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')
        spin()


def spin_for(spin, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        spin()


def start_tracking(spin, probe, trigger):
    """The answer of /pa10_ik_node/start_tracking (service type ``trigger``)."""
    # The killed server's endpoints stay in the graph until their lease ends, so the
    # service can look ready while a request reaches only the dead one: ask again.
    client = probe.create_client(trigger, '/pa10_ik_node/start_tracking')
    for _ in range(6):
        spin_until(spin, client.service_is_ready, 30, 'the start_tracking service')
        future = client.call_async(trigger.Request())
        try:
            spin_until(spin, future.done, 5, 'the start_tracking answer')
            return future.result()
        except TimeoutError:
            client.remove_pending_request(future)
    raise TimeoutError('start_tracking never answered')


def measure_tool_pose_rate(spin, arrivals):
    """Wait for host b's tool poses, then count them for 2 s: figures."""
    print('waiting for tool poses from host b', flush=True)
    spin_until(spin, lambda: len(arrivals) > 50, 90, 'tool poses from host b')
    count, started = len(arrivals), time.monotonic()
    spin_for(spin, 2.0)
    rate = (len(arrivals) - count) / (time.monotonic() - started)
    return dict(tool_poses_before_outage=len(arrivals), tool_pose_rate=rate)


def measure_link_outage(spin, arrivals, link, rate):
    """Fault 1: ``link`` down for OUTAGE s, then up; ``rate`` [1/s] of tool poses before
    it. Returns figures: the outage, the recovery and the tool poses lost."""
    print(f'link down for {OUTAGE} s ({rate:.0f} tool poses/s before)', flush=True)
    subprocess.run(['ip', 'link', 'set', link, 'down'], check=True)
    down = time.monotonic()
    spin_for(spin, OUTAGE)
    subprocess.run(['ip', 'link', 'set', link, 'up'], check=True)
    up = time.monotonic()
    during = sum(1 for t in arrivals if down < t)
    spin_until(spin, lambda: arrivals[-1] > up, 60, 'tool poses after the link came back')
    back = next(t for t in arrivals if t > up)
    print(f'data again {back - up:.2f} s after link up', flush=True)
    return dict(
        outage_s=up - down,
        recovery_s=back - up,
        lost_tool_poses=max(0, round(rate * (back - down)) - during),
    )


def restart_pa10(spin, arrivals, node, pa10):
    """Fault 2: SIGKILL ``node`` (pa10_ik_node on host b) and ``pa10()`` it again. Returns
    the time [s] from the restart to its first tool pose."""
    print('killing pa10_ik_node on host b and starting it again', flush=True)
    os.killpg(node.pid, signal.SIGKILL)
    node.wait()
    restarted = time.monotonic()
    pa10()
    spin_until(spin, lambda: arrivals[-1] > restarted, 60, 'tool poses of the restarted node')
    return next(t for t in arrivals if t > restarted) - restarted


def main():
    args = parse_args()
    b_prefix = shlex.split(args.host_b_prefix)
    truth = args.work / 'truth'
    processes = Processes(args.work)

    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg
    from std_srvs.srv import Trigger

    from vgm_common.conversions import matrices_to_path
    from vgm_common.node_main import init_rclpy
    from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS

    init_rclpy([])
    probe = rclpy.create_node('fault_probe')
    arrivals = []
    probe.create_subscription(
        PoseStamped, '/tool_pose', lambda msg: arrivals.append(time.monotonic()), DEFAULT_QOS
    )
    spin = functools.partial(rclpy.spin_once, probe, timeout_sec=0.02)

    def pa10():
        return processes.start([*b_prefix, str(executable('pa10_ik_node'))], 'pa10_ik_node')

    figures = {}
    try:
        processes.start(
            [
                str(executable('sensor_sim')),
                '--ros-args',
                '-p',
                f'scenario:={SCENARIO_DIR / "quick.yaml"}',
                '-p',
                'calibration_phase:=false',
                '-p',
                'rate:=1.0',
                '-p',
                f'ground_truth_dir:={truth}',
            ],
            'sensor_sim',
        )
        spin_until(spin, lambda: (truth / 'curve_base.npz').exists(), 90, 'the ground truth')
        path_publisher = probe.create_publisher(PathMsg, '/curve/waypoints', LATCHED_QOS)
        path_publisher.publish(matrices_to_path(waypoints_of_true_curve(truth), 1, 'base_link'))
        node = pa10()
        figures.update(measure_tool_pose_rate(spin, arrivals))
        figures.update(measure_link_outage(spin, arrivals, args.link, figures['tool_pose_rate']))
        figures['restart_to_tool_pose_s'] = restart_pa10(spin, arrivals, node, pa10)
        answer = start_tracking(spin, probe, Trigger)
        figures['start_tracking_after_restart'] = bool(answer.success)
        figures['start_tracking_message'] = answer.message
    except TimeoutError as error:
        print(f'FAILED: {error}', flush=True)
        return 1
    finally:
        processes.stop_all()
        probe.destroy_node()
        rclpy.try_shutdown()
    print(json.dumps(figures), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
