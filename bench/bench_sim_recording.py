#!/usr/bin/env python3
"""sensor_sim (three 640x480 cameras) while the recorder records, at 10 and 30 Hz,
repeated, on one host and split over two (sensor_sim on host a, the recorder on host b:
network namespaces on a veth, tests/multihost/netns.py; needs root): frames published
vs frames in the bag, achieved camera and joint-state rates, image latency (bag receive
time - capture stamp), bytes over the link, CPU of each process.

    make bench            # or: python bench/bench_sim_recording.py --seconds 20 --repeats 3
Writes bench/results/sim_recording.md and .json.
"""

import argparse
import os
import sys
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import psutil
from ament_index_python.packages import get_package_share_directory
from mcap.reader import make_reader
from vgm_evaluation.bench_report import markdown_table, write_results

from sensor_sim.render import add_noise
from vgm_common.diagnostics import parse_published_counts
from vgm_common.launcher import Launch

RESULTS = Path(__file__).resolve().parent / 'results'
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests' / 'multihost'))
from netns import TwoHosts  # noqa: E402

from vgm_common.topics import IMAGE_TOPICS, JOINT_STATES_TOPIC  # noqa: E402

IMAGE_TOPICS = (IMAGE_TOPICS['left'], IMAGE_TOPICS['right'], IMAGE_TOPICS['aux'])


def wait_for_recording(launch, timeout):
    """Until the recorder subscribed to every camera (sensor_sim waits for it)."""
    deadline = time.monotonic() + timeout
    while not all(f'recording {topic} ' in launch.log_text('recorder') for topic in IMAGE_TOPICS):
        if time.monotonic() > deadline or launch.failed():
            raise TimeoutError('the recorder did not subscribe to the cameras')
        time.sleep(0.1)


def cpu_seconds(pid):
    process = psutil.Process(pid)
    total = sum(process.cpu_times()[:2])
    for child in process.children(recursive=True):
        total += sum(child.cpu_times()[:2])
    return total


def measure(rate, seconds, hosts=None):
    """One run: start recorder + sensor_sim at ``rate`` [Hz] (on the two ``hosts`` if
    given), record ``seconds`` [s] once the recorder subscribed, stop, compare what was
    published with what is in the bag."""
    graph = Path(get_package_share_directory('vgm_common')) / 'params' / 'graph.yaml'
    prefixes = (
        {} if hosts is None else {'sensor_sim': hosts.prefix('a'), 'recorder': hosts.prefix('b')}
    )
    if hosts is not None:
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'  # the hosts see each other
    with tempfile.TemporaryDirectory() as tmp:
        launch = Launch(
            graph,
            nodes=['recorder', 'sensor_sim'],
            overrides=[
                f'recorder:output_dir:={tmp}',
                'recorder:bag_name:=bench',
                'sensor_sim:calibration_phase:=false',
                f'sensor_sim:rate:={rate}',
                'sensor_sim:min_subscribers:=1',
            ],
            command_prefixes=prefixes,
        )
        launch.start()
        try:
            wait_for_recording(launch, 60.0)
            pids = {name: p.pid for name, p in launch.processes.items()}
            cpu_start = {name: cpu_seconds(pid) for name, pid in pids.items()}
            link_start = hosts.transmitted_bytes('a') if hosts else 0
            start = time.monotonic()
            time.sleep(seconds)  # the measurement window itself, not a wait for a condition
            wall = time.monotonic() - start
            cpu = {
                name: (cpu_seconds(pid) - cpu_start[name]) / wall * 100
                for name, pid in pids.items()
            }
            link_rate = (hosts.transmitted_bytes('a') - link_start) / wall if hosts else 0
        finally:
            launch.stop()
        published = parse_published_counts(launch.log_text('sensor_sim'))
        in_bag = {}
        stamps = {IMAGE_TOPICS[0]: [], JOINT_STATES_TOPIC: []}
        latencies = []
        with open(Path(tmp) / 'bench' / 'bench_0.mcap', 'rb') as stream:
            reader = make_reader(stream)
            for _, channel, message in reader.iter_messages(topics=list(stamps)):
                stamps[channel.topic].append(message.publish_time)
                if channel.topic == IMAGE_TOPICS[0]:
                    latencies.append((message.log_time - message.publish_time) * 1e-6)
            summary = reader.get_summary()
            for channel_id, count in summary.statistics.channel_message_counts.items():
                in_bag[summary.channels[channel_id].topic] = count
    image_periods = np.diff(np.array(stamps[IMAGE_TOPICS[0]]) * 1e-9)
    joint_periods = np.diff(np.array(stamps[JOINT_STATES_TOPIC]) * 1e-9)
    frames = sum(published[t] for t in IMAGE_TOPICS)
    frames_lost = frames - sum(in_bag.get(t, 0) for t in IMAGE_TOPICS)
    joints_lost = published[JOINT_STATES_TOPIC] - in_bag.get(JOINT_STATES_TOPIC, 0)
    return {
        'hosts': 1 if hosts is None else 2,
        'requested_hz': rate,
        'achieved_hz': round(1 / float(np.mean(image_periods)), 2),
        'period_p95_ms': round(float(np.percentile(image_periods, 95)) * 1e3, 1),
        'frames_published': frames,
        'frames_lost': frames_lost,
        'frames_lost_percent': round(100 * frames_lost / frames, 2),
        'joint_states_hz': round(1 / float(np.mean(joint_periods)), 1),
        'joint_states_lost': joints_lost,
        'image_latency_p50_ms': round(float(np.percentile(latencies, 50)), 1),
        'image_latency_p99_ms': round(float(np.percentile(latencies, 99)), 1),
        'link_MB_per_s': round(link_rate / 1e6, 1),
        'cpu_sensor_sim_percent': round(cpu['sensor_sim'], 1),
        'cpu_recorder_percent': round(cpu['recorder'], 1),
    }


def time_noise(repeats=30):
    """[ms] per 640x480 image: sensor_sim's add_noise vs numpy's rng.normal."""
    clean = np.random.default_rng(0).uniform(0, 255, (480, 640))
    timings = {}
    for name, noisy in (
        ('add_noise', lambda rng: add_noise(clean, 1.0, rng)),
        (
            'rng.normal',
            lambda rng: np.clip(np.rint(clean + rng.normal(0.0, 1.0, clean.shape)), 0, 255).astype(
                np.uint8
            ),
        ),
    ):
        start = time.perf_counter()
        for k in range(repeats):
            noisy(np.random.default_rng(k))
        timings[name] = round((time.perf_counter() - start) / repeats * 1e3, 2)
    return timings


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--rates', type=float, nargs='+', default=[10.0, 30.0])
    parser.add_argument('--repeats', type=int, default=2)
    parser.add_argument(
        '--single-host', action='store_true', help='skip the two-host split (it needs root)'
    )
    args = parser.parse_args()
    runs = []
    for split in (False,) if args.single_host else (False, True):
        with TwoHosts(os.getpid()) if split else nullcontext() as hosts:
            for rate in args.rates:
                for repeat in range(args.repeats):
                    print(
                        f'== {"two hosts" if split else "one host"}, {rate:g} Hz, '
                        f'run {repeat + 1}/{args.repeats}',
                        flush=True,
                    )
                    runs.append(measure(rate, args.seconds, hosts))
    columns = list(runs[0])
    lines = [
        '# sensor_sim (3 x 640x480 mono8) + recorder',
        '',
        f'Command: `python bench/bench_sim_recording.py --seconds {args.seconds:g} '
        f'--rates {" ".join(f"{r:g}" for r in args.rates)} --repeats {args.repeats}` '
        f'(part of `make bench`); {psutil.cpu_count()} cores. Frames are counted over '
        'the three cameras; lost = published by sensor_sim but not in the bag. '
        'hosts 2: sensor_sim on host a, the recorder on host b (network namespaces '
        'on a veth); latency = receive time in the bag - capture stamp.',
        '',
    ]
    lines += markdown_table(columns, [[run[c] for c in columns] for run in runs])
    noise = time_noise()
    lines += [
        '',
        'Pixel noise per 640x480 image [ms]: '
        + ', '.join(f'{name} {ms}' for name, ms in noise.items()),
    ]
    write_results(RESULTS, 'sim_recording', lines, runs)


if __name__ == '__main__':
    main()
