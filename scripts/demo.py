#!/usr/bin/env python3
"""make demo: run the graph on a scenario, record every topic, check the bag with two
independent readers, and write a report (markdown + PNG) beside the bag.

So far the graph is the simulator and the recorder (the pipeline nodes come with their
own issues): the chart is shown at every calibration stage pose, then the scene with the
curve. Meanwhile the demo moves the arm by a scripted joint trajectory: down until the
tool presses 5 mm into the surface, hold, and back, so the contact force shows.
"""
import argparse
import shutil
import sys
import time
from collections import Counter, defaultdict
from datetime import datetime
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import rclpy  # noqa: E402
from ament_index_python.packages import get_package_share_directory  # noqa: E402
from builtin_interfaces.msg import Duration  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from sensor_sim.contact import joint_vector_pressing  # noqa: E402
from sensor_sim.sensor_sim_node import parse_published_counts  # noqa: E402
from vgm_common.launcher import Launch  # noqa: E402
from vgm_common.qos import DEFAULT_QOS  # noqa: E402
from vgm_common.robot_model import load_robot  # noqa: E402
from vgm_common.scenario import load_scenario, resolve_scenario_path  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
IMAGE_TOPICS = ('/stereo/left/image_raw', '/stereo/right/image_raw', '/aux/image_raw')
EXPECTED_TOPICS = (*IMAGE_TOPICS, '/calibration/target_pose', '/joint_states',
                   '/tool/pressure', '/diagnostics')


def stage(number, total, text):
    print(f'\n== [{number}/{total}] {text}', flush=True)


# Lowering the shoulder, elbow and wrist pitch joints brings a tool pointing down to the
# surface in the shipped rig scenarios; the touch is skipped where it does not.
LOWERING_JOINT_STEP = np.array([0.0, 0.25, 0.0, 0.25, 0.0, 0.15, 0.0])  # [rad]
TOUCH_PENETRATION = 0.005  # [m]


def touch_trajectory(scenario):
    """Joint trajectory: initial pose -> pressing pose (3 s) -> hold (2 s) -> back (3 s)."""
    robot = load_robot(scenario.robot.model, scenario.robot.tool_length)
    q0 = scenario.robot.initial_joints
    try:
        q_press = joint_vector_pressing(robot, scenario.surface, q0, q0 + LOWERING_JOINT_STEP,
                                        TOUCH_PENETRATION)
    except ValueError as error:
        print(f'   (no touch in this scenario: {error})')
        return None
    points = [JointTrajectoryPoint(positions=q.tolist(), time_from_start=Duration(sec=t))
              for q, t in ((q_press, 3), (q_press, 5), (q0, 8))]
    return JointTrajectory(joint_names=list(robot.joint_names), points=points)


class Progress:
    """Counts captures as they are published, to show how far the demo has got, and
    sends the touch trajectory once the calibration phase is over."""

    def __init__(self, chart_captures, touch):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('demo_progress', context=self.context)
        self.stamps = Counter()
        # Subscribed to every camera, so sensor_sim's min_subscribers (recorder + this
        # probe) holds on each; captures are counted on the first.
        self.node.create_subscription(Image, IMAGE_TOPICS[0], self._on_image, DEFAULT_QOS)
        for topic in IMAGE_TOPICS[1:]:
            self.node.create_subscription(Image, topic, lambda msg: None, DEFAULT_QOS)
        self.trajectory_publisher = self.node.create_publisher(
            JointTrajectory, '/pa10_controller/joint_trajectory', DEFAULT_QOS)
        self.chart_captures, self.touch = chart_captures, touch
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.last_print = 0.0

    def _on_image(self, msg):
        self.stamps['captures'] += 1

    def spin(self, total_captures):
        self.executor.spin_once(timeout_sec=0.05)
        if self.touch is not None and self.stamps['captures'] >= self.chart_captures:
            print('   ... calibration phase over: pressing the tool on the surface', flush=True)
            self.trajectory_publisher.publish(self.touch)
            self.touch = None
        if time.monotonic() - self.last_print > 2.0:
            self.last_print = time.monotonic()
            print(f'   ... {self.stamps["captures"]}/{total_captures} captures', flush=True)
        return self.stamps['captures'] >= total_captures

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def read_with_mcap(bag_dir):
    """Decode every message with mcap's reader + mcap_ros2 (independent of our code)."""
    messages = defaultdict(list)
    for path in sorted(bag_dir.glob('*.mcap')):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages():
                messages[channel.topic].append((message.log_time, decoded))
    return messages


def count_with_rosbags(bag_dir):
    with AnyReader([bag_dir]) as reader:
        return Counter(connection.topic for connection, _, _ in reader.messages())


def image_array(msg):
    return np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.step)[:, :msg.width]


def write_report(bag_dir, scenario, messages, counts_rosbags, published, seconds):
    report_dir = bag_dir / 'report'
    report_dir.mkdir(exist_ok=True)
    figures = []

    # The three views: first calibration capture and last scene capture.
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for column, topic in enumerate(IMAGE_TOPICS):
        images = messages.get(topic, [])
        for row, (label, index) in enumerate((('first capture', 0), ('last capture', -1))):
            ax = axes[row, column]
            ax.axis('off')
            if images:
                ax.imshow(image_array(images[index][1]), cmap='gray', vmin=0, vmax=255)
                ax.set_title(f'{topic}\n{label}', fontsize=9)
    fig.tight_layout()
    fig.savefig(report_dir / 'views.png', dpi=80)
    plt.close(fig)
    figures.append(('The three views', 'views.png'))

    joint_states = messages.get('/joint_states', [])
    pressure = messages.get('/tool/pressure', [])
    if joint_states:
        fig, (ax_q, ax_f) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        t0 = joint_states[0][0]
        t = np.array([log_time - t0 for log_time, _ in joint_states]) * 1e-9
        q = np.array([m.position for _, m in joint_states])
        for j in range(q.shape[1]):
            ax_q.plot(t, q[:, j], label=joint_states[0][1].name[j])
        ax_q.set_ylabel('joint position [rad]')
        ax_q.legend(fontsize=7, ncol=4)
        if pressure:
            tp = np.array([log_time - t0 for log_time, _ in pressure]) * 1e-9
            ax_f.plot(tp, [m.wrench.force.z for _, m in pressure])
        ax_f.set_ylabel('contact force [N]')
        ax_f.set_xlabel('time [s]')
        fig.tight_layout()
        fig.savefig(report_dir / 'arm.png', dpi=80)
        plt.close(fig)
        figures.append(('Joint positions and contact force', 'arm.png'))

    rows = []
    for topic in sorted(set(messages) | set(counts_rosbags)):
        stamps = [log_time for log_time, _ in messages.get(topic, [])]
        rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-9) if len(stamps) > 2 else 0
        sent = published.get(topic)
        lost = '' if sent is None else sent - len(stamps)
        rows.append((topic, '' if sent is None else sent, len(stamps),
                     counts_rosbags.get(topic, 0), lost, rate))
    table = ['| topic | published | in bag (mcap reader) | in bag (rosbags) | lost | rate [Hz] |',
             '|---|---|---|---|---|---|']
    table += [f'| `{t}` | {p} | {n} | {m} | {lost} | {r:.1f} |'
              for t, p, n, m, lost, r in rows]
    text = [f'# Demo report: {bag_dir.name}', '',
            f'Scenario `{scenario.name}` ({scenario.path}), seed {scenario.seed}; '
            f'recorded for {seconds:.1f} s.', '', '## Messages in the bag', '', *table, '']
    for title, file in figures:
        text += [f'## {title}', '', f'![{title}]({file})', '']
    (report_dir / 'report.md').write_text('\n'.join(text))
    return rows, report_dir


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scenario', default='default', help='shipped name or file')
    parser.add_argument('--seconds', type=float, default=12.0,
                        help='scene time recorded after the calibration phase [s]')
    parser.add_argument('--bags', type=Path, default=REPO_ROOT / 'bags')
    args = parser.parse_args()

    scenario_path = resolve_scenario_path(args.scenario).resolve()
    scenario = load_scenario(scenario_path)
    name = f'demo-{datetime.now():%Y%m%d-%H%M%S}'
    bag_dir = args.bags / name
    truth_dir = args.bags / f'.{name}-ground-truth'
    chart_captures = (len(scenario.calibration.T_base_chart) *
                      scenario.calibration.captures_per_pose if scenario.calibration else 0)
    total_captures = chart_captures + int(args.seconds * scenario.rate)
    total = 3

    stage(1, total, f'simulating scenario {scenario.name} and recording to {bag_dir}')
    graph = Path(get_package_share_directory('vgm_common')) / 'params' / 'graph.yaml'
    launch = Launch(graph, nodes=['recorder', 'sensor_sim'], overrides=[
        f'recorder:output_dir:={args.bags}', f'recorder:bag_name:={name}',
        f'sensor_sim:scenario:={scenario_path}', f'sensor_sim:ground_truth_dir:={truth_dir}',
        # the recorder and this script's progress probe: nothing is lost to discovery
        'sensor_sim:min_subscribers:=2'])
    progress = Progress(chart_captures, touch_trajectory(scenario))
    started = time.monotonic()
    try:
        status = launch.run(duration=total_captures / scenario.rate + 60.0,
                            until=lambda: progress.spin(total_captures))
    finally:
        progress.close()
    seconds = time.monotonic() - started
    published = parse_published_counts(launch.log_text('sensor_sim'))
    if status != 0:
        print('a node failed: see its log lines above', file=sys.stderr)
        return 1
    if truth_dir.exists():
        shutil.move(str(truth_dir), str(bag_dir / 'ground_truth'))

    stage(2, total, 'reading the bag with mcap + mcap_ros2 and with rosbags')
    messages = read_with_mcap(bag_dir)
    counts_rosbags = count_with_rosbags(bag_dir)

    stage(3, total, 'writing the report')
    rows, report_dir = write_report(bag_dir, scenario, messages, counts_rosbags, published,
                                    seconds)
    print(f'\n{"topic":32} {"published":>9} {"mcap":>7} {"rosbags":>8} {"lost":>5} '
          f'{"rate Hz":>8}')
    for topic, sent, n_mcap, n_rosbags, lost, rate in rows:
        print(f'{topic:32} {sent:>9} {n_mcap:7d} {n_rosbags:8d} {lost:>5} {rate:8.1f}')
    missing = [t for t in EXPECTED_TOPICS if not messages.get(t)]
    disagree = [row[0] for row in rows if row[2] != row[3]]
    lost = [row[0] for row in rows if row[4] not in ('', 0)]
    print(f'\nbag:    {bag_dir}\nreport: {report_dir / "report.md"}')
    if missing or disagree or lost:
        print(f'FAILED: topics missing from the bag: {missing}; reader counts differ: '
              f'{disagree}; messages lost: {lost}', file=sys.stderr)
        return 1
    print('OK: every expected topic recorded, nothing lost, both readers agree')
    return 0


if __name__ == '__main__':
    sys.exit(main())
