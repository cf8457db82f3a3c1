#!/usr/bin/env python3
"""make demo: the closed loop on a scenario. sensor_sim, calib_node, curve_recon_node,
sfs_stereo_node, pa10_ik_node, live_view and the recorder run as separate processes; the
chart is shown and the rig calibrated, the curve reconstructed, the depth fused, and the
arm follows the curve pressing on the surface. Then the bag is read back with two
independent readers, everything is compared with the simulator's ground truth, and a
report (markdown + PNG) and a summary table are written. Exit status 1 if a stage misses
its tolerance, a node fails or a message is lost.

A curve that does not lie on the scenario's surface (the thesis's chapter-3 curves float
in front of a background plane) has nothing to press on: then the demo runs the vision
stages only, without pa10_ik_node, and says so.
"""

import argparse
import json
import re
import shlex
import shutil
import socket
import sys
import time
from collections import Counter, defaultdict
from datetime import datetime
from pathlib import Path

import matplotlib
import numpy as np
import yaml

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
from ament_index_python.packages import get_package_share_directory  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import demo_evaluation as evaluation  # noqa: E402
from vgm_evaluation.graph_probe import GraphProbe, status_values  # noqa: E402

from sensor_sim.curves import curve_points_base  # noqa: E402
from sensor_sim.scenario import load_scenario, resolve_scenario_path  # noqa: E402
from sensor_sim.surfaces import signed_height_base  # noqa: E402
from vgm_common.camera_topics import CalibratedCameras  # noqa: E402
from vgm_common.conversions import image_to_numpy, pose_to_matrix  # noqa: E402
from vgm_common.diagnostics import parse_published_counts
from vgm_common.launcher import Launch  # noqa: E402
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS  # noqa: E402
from vgm_common.topics import (  # noqa: E402
    CAMERA_INFO_TOPICS,
    DEPTH_INFO_TOPIC,
    DIAGNOSTICS_TOPIC,
    FUSED_DEPTH_TOPIC,
    IMAGE_TOPICS,
    JOINT_STATES_TOPIC,
    POSE_TOPICS,
    PRESSURE_TOPIC,
    SFS_DEPTH_TOPIC,
    STEREO_DEPTH_TOPIC,
    TOOL_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
NODES = [
    'recorder',
    'live_view',
    'sensor_sim',
    'calib_node',
    'sfs_stereo_node',
    'curve_recon_node',
    'pa10_ik_node',
]
LIVE_VIEW_PORT = 8765  # live_view's default (foxglove_bridge's), on 127.0.0.1
# Pipeline outputs the demo's probe watches to know how far the graph has got.
WATCHED_TOPICS = {WAYPOINTS_TOPIC: (PathMsg, LATCHED_QOS), FUSED_DEPTH_TOPIC: (Image, DEFAULT_QOS)}
DESIRED_FORCE = 5.0  # [N]
ON_SURFACE_TOLERANCE = 1e-3  # [m] a curve this close to the surface can be pressed on
# Image-curve degree for curve_recon_node by the scenario's curve kind; a loop on a curved
# surface is fitted piecewise with conics (the graph's default).
CURVE_DEGREES = {'parabola': 2, 'ellipse': 2, 'circle': 2, 'line_pair': 2, 'cubic': 3}

# Tolerances of the stages (the summary table shows each beside its measured value).
TOLERANCES = {
    'calibration image RMS [px]': 0.5,  # calibrated vs true projection of the surface
    'curve RMS [mm]': 1.0,  # waypoints to the true curve
    'curve coverage [mm]': 5.0,  # farthest true-curve point from the waypoints
    'fused depth median [mm]': 5.0,  # |height| of fused-depth points over the surface
    'tool path RMS [mm]': 1.0,  # tool tip (on the surface) to the true curve
    'force in band [%]': 95.0,  # samples within +-10 % of the desired force
}
LIFT_OFF_TIME = 2.0  # [s] the graph runs on this long once the arm reports done
DEPTH_GRACE = 30.0  # [s] without tracking: how long to wait for fused depth after the curve
STAGE_TIMEOUTS = {'calibrated': 120.0, 'reconstructed': 60.0, 'tracking': 300.0}  # [s]
STAGES = 6  # the numbered stages the demo prints, [n/6]
# What the evaluation and the report's plots decode from the bag.
BAG_TOPICS = [
    *IMAGE_TOPICS.values(),
    WAYPOINTS_TOPIC,
    FUSED_DEPTH_TOPIC,
    SFS_DEPTH_TOPIC,
    STEREO_DEPTH_TOPIC,
    DEPTH_INFO_TOPIC,
    CAMERA_INFO_TOPICS['left'],
    POSE_TOPICS['left'],
    DIAGNOSTICS_TOPIC,
    TOOL_POSE_TOPIC,
    PRESSURE_TOPIC,
    JOINT_STATES_TOPIC,
]


def stage(number, total, text):
    print(f'\n== [{number}/{total}] {text}', flush=True)


class DemoProbe:
    """The demo's view of the running graph: calibration, waypoints, depth and the
    arm's progress (from /diagnostics); starts tracking once the curve is known."""

    def __init__(self):
        # /diagnostics not from the start: nodes hold their first diagnostics until a
        # subscriber matched, and that must be the recorder (watch_diagnostics, later).
        self.graph = GraphProbe('demo_probe', watch_diagnostics=False)
        self.node = self.graph.node
        self.cameras = CalibratedCameras(self.node)
        self.received = Counter()
        self.waypoints = None
        for topic, (kind, qos) in WATCHED_TOPICS.items():
            self.node.create_subscription(kind, topic, lambda m, t=topic: self._count(t, m), qos)
        self.watch_diagnostics = self.graph.watch_diagnostics
        self.spin = self.graph.spin_once
        self.close = self.graph.close
        self.start_client = self.node.create_client(Trigger, '/pa10_ik_node/start_tracking')
        self.start_future = None

    def _count(self, topic, msg):
        self.received[topic] += 1
        if topic == WAYPOINTS_TOPIC:
            self.waypoints = msg

    def message(self, name, default=''):
        status = self.graph.status(name)
        return default if status is None else status.message

    def values(self, name):
        status = self.graph.status(name)
        return {} if status is None else status_values(status)

    def start_tracking(self):
        if self.start_future is None and self.start_client.service_is_ready():
            self.start_future = self.start_client.call_async(Trigger.Request())
        return self.start_future is not None and self.start_future.done()


class ClosedLoop:
    """Steps of the run, checked each time the launcher polls (``until``)."""

    def __init__(self, launch, probe, total_stages, track):
        self.launch, self.probe, self.total, self.track = launch, probe, total_stages, track
        self.step = 'calibrated'
        self.step_started = time.monotonic()
        self.last_print = 0.0
        self.failure = None
        self.done_at = self.curve_at = None

    def __call__(self):
        self.probe.spin()
        now = time.monotonic()
        elapsed = now - self.step_started
        chatty = now - self.last_print > 3.0
        if chatty:
            self.last_print = now
        finished = None  # None: the step goes on (within its timeout)
        if self.step == 'calibrated':
            self._wait_for_calibration(chatty)
        elif self.step == 'reconstructed' and self.probe.waypoints is not None:
            finished = self._wait_for_depth(now)
        elif self.step == 'tracking':
            finished = self._watch_tracking(now, chatty)
        if finished is not None:
            return finished
        if elapsed > STAGE_TIMEOUTS.get(self.step, np.inf):
            self.failure = f'timed out after {elapsed:.0f} s waiting until {self.step}'
            return True
        return False

    def _wait_for_calibration(self, chatty):
        """On to reconstruction once the rig's camera info is in."""
        if self.probe.cameras.ready:
            self.probe.watch_diagnostics()
            self._next('reconstructed', 3, 'reconstructing the curve and fusing depth')
        elif chatty:
            views = re.findall(r'view (\d+): chart found', self.launch.log_text('calib_node'))
            print(f'   ... {views[-1] if views else 0} chart views', flush=True)

    def _wait_for_depth(self, now):
        """The curve is known: on to tracking once fused depth came; without tracking,
        done then (or after DEPTH_GRACE without depth). True: the run is over."""
        self.curve_at = self.curve_at or now
        depth_frames = self.probe.received[FUSED_DEPTH_TOPIC]
        # Tracking needs the depth (approach directions); the vision stages alone
        # report a missing depth as a failed stage rather than waiting for it forever.
        if depth_frames or (not self.track and now - self.curve_at > DEPTH_GRACE):
            why_no_depth = (
                ''
                if depth_frames
                else ' ({})'.format(
                    self.probe.message('sfs_stereo_node: rejected stereo pair', 'no reason given')
                )
            )
            print(
                f'   curve: {len(self.probe.waypoints.poses)} waypoints; fused depth '
                f'frames: {depth_frames}{why_no_depth}',
                flush=True,
            )
            if not self.track:
                self._next(
                    'done',
                    4,
                    'no tracking: the curve does not lie on the '
                    'surface, there is nothing to press on',
                )
                return True
            self._next('tracking', 4, 'tracking the curve under force control')
        return None

    def _watch_tracking(self, now, chatty):
        """Start tracking and follow the arm's phase: True once it is done and lifted off
        or it stopped or failed (``failure`` says why), False while it lifts off, None
        otherwise (the step goes on)."""
        if self.probe.start_tracking() and self.probe.start_future.result() is not None:
            response = self.probe.start_future.result()
            if not response.success:
                self.failure = f'start_tracking refused: {response.message}'
                return True
        values = self.probe.values('pa10_ik_node: tracking')
        phase = values.get('phase', '?')
        if chatty:
            print(f'   ... {tracking_line(values)}', flush=True)
        if phase == 'done':  # give the arm a moment to lift off the surface
            self.done_at = self.done_at or now
            return now - self.done_at > LIFT_OFF_TIME
        if phase in ('stopped', 'failed'):
            self.failure = f'the arm {phase}: {self.probe.message("pa10_ik_node: tracking")}'
            return True
        return None

    def _next(self, step, number, text):
        print(f'   done in {time.monotonic() - self.step_started:.1f} s', flush=True)
        self.step, self.step_started = step, time.monotonic()
        stage(number, self.total, text)


def tracking_line(values):
    """The arm's progress from pa10_ik_node's tracking status ``values``. Its error is
    the controller's own (the tip across the approach axis from the reconstructed
    waypoint path, LIVE_ERROR), not the report's tool path against the true curve;
    reported only while it has one (tracking)."""
    if 'phase' not in values:
        return "waiting for pa10_ik_node's first tracking status"
    line = (
        f'{values["phase"]}: {float(values.get("progress", 0)):.0%} of the curve, '
        f'force {float(values.get("force_N", "nan")):.2f} N'
    )
    error_m = float(values.get('position_error_m', 'nan'))
    if np.isfinite(error_m):
        line += f', {LIVE_ERROR} {error_m * 1e3:.2f} mm'
    return line


LIVE_ERROR = 'tip to waypoint path'
# What each summary row and the live line measure (the report's "Measures" section).
MEASURES = [
    (
        'calibration image RMS [px]',
        'the calibrated and the true camera project the true surface; RMS of the pixel '
        'distance between the two projections, worst camera',
    ),
    ('curve RMS [mm]', 'waypoints to the nearest point of the true curve, RMS'),
    ('curve coverage [mm]', 'farthest point of the true curve from the waypoints'),
    (
        'fused depth median [mm]',
        'fused depth pixels lifted to 3D (calibrated left pose): median |height above the '
        'true surface| (depth.png, bottom row)',
    ),
    (
        'tool path RMS [mm]',
        'while tracking, the tool tip taken back onto the true surface along its normal, '
        'to the true curve, RMS (curve.png, blue); the pressed tip in 3D sits '
        'force / stiffness below the surface (curve.png, cyan: path_3d_rms_m)',
    ),
    ('force in band [%]', 'pressure samples while tracking within +-10 % of the desired force'),
    (
        f'live "{LIVE_ERROR}"',
        "printed while the demo runs: pa10_ik_node's own error, the tip across the approach "
        'axis from the reconstructed waypoints (not the true curve; position_error_m)',
    ),
]


def free_live_view_port():
    """LIVE_VIEW_PORT, or any free port while something else holds it (another demo)."""
    with socket.socket() as probe:
        try:
            probe.bind(('127.0.0.1', LIVE_VIEW_PORT))
        except OSError:
            probe.bind(('127.0.0.1', 0))
        return probe.getsockname()[1]


def write_params(graph, path, settings):
    """The graph's params file with ``settings`` {node: {parameter: value}} applied."""
    params = yaml.safe_load(graph.read_text())
    for node, values in settings.items():
        params.setdefault(node, {'ros__parameters': {}})['ros__parameters'].update(values)
    path.write_text(yaml.safe_dump(params, sort_keys=False))


def curve_on_surface(scenario):
    """Whether the scenario's curve lies on its surface: only then can the arm press on it."""
    heights = signed_height_base(
        scenario.surface, curve_points_base(scenario.curve, scenario.surface)
    )
    return bool(np.all(np.abs(heights) < ON_SURFACE_TOLERANCE))


def light_in_left_optical_frame(scenario):
    """The scene's light direction expressed in the left camera's optical frame, as a user
    would measure it when setting the rig up (sfs_stereo_node's ``light_direction``)."""
    R_base_left = scenario.cameras['left'].T_base_camera[:3, :3]
    return R_base_left.T @ scenario.lighting.direction_base


def read_bag(bag_dir, topics):
    """Decode ``topics`` with mcap's reader + mcap_ros2 (independent of our code) and
    count every topic's messages: {topic: [(log_time, msg)]}, Counter."""
    messages, counts = defaultdict(list), Counter()
    for path in sorted(bag_dir.glob('*.mcap')):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, _ in reader.iter_messages():
                counts[channel.topic] += 1
            stream.seek(0)
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages(topics=topics):
                messages[channel.topic].append((message.log_time, decoded))
    return messages, counts


def count_with_rosbags(bag_dir):
    with AnyReader([bag_dir]) as reader:
        return Counter(connection.topic for connection, _, _ in reader.messages())


def phase_windows(diagnostics, phase):
    """(start, end) log times [ns] during which pa10_ik_node reported ``phase``."""
    windows, start = [], None
    for log_time, msg in diagnostics:
        for status in msg.status:
            if status.name != 'pa10_ik_node: tracking':
                continue
            current = {kv.key: kv.value for kv in status.values}.get('phase')
            if current == phase and start is None:
                start = log_time
            elif current != phase and start is not None:
                windows.append((start, log_time))
                start = None
    if start is not None:
        windows.append((start, diagnostics[-1][0]))
    return windows


def inside(log_time, windows, margin_ns=int(0.5e9)):
    return any(a + margin_ns <= log_time <= b - margin_ns for a, b in windows)


def evaluate(scenario, messages, truth_dir, calibration_dir, track):
    """Every stage against the ground truth: {measure: value} and the data for plots."""
    curve = evaluation.true_curve(truth_dir)
    cameras = evaluation.true_cameras(truth_dir)
    depth_true = {name: np.load(truth_dir / f'depth_{name}.npy') for name in cameras}
    results, data = {}, {'curve': curve}

    calibration = evaluation.calibration_errors(calibration_dir, cameras, depth_true)
    results['calibration'] = calibration
    waypoints = messages[WAYPOINTS_TOPIC][-1][1]
    points = np.array(
        [[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in waypoints.poses]
    )
    results['curve'] = evaluation.curve_errors(points, curve)
    data['waypoints'] = points

    info = messages[DEPTH_INFO_TOPIC][-1][1] if messages.get(DEPTH_INFO_TOPIC) else None
    left_info = messages[CAMERA_INFO_TOPICS['left']][-1][1]
    left_pose = messages[POSE_TOPICS['left']][-1][1]
    T_base_left = pose_to_matrix(left_pose.pose)
    P_rect = np.array((info or left_info).p).reshape(3, 4)
    R_rect = np.array(left_info.r).reshape(3, 3)
    data['depth'], data['depth_heights'], data['depth_true'] = {}, {}, None
    results['depth'] = {}
    for topic in (SFS_DEPTH_TOPIC, FUSED_DEPTH_TOPIC, STEREO_DEPTH_TOPIC):
        if messages.get(topic):
            depth = image_to_numpy(messages[topic][-1][1])
            data['depth'][topic] = depth
            data['depth_heights'][topic] = evaluation.depth_heights(
                depth, P_rect, R_rect, T_base_left, scenario.surface
            )
            results['depth'][topic] = evaluation.depth_errors(
                depth, P_rect, R_rect, T_base_left, scenario.surface
            )
            data['depth_true'] = evaluation.true_rectified_depth(
                cameras['left'], depth_true['left'], R_rect, P_rect, depth.shape
            )

    if not track:
        data.update(tool_all=np.empty((0, 3)), tool_tracking=np.empty((0, 3)), windows=[])
        return results, data
    windows = phase_windows(messages[DIAGNOSTICS_TOPIC], 'tracking')
    tool = [(t, m) for t, m in messages[TOOL_POSE_TOPIC] if inside(t, windows)]
    force = [(t, m.wrench.force.z) for t, m in messages[PRESSURE_TOPIC] if inside(t, windows)]
    tool_points = np.array(
        [[m.pose.position.x, m.pose.position.y, m.pose.position.z] for _, m in tool]
    ).reshape(-1, 3)
    if len(tool_points) and force:
        results['tracking'] = evaluation.tracking_errors(
            tool_points, curve, [f for _, f in force], DESIRED_FORCE, scenario.surface
        )
    data['tool_all'] = np.array(
        [
            [m.pose.position.x, m.pose.position.y, m.pose.position.z]
            for _, m in messages[TOOL_POSE_TOPIC]
        ]
    ).reshape(-1, 3)
    data['tool_tracking'] = tool_points
    data['tool_distances'] = (
        evaluation.tool_path_distances(tool_points, curve, scenario.surface)
        if len(tool_points)
        else (np.empty(0), np.empty(0))
    )
    data['windows'] = windows
    return results, data


def checks(results, track):
    """(measure, value, tolerance, passed) rows of the summary (no tracking rows when the
    demo did not track)."""
    rows = []

    def check(name, value, smaller_is_better=True):  # a missing value is inf (failed)
        tolerance = TOLERANCES[name]
        ok = value <= tolerance if smaller_is_better else value >= tolerance
        rows.append((name, value, tolerance, bool(ok)))

    calibration = results['calibration']
    check(
        'calibration image RMS [px]',
        max(calibration[n]['image_rms_px'] for n in ('left', 'right', 'aux')),
    )
    check('curve RMS [mm]', results['curve']['rms_m'] * 1e3)
    check('curve coverage [mm]', results['curve']['coverage_m'] * 1e3)
    fused = results['depth'].get(FUSED_DEPTH_TOPIC)
    check('fused depth median [mm]', fused['median_abs_m'] * 1e3 if fused else np.inf)
    if not track:
        return rows
    tracking = results.get('tracking')
    check('tool path RMS [mm]', tracking['path_rms_m'] * 1e3 if tracking else np.inf)
    check(
        'force in band [%]',
        tracking['force_in_band'] * 100 if tracking else 0.0,
        smaller_is_better=False,
    )
    return rows


def plot_report(report_dir, messages, data):
    figures = []

    def save(fig, file, title, tight=True):
        if tight:
            fig.tight_layout()
        fig.savefig(report_dir / file, dpi=80)
        plt.close(fig)
        figures.append((title, file))

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, (name, topic) in zip(axes, IMAGE_TOPICS.items()):
        images = messages.get(topic, [])
        ax.axis('off')
        if images:
            ax.imshow(image_to_numpy(images[-1][1]), cmap='gray', vmin=0, vmax=255)
            ax.set_title(f'{name}: last capture', fontsize=9)
    save(fig, 'views.png', 'The three views')

    plot_curve(data, save)
    plot_depth(data, save)

    joint_states = messages.get(JOINT_STATES_TOPIC, [])
    pressure = messages.get(PRESSURE_TOPIC, [])
    if joint_states:
        fig, (ax_q, ax_f) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        t0 = joint_states[0][0]
        t = (np.array([log_time for log_time, _ in joint_states]) - t0) * 1e-9
        q = np.array([m.position for _, m in joint_states])
        for j in range(q.shape[1]):
            ax_q.plot(t, q[:, j], label=joint_states[0][1].name[j])
        ax_q.set_ylabel('joint position [rad]')
        ax_q.legend(fontsize=7, ncol=4)
        tp = (np.array([log_time for log_time, _ in pressure]) - t0) * 1e-9
        ax_f.plot(tp, [m.wrench.force.z for _, m in pressure], lw=0.6)
        ax_f.axhspan(
            0.9 * DESIRED_FORCE, 1.1 * DESIRED_FORCE, color='g', alpha=0.15, label='desired +-10 %'
        )
        for a, b in data['windows']:
            ax_f.axvspan((a - t0) * 1e-9, (b - t0) * 1e-9, color='b', alpha=0.05)
        ax_f.set_ylabel('contact force [N]')
        ax_f.set_xlabel('time [s] (blue: tracking)')
        ax_f.legend(fontsize=7)
        save(fig, 'arm.png', 'Joint trajectories and contact force')
    return figures


def plot_curve(data, save):
    """curve.png: the curve, waypoints and tool path in 3D, and their distances to the
    true curve, each with the definition the summary table uses."""
    fig = plt.figure(figsize=(11, 5))
    ax = fig.add_subplot(1, 2, 1, projection='3d')
    for piece in data['curve']:
        ax.plot(*piece.T, 'k-', lw=1, label='true curve')
    ax.plot(*data['waypoints'].T, 'r.', ms=2, label='waypoints')
    if len(data['tool_tracking']):
        ax.plot(*data['tool_tracking'].T, 'b-', lw=0.8, label='tool tip (tracking, pressed in)')
    ax.set_xlabel('x [m]', fontsize=8)
    ax.set_ylabel('y [m]', fontsize=8)
    ax.set_zlabel('z [m]', fontsize=8)
    ax.set_title('curve, waypoints and tool path in base_link', fontsize=9)
    handles, labels = ax.get_legend_handles_labels()
    ax.legend(dict(zip(labels, handles)).values(), dict(zip(labels, handles)).keys(), fontsize=7)
    ax2 = fig.add_subplot(1, 2, 2)
    d = evaluation.distance_to_polylines(data['waypoints'], data['curve']) * 1e3
    ax2.plot(d, 'r-', lw=0.8, label=f'waypoint to true curve (RMS {_rms(d):.2f} mm)')
    if len(data['tool_tracking']):
        on_surface, in_3d = (x * 1e3 for x in data['tool_distances'])
        t = np.linspace(0, len(d), len(on_surface))
        ax2.plot(
            t,
            on_surface,
            'b-',
            lw=0.8,
            label=f'tool path: tip on the surface to true curve (RMS {_rms(on_surface):.2f} mm)',
        )
        ax2.plot(
            t,
            in_3d,
            'c-',
            lw=0.6,
            alpha=0.7,
            label=f'pressed tip in 3D to true curve, pressing included (RMS {_rms(in_3d):.2f} mm)',
        )
    ax2.set_ylabel('distance to the true curve [mm]')
    ax2.set_xlabel('waypoint index (tool samples stretched over it)')
    ax2.legend(fontsize=7)
    save(fig, 'curve.png', 'Reconstructed curve and tool path against the true curve')


def _rms(values):
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else float('nan')


def plot_depth(data, save):
    """depth.png: the true depth beside each estimate on one colour scale (top row) and
    each estimate's height above the true surface, the report's depth measure (bottom)."""
    depths = data['depth']
    if not depths:
        return
    columns = [('true depth', data['depth_true'])] + list(depths.items())
    fig, axes = plt.subplots(2, len(columns), figsize=(4.0 * len(columns), 6.4), squeeze=False)
    finite = np.concatenate([d[np.isfinite(d)] for _, d in columns if d is not None])
    low, high = np.percentile(finite, [2, 98]) if finite.size else (0, 1)
    limit_mm = 10.0  # the colour scale of the height panels, +- [mm]
    for column, (name, depth) in enumerate(columns):
        top, bottom = axes[0, column], axes[1, column]
        top.axis('off')
        bottom.axis('off')
        if depth is None:
            continue
        shown = top.imshow(depth, vmin=low, vmax=high, cmap='viridis')
        top.set_title(f'{name} [m]', fontsize=9)
        heights = data['depth_heights'].get(name)
        if heights is None:
            bottom.set_title('(the truth)', fontsize=8)
            continue
        error = bottom.imshow(heights * 1e3, vmin=-limit_mm, vmax=limit_mm, cmap='RdBu_r')
        median = np.nanmedian(np.abs(heights)) * 1e3 if np.isfinite(heights).any() else np.nan
        bottom.set_title(
            f'height above the true surface\n(median |h| {median:.1f} mm)', fontsize=8
        )
    fig.colorbar(shown, ax=axes[0, :], shrink=0.8, label='depth [m]')
    fig.colorbar(error, ax=axes[1, :], shrink=0.8, label='height above true surface [mm]')
    save(
        fig, 'depth.png', 'Depth: truth, SFS, fused, sparse stereo, and their errors', tight=False
    )


def message_rows(messages_counts, counts_rosbags, published):
    """(topic, sent, in bag by mcap, in bag by rosbags, lost) for every topic."""
    rows = []
    for topic in sorted(set(messages_counts) | set(counts_rosbags)):
        sent = published.get(topic)
        n = messages_counts.get(topic, 0)
        rows.append(
            (topic, sent, n, counts_rosbags.get(topic, 0), None if sent is None else sent - n)
        )
    return rows


def write_report(report_dir, bag_dir, scenario, results, check_rows, rows, figures, timings):
    lines = [
        f'# Demo report: {bag_dir.name}',
        '',
        f'Scenario `{scenario.name}` ({scenario.path}), seed {scenario.seed}; '
        f'wall time {timings["total_s"]:.0f} s.',
        '',
        '## Summary',
        '',
        '| measure | value | tolerance | |',
        '|---|---|---|---|',
    ]
    lines += [
        f'| {n} | {v:.3f} | {"<=" if n != "force in band [%]" else ">="} {t} | '
        f'{"ok" if ok else "**FAILED**"} |'
        for n, v, t, ok in check_rows
    ]
    lines += ['', '## Measures', '']
    lines += [f'- **{name}**: {definition}' for name, definition in MEASURES]
    lines += [
        '',
        '## Measurements',
        '',
        '```',
        json.dumps(results, indent=1),
        '```',
        '',
        '## Messages',
        '',
        '| topic | sent | in bag (mcap) | in bag (rosbags) | lost |',
        '|---|---|---|---|---|',
    ]
    lines += [
        f'| `{t}` | {"" if s is None else s} | {n} | {m} | {"" if lost is None else lost} |'
        for t, s, n, m, lost in rows
    ]
    lines += [
        '',
        '"sent" is what the publishing nodes counted (their "published:" log line at '
        'shutdown); /rosout and /parameter_events are not counted.',
        '',
    ]
    for title, file in figures:
        lines += [f'## {title}', '', f'![{title}]({file})', '']
    (report_dir / 'report.md').write_text('\n'.join(lines))


def parse_args():
    """The command line: the scenario, where the bags go, the time limit and which nodes
    run on another host."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scenario', default='default', help='shipped name or file')
    parser.add_argument('--bags', type=Path, default=REPO_ROOT / 'bags')
    parser.add_argument('--timeout', type=float, default=600.0, help='give up after this long [s]')
    parser.add_argument(
        '--remote-nodes',
        nargs='+',
        default=[],
        metavar='NODE',
        help='nodes started through --remote-prefix (another host)',
    )
    parser.add_argument(
        '--remote-prefix',
        default='',
        metavar='COMMAND',
        help='command before each remote node, e.g. "ip netns exec B" '
        "(the multi-host test's simulated second machine)",
    )
    return parser.parse_args()


def chart_views(scenario):
    """How many chart views calibration takes: every chart pose, captured
    ``captures_per_pose`` times."""
    return len(scenario.calibration.T_base_chart) * scenario.calibration.captures_per_pose


def announce_live_view():
    """A port for live_view, printed with how to watch the run in Foxglove."""
    layout = Path(get_package_share_directory('live_view')) / 'layouts' / 'vgm_live_view.json'
    live_view_port = free_live_view_port()
    print(
        f'   watch it live: in Foxglove, Open connection > Foxglove WebSocket > '
        f'ws://127.0.0.1:{live_view_port} (layout: {layout})',
        flush=True,
    )
    return live_view_port


def demo_params(scenario, bags, name, work_dir, live_view_port):
    """The demo's settings over the graph's params file, {node: {parameter: value}}: the
    bag ``bags``/``name``, the scenario with its ground truth and calibration written to
    ``work_dir``, and what the stages must know of the chart, the scene and the arm."""
    light = light_in_left_optical_frame(scenario)
    return {
        'recorder': {'output_dir': str(bags), 'bag_name': name, 'compression': 'zstd'},
        'live_view': {'port': live_view_port},
        'sensor_sim': {
            'scenario': str(scenario.path),
            'ground_truth_dir': str(work_dir / 'ground_truth'),
            # no message is lost to discovery: the recorder has matched every
            # stream, and calib_node and curve_recon_node every camera (a count
            # alone was met by the pipeline while the recorder was starting)
            'wait_for_nodes': ['recorder'],
            'min_subscribers': 3,
        },
        'calib_node': {
            'min_views': chart_views(scenario),
            'output_dir': str(work_dir / 'calibration'),
            'chart.rows': scenario.calibration.rows,
            'chart.cols': scenario.calibration.cols,
            'chart.spacing': scenario.calibration.spacing,
        },
        'curve_recon_node': {'degree': CURVE_DEGREES.get(scenario.curve.kind, 2)},
        'sfs_stereo_node': {
            'light_direction': [float(v) for v in light],
            'albedo': scenario.surface.albedo,
            'roughness': scenario.surface.roughness,
        },
        # The recorder has matched every stream and live_view /tool_pose (its /tf)
        # before the loop starts (a remote arm's endpoints are discovered later than the
        # simulator's). live_view is not named: it subscribes the joint commands only
        # while a Foxglove viewer watches them, so without a viewer the gate would hold
        # the arm for its whole timeout.
        'pa10_ik_node': {
            'wait_for_nodes': ['recorder'],
            'min_subscribers': 2,
            'robot': scenario.robot.model,
            'tool_length': scenario.robot.tool_length,
            'tip_frame': scenario.robot.tip_frame,
            'desired_force': DESIRED_FORCE,
        },
    }


def run_graph(args, params_file, log_path, nodes, track, views):
    """Start ``nodes`` as processes (logging to ``log_path``), run the closed loop until it
    is over, fails or times out, and stop them: (the launcher's exit status, why the loop
    failed or None, the launcher, when the loop started [monotonic s])."""
    log_file = open(log_path, 'w')
    launch = Launch(
        params_file,
        nodes=nodes,
        out=log_file,
        command_prefixes={node: shlex.split(args.remote_prefix) for node in args.remote_nodes},
    )
    probe = DemoProbe()
    loop = ClosedLoop(launch, probe, STAGES, track)
    stage(2, STAGES, f'calibrating the rig from {views} chart views')
    started = time.monotonic()
    try:
        status = launch.run(duration=args.timeout, until=loop)
    finally:
        probe.close()
        log_file.close()
    return status, loop.failure, launch, started


def move_into_bag(work_dir, bag_dir):
    """Move the run's ground truth, calibration, node log and params file from
    ``work_dir`` into the bag directory, and remove ``work_dir``."""
    for item in ('ground_truth', 'calibration'):
        if (work_dir / item).exists():
            shutil.move(str(work_dir / item), str(bag_dir / item))
    for item in ('launch.log', 'params.yaml'):
        shutil.move(str(work_dir / item), str(bag_dir / item))
    work_dir.rmdir()


def print_failure(failure, bag_dir):
    """Why the run failed, and the last node log lines, on stderr."""
    print(f'FAILED: {failure or "a node failed"}; last node log lines:', file=sys.stderr)
    print(''.join((bag_dir / 'launch.log').read_text().splitlines(True)[-40:]), file=sys.stderr)


def read_recording(bag_dir):
    """The bag read with both readers: the decoded BAG_TOPICS {topic: [(log_time, msg)]}
    and every topic's count by mcap and by rosbags."""
    messages, counts_mcap = read_bag(bag_dir, BAG_TOPICS)
    return messages, counts_mcap, count_with_rosbags(bag_dir)


def published_counts(launch, nodes, messages):
    """What every node but the recorder says it published, per topic, and the recorder's
    own diagnostics in the bag."""
    published = Counter()
    for node in nodes[1:]:
        published.update(parse_published_counts(launch.log_text(node)))
    # The recorder's own diagnostics: its last ones follow the bag's closing, so those in
    # the bag are all that can be compared.
    published[DIAGNOSTICS_TOPIC] += sum(
        1
        for _, m in messages[DIAGNOSTICS_TOPIC]
        if m.status and m.status[0].name.startswith('recorder:')
    )
    return published


def write_results(report_dir, results, check_rows, rows, timings):
    """results.json: the measures, the summary's checks, the message counts and the
    timings."""
    (report_dir / 'results.json').write_text(
        json.dumps(
            {'results': results, 'checks': check_rows, 'messages': rows, 'timings': timings},
            indent=1,
        )
    )


def print_summary(check_rows, rows, bag_dir, report_dir, timings):
    """The summary table, the message counts, and where the bag and the report are."""
    print(f'\n{"measure":30} {"value":>10} {"tolerance":>10}')
    for measure, value, tolerance, ok in check_rows:
        print(f'{measure:30} {value:10.3f} {tolerance:10} {"ok" if ok else "FAILED"}')
    print(f'\n{"topic":36} {"sent":>7} {"mcap":>7} {"rosbags":>8} {"lost":>5}')
    for topic, sent, n_mcap, n_rosbags, lost in rows:
        print(
            f'{topic:36} {"" if sent is None else sent:>7} {n_mcap:7d} {n_rosbags:8d} '
            f'{"" if lost is None else lost:>5}'
        )
    print(
        f'\nbag:    {bag_dir}\nreport: {report_dir / "report.md"}\n'
        f'time:   {timings["total_s"]:.0f} s'
    )


def verdict(check_rows, rows):
    """The exit status, printed as a verdict: 1 if a stage missed its tolerance, a message
    was lost or the two readers' counts differ, else 0."""
    lost = [row[0] for row in rows if row[4] not in (None, 0)]
    disagree = [row[0] for row in rows if row[2] != row[3]]
    failed = [row[0] for row in check_rows if not row[3]]
    if lost or disagree or failed:
        print(
            f'FAILED: out of tolerance: {failed}; messages lost: {lost}; reader counts '
            f'differ: {disagree}',
            file=sys.stderr,
        )
        return 1
    print('OK: every stage within tolerance, nothing lost, both readers agree')
    return 0


def main():
    args = parse_args()
    scenario = load_scenario(resolve_scenario_path(args.scenario).resolve())
    if scenario.calibration is None:
        print(
            f'scenario {scenario.name} has no calibration chart: the demo needs one',
            file=sys.stderr,
        )
        return 2
    track = curve_on_surface(scenario)
    nodes = NODES if track else [n for n in NODES if n != 'pa10_ik_node']
    name = f'demo-{datetime.now():%Y%m%d-%H%M%S}'
    bag_dir = args.bags / name
    work_dir = args.bags / f'.{name}-work'  # moved into the bag directory at the end
    work_dir.mkdir(parents=True)

    stage(1, STAGES, f'starting the graph on scenario {scenario.name}: {", ".join(nodes)}')
    print(f'   node logs: {bag_dir}/launch.log; bag: {bag_dir}', flush=True)
    live_view_port = announce_live_view()
    graph = Path(get_package_share_directory('vgm_common')) / 'params' / 'graph.yaml'
    params_file = work_dir / 'params.yaml'  # kept with the bag: how it was made
    settings = demo_params(scenario, args.bags, name, work_dir, live_view_port)
    write_params(graph, params_file, settings)
    status, failure, launch, started = run_graph(
        args, params_file, work_dir / 'launch.log', nodes, track, chart_views(scenario)
    )
    timings = {'graph_s': time.monotonic() - started}
    move_into_bag(work_dir, bag_dir)
    if status != 0 or failure:
        print_failure(failure, bag_dir)
        return 1

    stage(5, STAGES, 'reading the bag with mcap + mcap_ros2 and with rosbags')
    messages, counts_mcap, counts_rosbags = read_recording(bag_dir)
    published = published_counts(launch, nodes, messages)

    stage(6, STAGES, 'comparing with the ground truth and writing the report')
    results, data = evaluate(
        scenario, messages, bag_dir / 'ground_truth', bag_dir / 'calibration', track
    )
    check_rows = checks(results, track)
    rows = message_rows(counts_mcap, counts_rosbags, published)
    report_dir = bag_dir / 'report'
    report_dir.mkdir(exist_ok=True)
    figures = plot_report(report_dir, messages, data)
    timings['total_s'] = time.monotonic() - started
    write_report(report_dir, bag_dir, scenario, results, check_rows, rows, figures, timings)
    write_results(report_dir, results, check_rows, rows, timings)
    print_summary(check_rows, rows, bag_dir, report_dir, timings)
    return verdict(check_rows, rows)


if __name__ == '__main__':
    sys.exit(main())
