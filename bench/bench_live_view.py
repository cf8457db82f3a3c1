#!/usr/bin/env python3
"""live_view forwarding sensor_sim's three 640x480 mono8 cameras at 30 Hz and its 200 Hz
joint states to Foxglove WebSocket clients, beside the recorder, in three runs on the same
graph, back to back:

- ``baseline``: no live_view; a plain raw rclpy subscriber (the peer: the least a Python
  process pays to receive the same topics) and the recorder (zstd, as ``make demo``).
- ``one client``: live_view and one client subscribed to the cameras and joint states.
- ``slow client``: the same plus a second client that reads only a few frames a second
  (a viewer on a bad link): it must lose old messages, not stall live_view or the graph.

Per run: live_view's CPU [% of one core] beside the plain subscriber's, the image latency
the WebSocket client sees minus what the plain subscriber sees for the same capture
(added latency, p50/p99), messages lost by the recorder (published by sensor_sim but not
in the bag) and by each client. Then the demo bag's size with zstd beside the same bag's
uncompressed size (the chunks' own sizes), if a demo bag is given.

    python bench/bench_live_view.py [--seconds 20] [--demo-bag bags/demo-...]
Writes bench/results/live_view/results.md and results.json.
"""

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
import yaml
from ament_index_python.packages import get_package_share_directory

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'tests'))
from foxglove_ws import FoxgloveClient, live_view_url  # noqa: E402
from vgm_evaluation.bench_report import markdown_table, write_results  # noqa: E402

from bag_tools.bag_writer import header_stamp_ns  # noqa: E402
from vgm_common.diagnostics import parse_published_counts  # noqa: E402
from vgm_common.launcher import Launch  # noqa: E402
from vgm_common.topics import IMAGE_TOPICS, JOINT_STATES_TOPIC  # noqa: E402

RESULTS = REPO / 'bench' / 'results' / 'live_view'
IMAGE_TOPICS = [IMAGE_TOPICS['left'], IMAGE_TOPICS['right'], IMAGE_TOPICS['aux']]
TOPICS = [*IMAGE_TOPICS, JOINT_STATES_TOPIC]
RATE = 30.0  # [Hz] cameras
SLOW_READ_PERIOD = 0.2  # [s] the slow client takes one frame this often


# -- probes, each its own process (no GIL shared with what they measure) ---------------


def ros_probe(seconds, out):
    """Raw subscriptions to TOPICS for ``seconds``: receive time of every image per stamp."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image, JointState

    from vgm_common.qos import DEFAULT_QOS

    rclpy.init()
    node = rclpy.create_node('bench_live_view_probe')
    images, counts = {t: {} for t in IMAGE_TOPICS}, dict.fromkeys(TOPICS, 0)

    def on_image(topic, data):
        images[topic][header_stamp_ns(data)] = time.time_ns()
        counts[topic] += 1

    for topic in IMAGE_TOPICS:
        node.create_subscription(
            Image, topic, lambda d, t=topic: on_image(t, d), DEFAULT_QOS, raw=True
        )
    node.create_subscription(
        JointState,
        JOINT_STATES_TOPIC,
        lambda d: counts.__setitem__(JOINT_STATES_TOPIC, counts[JOINT_STATES_TOPIC] + 1),
        DEFAULT_QOS,
        raw=True,
    )
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    Path(out + '.ready').touch()
    start_cpu, start = _cpu_self(), time.monotonic()
    while time.monotonic() - start < seconds:
        executor.spin_once(timeout_sec=0.05)
    cpu = (_cpu_self() - start_cpu) / (time.monotonic() - start) * 100
    Path(out).write_text(json.dumps({'images': images, 'counts': counts, 'cpu': cpu}))


def ws_probe(url, seconds, out, read_period=0.0):
    """A Foxglove client subscribed to TOPICS for ``seconds``; ``read_period`` > 0 reads
    one frame that often (a slow viewer)."""
    client = FoxgloveClient(url)
    client.wait_for_channels(TOPICS, 60)
    client.subscribe(TOPICS)
    images, counts = {t: {} for t in IMAGE_TOPICS}, dict.fromkeys(TOPICS, 0)
    Path(out + '.ready').touch()
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        try:
            topic, _, payload = client.receive(1.0)
        except TimeoutError:
            continue
        counts[topic] += 1
        if topic in images:
            images[topic][header_stamp_ns(payload)] = time.time_ns()
        if read_period:
            time.sleep(read_period)  # the slow viewer's bad link
    client.close()
    Path(out).write_text(json.dumps({'images': images, 'counts': counts}))


def _cpu_self():
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _start_probe(kind, out, seconds, url=''):
    return subprocess.Popen(
        [
            sys.executable,
            __file__,
            '--probe',
            kind,
            '--out',
            str(out),
            '--seconds',
            str(seconds),
            '--url',
            url,
        ]
    )


# -- runs ----------------------------------------------------------------------------


def cpu_seconds(pid):
    process = psutil.Process(pid)
    return sum(process.cpu_times()[:2]) + sum(
        sum(child.cpu_times()[:2]) for child in process.children(recursive=True)
    )


def run(name, seconds, live_view, clients):
    """One graph: sensor_sim at RATE + recorder (+ live_view and ``clients``: read periods)."""
    graph = Path(get_package_share_directory('vgm_common')) / 'params' / 'graph.yaml'
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        params = yaml.safe_load(graph.read_text())
        params['live_view'] = {'ros__parameters': {'port': 0}}
        params_file = tmp / 'params.yaml'
        params_file.write_text(yaml.safe_dump(params))
        nodes = ['recorder', *(['live_view'] if live_view else []), 'sensor_sim']
        launch = Launch(
            params_file,
            nodes=nodes,
            overrides=[
                f'recorder:output_dir:={tmp}',
                'recorder:bag_name:=bench',
                'recorder:exclude:=[/parameter_events, /rosout]',
                'recorder:compression:=zstd',
                'sensor_sim:calibration_phase:=false',
                f'sensor_sim:rate:={RATE}',
            ],
            out=open(tmp / 'launch.log', 'w'),
        )
        launch.start()
        try:
            url = ''
            if live_view:
                url = _wait(
                    lambda: live_view_url(launch.log_text('live_view')), 60, 'live_view to listen'
                )
            window = seconds + 5.0  # the probes outlast the measured window a little
            probes = {'ros': _start_probe('ros', tmp / 'ros.json', window)}
            for index, read_period in enumerate(clients):
                probes[f'ws{index}'] = _start_probe(
                    'slow' if read_period else 'ws', tmp / f'ws{index}.json', window, url
                )
            _wait(
                lambda: all((tmp / f'{p}.json.ready').exists() for p in probes),
                90,
                'the probes to subscribe',
            )
            pids = {n: p.pid for n, p in launch.processes.items()}
            cpu_start = {n: cpu_seconds(pid) for n, pid in pids.items()}
            start = time.monotonic()
            time.sleep(seconds)  # the measurement window itself, not a wait for a condition
            wall = time.monotonic() - start
            cpu = {n: (cpu_seconds(pid) - cpu_start[n]) / wall * 100 for n, pid in pids.items()}
            for probe in probes.values():
                probe.wait(timeout=window + 120)
        finally:
            launch.stop()
        published = parse_published_counts(launch.log_text('sensor_sim'))
        recorded = {
            topic: int(n)
            for topic, n in (
                line.split(':') for line in _recorded_lines(launch.log_text('recorder'))
            )
        }
        results = {p: json.loads((tmp / f'{p}.json').read_text()) for p in probes}
    row = {
        'run': name,
        'camera_hz': _camera_hz(results['ros']),
        'cpu_live_view_percent': round(cpu.get('live_view', 0.0), 1),
        'cpu_plain_subscriber_percent': round(results['ros']['cpu'], 1),
        'cpu_sensor_sim_percent': round(cpu['sensor_sim'], 1),
        'cpu_recorder_percent': round(cpu['recorder'], 1),
        'recorder_lost': sum(published[t] - recorded.get(t, 0) for t in TOPICS),
    }
    ros_images = results['ros']['images']
    for probe, result in results.items():
        if probe == 'ros':
            continue
        added = [
            (result['images'][t][s] - ros_images[t][s]) * 1e-6
            for t in IMAGE_TOPICS
            for s in result['images'][t]
            if s in ros_images[t]
        ]
        # Images the plain subscriber got, while this client was receiving, that it lost.
        lost = offered = 0
        for t in IMAGE_TOPICS:
            seen = [int(s) for s in result['images'][t]]
            if not seen:
                continue
            window = [s for s in ros_images[t] if min(seen) <= int(s) <= max(seen)]
            offered += len(window)
            lost += sum(1 for s in window if s not in result['images'][t])
        row[f'{probe}_images_received'] = sum(len(result['images'][t]) for t in IMAGE_TOPICS)
        row[f'{probe}_images_lost'] = f'{lost} of {offered}'
        row[f'{probe}_joint_states_received'] = result['counts'][JOINT_STATES_TOPIC]
        if added and probe == 'ws0':
            row['added_latency_p50_ms'] = round(float(np.percentile(added, 50)), 2)
            row['added_latency_p99_ms'] = round(float(np.percentile(added, 99)), 2)
    return row


def _camera_hz(ros_result):
    """The cameras' achieved rate, from the captures the plain subscriber saw."""
    stamps = sorted(int(s) for s in ros_result['images'][IMAGE_TOPICS[0]])
    if len(stamps) < 2:
        return 0.0
    return round((len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-9), 1)


def _recorded_lines(log_text):
    """'/topic: N' lines of the recorder's closing log."""
    import re

    return [m.group(1) for m in re.finditer(r'\]:\s+(/\S+: \d+)', log_text)]


def _wait(condition, timeout, what):
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        if time.monotonic() > deadline:
            raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')
        time.sleep(0.1)
    return value


def bag_sizes(bag_dir):
    """The bag's size on disk and the sum of its chunks uncompressed (what the same
    recording takes without compression, to within the summary and index bytes)."""
    from mcap.reader import make_reader

    files = sorted(Path(bag_dir).glob('*.mcap'))
    on_disk = sum(f.stat().st_size for f in files)
    uncompressed = compressed = 0
    compression = set()
    for file in files:
        with open(file, 'rb') as stream:
            summary = make_reader(stream).get_summary()
        for chunk in summary.chunk_indexes:
            uncompressed += chunk.uncompressed_size
            compressed += chunk.compressed_size
            compression.add(chunk.compression or 'none')
    meta = yaml.safe_load((Path(bag_dir) / 'metadata.yaml').read_text())
    seconds = meta['rosbag2_bagfile_information']['duration']['nanoseconds'] * 1e-9
    return {
        'bag': str(bag_dir),
        'compression': ','.join(sorted(compression)),
        'duration_s': round(seconds, 1),
        'on_disk_MB': round(on_disk / 1e6, 1),
        'chunks_uncompressed_MB': round(uncompressed / 1e6, 1),
        'chunks_compressed_MB': round(compressed / 1e6, 1),
        'ratio': round(uncompressed / max(compressed, 1), 2),
    }


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--demo-bag', type=Path, help='a bag `make demo` recorded')
    parser.add_argument('--probe', choices=['ros', 'ws', 'slow'], help=argparse.SUPPRESS)
    parser.add_argument('--out', help=argparse.SUPPRESS)
    parser.add_argument('--url', default='', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.probe == 'ros':
        return ros_probe(args.seconds, args.out)
    if args.probe:
        return ws_probe(
            args.url, args.seconds, args.out, SLOW_READ_PERIOD if args.probe == 'slow' else 0.0
        )
    rows = []
    for name, live_view, clients in (
        ('baseline', False, []),
        ('one client', True, [0.0]),
        ('slow client', True, [0.0, SLOW_READ_PERIOD]),
    ):
        print(f'== {name}', flush=True)
        rows.append(run(name, args.seconds, live_view, clients))
        print(rows[-1], flush=True)
    bag = bag_sizes(args.demo_bag) if args.demo_bag else None
    columns = sorted({c for row in rows for c in row}, key=lambda c: (c != 'run', c))
    lines = [
        '# live_view: 3 cameras 640x480 mono8 at 30 Hz + 200 Hz joint states',
        '',
        f'Command: `python bench/bench_live_view.py --seconds {args.seconds:g}'
        + (f' --demo-bag {args.demo_bag}' if args.demo_bag else '')
        + '`; '
        f'{psutil.cpu_count()} cores, shared with other work (absolute CPU figures '
        'are loaded-machine figures; compare within a run). Plain subscriber: a raw '
        'rclpy subscription to the same topics in its own process, the peer floor. '
        "Added latency: the WebSocket client's receive time minus the plain "
        "subscriber's for the same capture. Lost: published by sensor_sim but not in "
        'the bag (recorder); for a client (ws0 the normal one, ws1 the slow one), '
        'images the plain subscriber received while the client was receiving that '
        'the client did not.',
        '',
    ]
    lines += markdown_table(columns, [[row.get(c, '') for c in columns] for row in rows])
    if bag:
        lines += [
            '',
            f'Demo bag ({bag["bag"]}, {bag["duration_s"]} s): {bag["on_disk_MB"]} MB '
            f'on disk with {bag["compression"]}; its chunks uncompressed '
            f'{bag["chunks_uncompressed_MB"]} MB (ratio {bag["ratio"]}).',
        ]
    write_results(RESULTS, 'results', lines, {'runs': rows, 'demo_bag': bag})


if __name__ == '__main__':
    sys.exit(main())
