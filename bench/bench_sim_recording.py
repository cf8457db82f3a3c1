#!/usr/bin/env python3
"""sensor_sim at 30 Hz (three 640x480 cameras) while the recorder records: frames
published vs frames in the bag, achieved camera rate, CPU of each process.

    make bench            # or: python bench/bench_sim_recording.py --seconds 30
Writes bench/results/sim_recording.md and .json.
"""
import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
import rclpy
from ament_index_python.packages import get_package_share_directory
from mcap.reader import make_reader
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import Image

from sensor_sim.sensor_sim_node import parse_published_counts
from vgm_common.launcher import Launch
from vgm_common.qos import DEFAULT_QOS

RESULTS = Path(__file__).resolve().parent / 'results'
IMAGE_TOPICS = ('/stereo/left/image_raw', '/stereo/right/image_raw', '/aux/image_raw')


def wait_for_first_image(timeout):
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('bench_probe', context=context)
    seen = []
    node.create_subscription(Image, IMAGE_TOPICS[0], seen.append, DEFAULT_QOS)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    deadline = time.monotonic() + timeout
    while not seen and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.1)
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=context)
    if not seen:
        raise TimeoutError('no image from sensor_sim')


def cpu_seconds(pid):
    process = psutil.Process(pid)
    total = sum(process.cpu_times()[:2])
    for child in process.children(recursive=True):
        total += sum(child.cpu_times()[:2])
    return total


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--rate', type=float, default=30.0)
    args = parser.parse_args()
    graph = Path(get_package_share_directory('vgm_common')) / 'params' / 'graph.yaml'
    with tempfile.TemporaryDirectory() as tmp:
        launch = Launch(graph, nodes=['recorder', 'sensor_sim'], overrides=[
            f'recorder:output_dir:={tmp}', 'recorder:bag_name:=bench',
            'sensor_sim:calibration_phase:=false', f'sensor_sim:rate:={args.rate}'])
        launch.start()
        try:
            wait_for_first_image(60.0)
            pids = {name: p.pid for name, p in launch.processes.items()}
            cpu_start = {name: cpu_seconds(pid) for name, pid in pids.items()}
            start = time.monotonic()
            time.sleep(args.seconds)  # the measurement window itself, not a wait for a condition
            wall = time.monotonic() - start
            cpu = {name: (cpu_seconds(pid) - cpu_start[name]) / wall * 100
                   for name, pid in pids.items()}
        finally:
            launch.stop()
        published = parse_published_counts(launch.log_text('sensor_sim'))
        in_bag = {}
        stamps = {IMAGE_TOPICS[0]: [], '/joint_states': []}
        with open(Path(tmp) / 'bench' / 'bench_0.mcap', 'rb') as stream:
            reader = make_reader(stream)
            for _, channel, message in reader.iter_messages(topics=list(stamps)):
                stamps[channel.topic].append(message.publish_time)
            summary = reader.get_summary()
            for channel_id, count in summary.statistics.channel_message_counts.items():
                in_bag[summary.channels[channel_id].topic] = count
    periods = np.diff(np.array(stamps[IMAGE_TOPICS[0]]) * 1e-9)
    joint_periods = np.diff(np.array(stamps['/joint_states']) * 1e-9)
    result = {
        'requested_rate_hz': args.rate, 'window_s': round(wall, 2),
        'frames_published': {t: published[t] for t in IMAGE_TOPICS},
        'frames_in_bag': {t: in_bag.get(t, 0) for t in IMAGE_TOPICS},
        'frames_lost': {t: published[t] - in_bag.get(t, 0) for t in IMAGE_TOPICS},
        'joint_states_published': published['/joint_states'],
        'joint_states_in_bag': in_bag.get('/joint_states', 0),
        'achieved_rate_hz': round(1 / float(np.mean(periods)), 2),
        'period_p95_ms': round(float(np.percentile(periods, 95)) * 1e3, 1),
        'joint_state_rate_hz': round(1 / float(np.mean(joint_periods)), 1),
        'cpu_percent': {k: round(v, 1) for k, v in cpu.items()},
        'cores': psutil.cpu_count(),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / 'sim_recording.json').write_text(json.dumps(result, indent=2))
    lines = ['# sensor_sim + recorder at 30 Hz', '',
             f'Command: `python bench/bench_sim_recording.py --seconds {args.seconds:g} '
             f'--rate {args.rate:g}` (via `make bench`). {result["cores"]} cores.', '',
             '| measure | value |', '|---|---|']
    lines += [f'| {k} | {v} |' for k, v in result.items() if k != 'cores']
    (RESULTS / 'sim_recording.md').write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))


if __name__ == '__main__':
    main()
