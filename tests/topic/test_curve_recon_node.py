"""Topic level, real processes: curve_recon_node reconstructs sensor_sim's curve from three
calibrated views (the true rig published as calib_node's `calibration_file` mode does),
compared with the simulator's ground truth; and its handling of bad input (no camera
info yet, mismatched stamps, the curve in one view only, no curve at all)."""

import time

import cv2
import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from scipy.spatial import cKDTree
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from vgm_evaluation.graph_probe import status_values
from vgm_evaluation.metrics import curve_agreement

from harness import SCENARIO_DIR, executable, publish_rig, wait_for
from sensor_sim.scenario import load_scenario
from vgm_common.calibration_io import read_calibration, stereo_rectification, write_calibration
from vgm_common.conversions import (
    camera_to_camera_info,
    numpy_to_image,
    path_to_matrices,
    pointcloud2_to_points,
    stamp_to_ns,
)
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import (
    CURVE_POINTS_TOPIC,
    DEPTH_INFO_TOPIC,
    FUSED_DEPTH_TOPIC,
    IMAGE_TOPICS,
    OPTICAL_FRAMES,
    TARGET_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)

SPACING = 0.005  # [m] the default


class Probe:
    """What the test node receives from curve_recon_node."""

    def __init__(self, node):
        self.graph = node.graph
        self.graph.watch_diagnostics()
        self.statuses = self.graph.statuses
        self.paths = self.graph.record(WAYPOINTS_TOPIC, Path, LATCHED_QOS)
        self.clouds = self.graph.record(CURVE_POINTS_TOPIC, PointCloud2)

    def diagnostic(self, name, containing=''):
        return self.graph.status(f'curve_recon_node: {name}', containing)


def run_scenario(
    spawn, rclpy_node, tmp_path, scenario, node_args=(), calibration_phase=False, rate=2.0
):
    """sensor_sim on ``scenario`` + curve_recon_node + the true rig; returns the probe,
    the truth directory and the rig publishers (keep them)."""
    probe = Probe(rclpy_node)
    chart_stamps = []
    rclpy_node.create_subscription(
        PoseStamped,
        TARGET_POSE_TOPIC,
        lambda m: chart_stamps.append(stamp_to_ns(m.header.stamp)),
        DEFAULT_QOS,
    )
    spawn([executable('curve_recon_node'), '--ros-args', *node_args])
    truth = tmp_path / 'truth'
    spawn(
        [
            executable('sensor_sim'),
            '--ros-args',
            '-p',
            f'scenario:={scenario}',
            '-p',
            f'calibration_phase:={str(calibration_phase).lower()}',
            '-p',
            f'ground_truth_dir:={truth}',
            '-p',
            'min_subscribers:=1',
            '-p',
            f'rate:={rate}',
        ]
    )
    calibration = truth / 'true_calibration' / 'calibration.yaml'
    wait_for(
        lambda: calibration.exists() and (truth / 'curve_base.npz').exists(),
        90,
        'sensor_sim ground truth',
    )
    # the ground truth files are written one after another: wait for the last one
    wait_for(lambda: (truth / 'depth_aux.npy').exists(), 30, 'the depth ground truth')
    publishers, _ = publish_rig(rclpy_node, calibration)
    return probe, truth, publishers, chart_stamps


def check_waypoints(path, truth_dir, rms_tol, max_tol, coverage_tol):
    """Waypoints against the true polylines; returns the measured numbers."""
    poses = path_to_matrices(path)
    points = poses[:, :3, 3]
    with np.load(truth_dir / 'curve_base.npz') as data:
        true_curve = np.vstack([data[k] for k in data.files])
    # coverage: every true point near the waypoint polyline (Hausdorff, other direction)
    agreement = curve_agreement(points, true_curve)
    rms, worst, coverage = agreement.rms_m, agreement.max_m, agreement.farthest_uncovered_m
    assert path.header.frame_id == 'base_link'
    assert rms < rms_tol, f'RMS {rms * 1e3:.3f} mm'
    assert worst < max_tol, f'max {worst * 1e3:.3f} mm'
    assert coverage < coverage_tol, f'coverage {coverage * 1e3:.2f} mm'
    # spacing respected: L / round(L / spacing) between neighbours, all within 10 %
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    assert np.all(np.abs(steps - SPACING) < 0.1 * SPACING), (steps.min(), steps.max())
    # orientation: x along the path, a proper rotation
    R = poses[:, :3, :3]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (len(R), 1, 1)), atol=1e-6
    )
    direction = np.diff(points, axis=0) / steps[:, None]
    assert np.median(np.sum(R[1:-1, :, 0] * direction[1:], axis=1)) > 0.98
    return rms, worst, coverage, points


@pytest.mark.parametrize(
    'scenario, degree, method, views, rms_tol, max_tol',
    [
        # the default loop on S3, noise 1 grey level: issue goal "well under 1 mm"; measured
        # 0.32 mm RMS, 1.5 mm max
        ('default', 2, 'ray_roots', 3, 0.6e-3, 3e-3),
        # the thesis's method through the node: measured 0.39 mm RMS, 2.9 mm max
        ('default', 2, 'cone_lsq', 3, 0.8e-3, 5e-3),
        # two views: only unique intersections (about a quarter of the loop here) are kept and
        # the rest is reported as ambiguous; no coverage claim
        ('default', 2, 'ray_roots', 2, 1e-3, 5e-3),
        # thesis fig. 3.4 ellipse, perfect stereo (0.2 m long): measured 0.07 mm RMS
        ('ch3_ellipse_perfect', 2, 'ray_roots', 3, 0.3e-3, 1e-3),
        # thesis fig. 3.13 non-planar cubic, general stereo: measured 0.07 mm RMS
        ('ch3_cubic_general', 3, 'ray_roots', 3, 0.3e-3, 1e-3),
    ],
)
def test_reconstructs_the_scenario_curve(
    spawn, rclpy_node, tmp_path, scenario, degree, method, views, rms_tol, max_tol
):
    probe, truth, publishers, _ = run_scenario(
        spawn,
        rclpy_node,
        tmp_path,
        scenario,
        ['-p', f'degree:={degree}', '-p', f'method:={method}', '-p', f'views:={views}'],
    )
    rclpy_node.spin_until(lambda: probe.paths, 90, 'waypoints')
    rclpy_node.spin_until(
        lambda: probe.diagnostic('reconstruction') and probe.clouds,
        10,
        'the reconstruction diagnostic and the points',
    )
    status = status_values(probe.diagnostic('reconstruction'))
    assert status['method'] == method and status['views'] == str(views)
    if views == 2:
        assert int(status['ambiguous']) > 0
        assert 'ambiguous' in probe.diagnostic('reconstruction').message
    closed = scenario in ('default', 'ch3_ellipse_perfect') and views == 3
    assert status['closed'] == str(closed)
    # open curves lose 3 line widths at each image end (trimmed): a few mm in 3D
    coverage_tol = 4e-3 if closed else (8e-3 if views == 3 else np.inf)
    rms, worst, coverage, points = check_waypoints(
        probe.paths[-1], truth, rms_tol, max_tol, coverage_tol
    )
    if closed:
        assert np.linalg.norm(points[0] - points[-1]) < 1.1 * SPACING  # not repeated
    raw = pointcloud2_to_points(probe.clouds[-1])
    assert len(raw) == int(status['points']) and len(raw) > len(points)
    print(
        f'{scenario} {method} {views} views: {len(points)} waypoints, RMS '
        f'{rms * 1e3:.3f} mm, max {worst * 1e3:.3f} mm, coverage {coverage * 1e3:.2f} mm; '
        f'{status}'
    )


def test_chart_captures_are_skipped_then_depth_normals_are_used(spawn, rclpy_node, tmp_path):
    """calibration_phase true: the chart captures (same stamp as a target pose) never
    become waypoints; then a fused depth arriving late makes the node republish with
    approach directions from the surface normals."""
    probe, truth, publishers, chart_stamps = run_scenario(
        spawn, rclpy_node, tmp_path, 'default', calibration_phase=True, rate=4.0
    )
    rclpy_node.spin_until(lambda: probe.paths, 60, 'waypoints')
    assert chart_stamps and stamp_to_ns(probe.paths[0].header.stamp) > max(chart_stamps)
    poses = path_to_matrices(probe.paths[-1])
    # no depth yet: z is the base's -z made orthogonal to x
    assert np.all(poses[:, 2, 2] < -0.5)
    # publish the true left depth as the fused depth, in the rectified left frame
    rig = read_calibration(truth / 'true_calibration')
    left, right = rig['left'][0], rig['right'][0]
    R_left, P_left = stereo_rectification(left, right)['left']
    depth_raw = np.load(truth / 'depth_left.npy')
    depth_rect = rectified_depth(left, depth_raw, R_left, P_left)
    info_pub = rclpy_node.create_publisher(CameraInfo, DEPTH_INFO_TOPIC, DEFAULT_QOS)
    depth_pub = rclpy_node.create_publisher(Image, FUSED_DEPTH_TOPIC, DEFAULT_QOS)
    rclpy_node.spin_until(lambda: depth_pub.get_subscription_count() > 0, 10, 'depth sub')

    def approach_from_depth(path):
        """Whether a path's approach axes are not the no-depth fallback (base -z made
        orthogonal to x). A capture reconstructed before the depth arrived can still be
        published after it, so counting paths is not enough."""
        poses = path_to_matrices(path)
        x = poses[:, :3, 0]
        fallback = -np.array([0.0, 0.0, 1.0]) + x[:, 2:3] * x
        fallback /= np.linalg.norm(fallback, axis=1, keepdims=True)
        return np.max(np.linalg.norm(poses[:, :3, 2] - fallback, axis=1)) > 0.01

    def publish_depth():
        info_pub.publish(camera_to_camera_info(left, 1, OPTICAL_FRAMES['left'], R_left, P_left))
        depth_pub.publish(
            numpy_to_image(depth_rect.astype(np.float32), '32FC1', 1, OPTICAL_FRAMES['left'])
        )
        return any(approach_from_depth(path) for path in probe.paths)

    deadline = time.monotonic() + 30
    while not publish_depth():
        assert time.monotonic() < deadline, 'no waypoints with approach from the depth'
        end = time.monotonic() + 0.5
        rclpy_node.spin_until(lambda end=end: time.monotonic() > end, 5, 'half a second')
    poses = path_to_matrices(next(p for p in probe.paths if approach_from_depth(p)))
    # the true surface normal at each waypoint, from the S3 surface: compare the approach
    # axis with the normal of the true surface points around it
    true_normals = surface_normals_at(truth, poses[:, :3, 3], left)
    z = poses[:, :3, 2]
    # z = -normal made orthogonal to x: compare after the same projection
    x = poses[:, :3, 0]
    expected = -true_normals + np.sum(true_normals * x, axis=1, keepdims=True) * x
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(z * expected, axis=1), -1, 1)))
    assert np.median(angle) < 2.0 and np.percentile(angle, 95) < 5.0, angle


def rectified_depth(camera, depth_raw, R_rect, P_rect):
    """Depth of the raw left image re-expressed as a depth image of the rectified frame."""
    H, W = depth_raw.shape
    v, u = np.mgrid[0:H, 0:W]
    xy = camera.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    points = np.column_stack([xy, np.ones(len(xy))]) * depth_raw.reshape(-1, 1)
    rect = points @ R_rect.T
    ok = np.all(np.isfinite(rect), axis=1) & (rect[:, 2] > 0)
    K = P_rect[:3, :3]
    uu = np.round(K[0, 0] * rect[ok, 0] / rect[ok, 2] + K[0, 2]).astype(int)
    vv = np.round(K[1, 1] * rect[ok, 1] / rect[ok, 2] + K[1, 2]).astype(int)
    inside = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
    out = np.full((H, W), np.nan)
    out[vv[inside], uu[inside]] = rect[ok, 2][inside]
    return out


def surface_normals_at(truth, points, camera):
    """Surface normals (toward the camera) at base points from the true left depth."""
    depth = np.load(truth / 'depth_left.npy')
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    xy = camera.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    cloud_cam = np.column_stack([xy, np.ones(len(xy))]) * depth.reshape(-1, 1)
    T = camera.T_base_camera
    cloud = cloud_cam @ T[:3, :3].T + T[:3, 3]
    cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
    tree = cKDTree(cloud)
    normals = []
    for p in points:
        patch = cloud[tree.query_ball_point(p, 0.01)]
        n = np.linalg.svd(patch - patch.mean(axis=0))[2][-1]
        normals.append(n if n @ (camera.centre_base - p) > 0 else -n)
    return np.array(normals)


# --- bad input: the test node publishes the images itself --------------------------


def ellipse_images(cameras, names_with_curve):
    """Grey images (uint8) of a 3D ellipse near the default scene, drawn as a 3 px dark
    line in the views ``names_with_curve``; plain grey in the others."""
    t = np.linspace(0, 2 * np.pi, 2000)
    centre = np.array([0.62, 0.0, 0.30])
    points = centre + np.column_stack([0.08 * np.cos(t), 0.05 * np.sin(t), 0.01 * np.sin(2 * t)])
    images = {}
    for name, camera in cameras.items():
        image = np.full((camera.height, camera.width), 160, np.uint8)
        if name in names_with_curve:
            pixels, _ = camera.project(points)
            cv2.polylines(
                image, [np.round(pixels * 16).astype(np.int32)], True, 60, 3, cv2.LINE_AA, shift=4
            )
        images[name] = image
    return images, points


@pytest.fixture
def bad_input_setup(spawn, rclpy_node, tmp_path):
    cameras = load_scenario(SCENARIO_DIR / 'default.yaml').cameras
    calibration = write_calibration(tmp_path / 'calib', dict(cameras), OPTICAL_FRAMES)
    probe = Probe(rclpy_node)
    publishers = {
        name: rclpy_node.create_publisher(Image, IMAGE_TOPICS[name], DEFAULT_QOS)
        for name in IMAGE_TOPICS
    }
    node = spawn([executable('curve_recon_node'), '--ros-args', '-p', 'service_timeout:=5.0'])
    rclpy_node.spin_until(
        lambda: all(p.get_subscription_count() for p in publishers.values()),
        30,
        'the node subscribing',
    )
    return cameras, calibration, probe, publishers, node


def test_bad_input_gives_diagnostics_and_no_waypoints(bad_input_setup, rclpy_node):
    cameras, calibration, probe, publishers, node = bad_input_setup
    stamp = [1_000_000_000]

    def publish(images, stamps=None):
        stamp[0] += 100_000_000
        for i, (name, image) in enumerate(images.items()):
            s = stamp[0] if stamps is None else stamp[0] + stamps[i]
            publishers[name].publish(numpy_to_image(image, 'mono8', s, OPTICAL_FRAMES[name]))

    def spin_publishing(images, condition, timeout, what, stamps=None):
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, f'timed out waiting for {what}'
            publish(images, stamps)
            end = time.monotonic() + 0.3
            rclpy_node.spin_until(lambda end=end: condition() or time.monotonic() > end, 2, what)

    good, ellipse = ellipse_images(cameras, ('left', 'right', 'aux'))
    one_view, _ = ellipse_images(cameras, ('left',))

    # 1. no camera info yet: nothing to reconstruct with. The curve is in one view only,
    # so a capture that a loaded machine delivers after the calibration cannot become
    # waypoints either.
    def uncalibrated_capture_seen():
        status = probe.diagnostic('status', 'no camera info yet')
        return status is not None and int(status_values(status)['matched']) >= 2

    spin_publishing(one_view, uncalibrated_capture_seen, 20, "'no camera info yet'")
    assert not probe.paths
    rig_publishers, _ = publish_rig(rclpy_node, calibration)
    # 2. mismatched stamps: never a complete capture
    spin_publishing(
        good,
        lambda: probe.diagnostic('status', 'not synchronized'),
        20,
        "'not synchronized'",
        stamps=[0, 1000, 2000],
    )
    assert int(status_values(probe.diagnostic('status', 'not synchronized'))['dropped']) > 0
    assert not probe.paths
    # 3. the curve in one view only: 'no curve', also as the service's answer
    spin_publishing(
        one_view, lambda: probe.diagnostic('rejected no curve'), 20, "'no curve' for one view"
    )
    assert 'right' in probe.diagnostic('rejected no curve').message
    client = rclpy_node.create_client(Trigger, '/curve_recon_node/reconstruct')
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(Trigger.Request())
    spin_publishing(one_view, future.done, 20, 'the service answer')
    assert not future.result().success and 'no curve' in future.result().message
    # 4. no curve at all (blank images)
    blank, _ = ellipse_images(cameras, ())
    count = sum(s.name.endswith('rejected no curve') for s in probe.statuses)
    spin_publishing(
        blank,
        lambda: sum(s.name.endswith('rejected no curve') for s in probe.statuses) > count,
        20,
        "'no curve'",
    )
    assert not probe.paths and node.alive()
    # 5. still serving: a good capture gives waypoints on the drawn ellipse. The "next"
    # capture may still be a blank one in flight on a loaded machine: then the answer
    # is 'no curve' and the next call takes a good one.
    for _ in range(3):
        future = client.call_async(Trigger.Request())
        spin_publishing(good, future.done, 30, 'the service answer')
        if future.result().success:
            break
        assert 'no curve' in future.result().message
    assert future.result().success and 'published' in future.result().message
    rclpy_node.spin_until(lambda: probe.paths, 10, 'waypoints')
    points = path_to_matrices(probe.paths[-1])[:, :3, 3]
    distance, _ = cKDTree(ellipse).query(points)
    assert np.sqrt(np.mean(distance**2)) < 1e-3  # drawn with 1/16 px rounding by OpenCV
    assert 'Traceback' not in node.output()


def test_bad_parameter_is_refused_at_start_up(spawn, rclpy_node):
    node = spawn([executable('curve_recon_node'), '--ros-args', '-p', 'method:=magic'])
    wait_for(lambda: not node.alive(), 30, 'the node to exit')
    assert node.proc.returncode == 2
    assert "parameter 'method'" in node.output() and 'Traceback' not in node.output()


class WedgeSession:
    """The test node's handles on a curve_recon_node fed good captures: its ~/reconstruct
    and parameter services, and the probe of what it publishes."""

    def __init__(self, rclpy_node, probe, publishers, good):
        self.rclpy_node, self.probe, self.publishers, self.good = (
            rclpy_node,
            probe,
            publishers,
            good,
        )
        self.stamp = 2_000_000_000
        self.client = rclpy_node.create_client(Trigger, '/curve_recon_node/reconstruct')
        self.get_client = rclpy_node.create_client(
            GetParameters, '/curve_recon_node/get_parameters'
        )
        self.set_client = rclpy_node.create_client(
            SetParameters, '/curve_recon_node/set_parameters'
        )

    def publish_capture(self):
        self.stamp += 100_000_000
        for name, image in self.good.items():
            self.publishers[name].publish(
                numpy_to_image(image, 'mono8', self.stamp, OPTICAL_FRAMES[name])
            )

    def call(self, c, request, timeout, what):
        future = c.call_async(request)
        self.rclpy_node.spin_until(future.done, timeout, what)
        return future.result()

    def pause(self, seconds, condition=lambda: False):
        """Spin for up to ``seconds`` [s] (between publications), less if ``condition``."""
        end = time.monotonic() + seconds
        self.rclpy_node.spin_until(
            lambda: condition() or time.monotonic() > end, seconds + 2, 'a pause'
        )

    def reconstruct(self, what, must_succeed=True):
        """A call answered by the next capture (published until it is answered)."""
        future = self.client.call_async(Trigger.Request())
        deadline = time.monotonic() + 40
        while not future.done():
            assert time.monotonic() < deadline, f'no answer: {what}'
            self.publish_capture()
            self.pause(0.3, future.done)
        if must_succeed:
            assert future.result().success, (what, future.result().message)
        return future.result()

    def set_parameter(self, name, value, kind):
        field = {
            ParameterType.PARAMETER_DOUBLE: 'double_value',
            ParameterType.PARAMETER_INTEGER: 'integer_value',
        }[kind]
        value_msg = ParameterValue(type=kind, **{field: value})
        result = self.call(
            self.set_client,
            SetParameters.Request(parameters=[ParameterMsg(name=name, value=value_msg)]),
            20,
            f'set {name}',
        )
        assert result.results[0].successful, result.results[0].reason


def check_waiting_calls_leave_the_executor_free(session):
    """Four waiting ~/reconstruct calls: get_parameters answers at once, and every call is
    answered once captures come."""
    probe = session.probe
    waiting = [session.client.call_async(Trigger.Request()) for _ in range(4)]
    session.rclpy_node.spin_until(
        lambda: (s := probe.diagnostic('status')) is not None
        and status_values(s).get('waiting_requests') == '4',
        20,
        'the four calls waiting',
    )
    started = time.monotonic()
    answer = session.call(
        session.get_client, GetParameters.Request(names=['spacing']), 20, 'get_parameters'
    )
    assert time.monotonic() - started < 3.0 and answer.values[0].double_value == SPACING
    deadline = time.monotonic() + 40
    while not all(f.done() for f in waiting):
        assert time.monotonic() < deadline, 'the waiting calls were not all answered'
        session.publish_capture()
        session.pause(0.3, lambda: all(f.done() for f in waiting))
    assert all(f.result().success for f in waiting), [f.result().message for f in waiting]


def depth_publishers(rclpy_node):
    """Publishers of /depth/camera_info and /depth/fused, once the node subscribed."""
    info_pub = rclpy_node.create_publisher(CameraInfo, DEPTH_INFO_TOPIC, DEFAULT_QOS)
    depth_pub = rclpy_node.create_publisher(Image, FUSED_DEPTH_TOPIC, DEFAULT_QOS)
    rclpy_node.spin_until(
        lambda: depth_pub.get_subscription_count() > 0 and info_pub.get_subscription_count() > 0,
        10,
        'depth subs',
    )
    return info_pub, depth_pub


def check_huge_depth_projection_is_rejected(session, left, info_pub, depth_pub):
    """/depth/camera_info with P of 1e308: rejected, and the approach axes stay base -z."""
    probe = session.probe
    huge = camera_to_camera_info(left, 1, OPTICAL_FRAMES['left'])
    huge.p = [1e308] * 12
    plane = np.full((left.height, left.width), 0.5, np.float32)
    deadline = time.monotonic() + 20
    while not probe.diagnostic('rejected /depth/camera_info', 'P: '):
        assert time.monotonic() < deadline, 'huge P not rejected'
        info_pub.publish(huge)
        depth_pub.publish(numpy_to_image(plane, '32FC1', 1, OPTICAL_FRAMES['left']))
        session.pause(0.3)
    session.reconstruct('after the huge P')
    assert status_values(probe.diagnostic('reconstruction'))['normals'].startswith('base -z')


def check_bad_fused_depth_is_rejected(session, left, info_pub, depth_pub):
    """Fused depth negative, zero or 1e30 m: rejected, never used for approach axes."""
    probe = session.probe
    info = camera_to_camera_info(left, 1, OPTICAL_FRAMES['left'])
    for bad_value, count in ((-0.5, 1), (0.0, 2), (1e30, 3)):
        bad = np.full((left.height, left.width), bad_value, np.float32)
        deadline = time.monotonic() + 20
        while (
            sum(
                s.name.endswith('rejected /depth/fused') and 'no usable depth' in s.message
                for s in probe.statuses
            )
            < count
        ):
            assert time.monotonic() < deadline, f'depth {bad_value} not rejected'
            info_pub.publish(info)
            depth_pub.publish(numpy_to_image(bad, '32FC1', 1, OPTICAL_FRAMES['left']))
            session.pause(0.3)
        session.reconstruct(f'after depth {bad_value}')
        assert status_values(probe.diagnostic('reconstruction'))['normals'].startswith('base -z')


def check_spacing_longer_than_the_loop(session):
    """`spacing` 0.5 and 1.0 on a loop 0.4 m long: at least 3 waypoints with proper
    rotations; then the default spacing again."""
    probe = session.probe
    for spacing in (0.5, 1.0):
        session.set_parameter('spacing', spacing, ParameterType.PARAMETER_DOUBLE)
        count = len(probe.paths)
        session.reconstruct(f'spacing {spacing}')
        session.rclpy_node.spin_until(lambda count=count: len(probe.paths) > count, 10, 'a path')
        poses = path_to_matrices(probe.paths[-1])
        assert len(poses) >= 3
        R = poses[:, :3, :3]
        np.testing.assert_allclose(
            R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (len(R), 1, 1)), atol=1e-6
        )
    session.set_parameter('spacing', SPACING, ParameterType.PARAMETER_DOUBLE)


def check_views_changed_at_run_time(session, ellipse):
    """`views` 3 -> 2 -> 3 at run time: an answer each time, and with 3 views again
    waypoints on the drawn ellipse."""
    probe = session.probe
    # Two views of this ellipse are ambiguous almost everywhere (it lies near the
    # epipolar plane's direction): a clear 'no curve' answer is right then; what matters
    # is an answer from a reconstruction, not a wedge
    session.set_parameter('views', 2, ParameterType.PARAMETER_INTEGER)
    answer = session.reconstruct('views 2', must_succeed=False)
    assert answer.success or 'ambiguous' in answer.message, answer.message
    if answer.success:
        assert status_values(probe.diagnostic('reconstruction'))['views'] == '2'
    session.set_parameter('views', 3, ParameterType.PARAMETER_INTEGER)
    session.reconstruct('views 3 again')
    assert status_values(probe.diagnostic('reconstruction'))['views'] == '3'
    points = path_to_matrices(probe.paths[-1])[:, :3, 3]
    assert np.sqrt(np.mean(cKDTree(ellipse).query(points)[0] ** 2)) < 1e-3


def test_bad_depth_runtime_parameters_and_waiting_calls_never_wedge(bad_input_setup, rclpy_node):
    """Wedges and depth sanity, each of which killed or blocked the node:
    ~/reconstruct calls waiting for a capture leave the executor free (get_parameters
    answers at once, every call is answered when a capture comes); /depth/camera_info
    with P of 1e308 and fused depth that is negative, zero or 1e30 m are rejected with a
    reason and never give approach axes; `spacing` 0.5 and 1.0 (the loop is 0.4 m long)
    and `views` 3 -> 2 -> 3 at run time still give waypoints with proper rotations."""
    cameras, calibration, probe, publishers, node = bad_input_setup
    rig_publishers, _ = publish_rig(rclpy_node, calibration)
    good, ellipse = ellipse_images(cameras, ('left', 'right', 'aux'))
    session = WedgeSession(rclpy_node, probe, publishers, good)
    for c in (session.client, session.get_client, session.set_client):
        assert c.wait_for_service(timeout_sec=20)

    # wedge 6: four waiting calls (more than the executor's three threads), no capture
    check_waiting_calls_leave_the_executor_free(session)
    # wedge 3: huge P entries in /depth/camera_info
    left = cameras['left']
    info_pub, depth_pub = depth_publishers(rclpy_node)
    check_huge_depth_projection_is_rejected(session, left, info_pub, depth_pub)
    # fused depth negative, zero or 1e30 m: rejected, never used for approach axes
    check_bad_fused_depth_is_rejected(session, left, info_pub, depth_pub)
    # wedge 4: spacing 0.5 and 1.0 on a loop 0.4 m long
    check_spacing_longer_than_the_loop(session)
    # wedge 5: views 3 -> 2 -> 3 at run time
    check_views_changed_at_run_time(session, ellipse)
    assert node.alive() and 'Traceback' not in node.output()


# --- generated draws unlike the shipped scenarios -------------------------


@pytest.mark.parametrize(
    'family, seed, noise_grey, max_m',
    [
        ('self_approaching', 1, 2.0, None),  # a closed space curve passing near itself
        ('planar_cubic', 2, 2.0, None),  # a tilted planar cubic with an inflection
        # a (2, 3) torus knot: its image crosses itself 3-6 times in every view, one
        # closed curve only if extraction follows the strands through the crossings
        # (before, the longest chain between crossings: in the bench, this draw
        # noise-free gave 7.3 mm RMS and 0.7 % of the knot)
        ('torus_knot', 1, 2.0, 1e-3),
        # a wavy closed loop on a sphere, the aux camera 20-45 deg oblique: the user's
        # case of this kind gave 3.1 mm excursions where triangulation had none
        ('sphere_loop', 1, 2.0, 1e-3),
        # an open helix, a stretch of it foreshortened in one view
        ('helix', 0, 2.0, 1e-3),
    ],
)
def test_generated_draw_within_bench_bounds_and_not_worse_than_triangulation(
    spawn, rclpy_node, tmp_path, family, seed, noise_grey, max_m
):
    """A generated curve and rig (vgm_evaluation.curve_families: f 400-1400 px, k1 down to
    -0.4, an oblique third camera) through the node: waypoints within the bench's goals
    (RMS < 1 mm, > 90 % of the true curve within 3 mm, and where given every waypoint
    within ``max_m`` of it), a closed curve published closed, and an RMS at or below the
    triangulation reference's on the same images and calibration."""
    from vgm_evaluation.curve_families import generate_case

    from curve_recon_node.pipeline import ReconstructionSettings, view_curve
    from curve_recon_node.reference import triangulate_views
    from sensor_sim.render import SceneRenderer, add_noise

    case = generate_case(family, seed, noise_grey=noise_grey)
    cameras = case.scenario.cameras
    renderer = SceneRenderer(case.scenario)
    images = {
        name: add_noise(renderer.scene_image(name), noise_grey, np.random.default_rng([seed, i]))
        for i, name in enumerate(('left', 'right', 'aux'))
    }
    calibration = write_calibration(tmp_path / 'calib', dict(cameras), OPTICAL_FRAMES)
    probe = Probe(rclpy_node)
    publishers = {
        name: rclpy_node.create_publisher(Image, IMAGE_TOPICS[name], DEFAULT_QOS)
        for name in IMAGE_TOPICS
    }
    node = spawn(
        [
            executable('curve_recon_node'),
            '--ros-args',
            '-p',
            f'degree:={case.degree}',
            '-p',
            f'line_width_px:={case.line_width_px:.3f}',
        ]
    )
    rig_publishers, _ = publish_rig(rclpy_node, calibration)
    rclpy_node.spin_until(
        lambda: all(p.get_subscription_count() for p in publishers.values()),
        30,
        'the node subscribing',
    )
    stamp = [3_000_000_000]
    deadline = time.monotonic() + 60
    while not probe.paths:  # the calibration's arrival triggers one reconstruction
        assert time.monotonic() < deadline, 'no waypoints'
        stamp[0] += 100_000_000
        for name, image in images.items():
            publishers[name].publish(
                numpy_to_image(image, 'mono8', stamp[0], OPTICAL_FRAMES[name])
            )
        end = time.monotonic() + 0.5
        rclpy_node.spin_until(
            lambda end=end: probe.paths or time.monotonic() > end, 2, 'waypoints'
        )
    points = path_to_matrices(probe.paths[-1])[:, :3, 3]
    ours = curve_agreement(points, case.truth_base, case.closed, case.closed)
    rms, worst, coverage = ours.rms_m, ours.max_m, ours.coverage
    # the reference on the same images, chains and calibration
    settings = ReconstructionSettings(degree=case.degree, line_width_px=case.line_width_px)
    views = [
        view_curve(images[n].astype(float), cameras[n], settings)[0]
        for n in ('left', 'right', 'aux')
    ]
    reference, _ = triangulate_views(views)
    reference_rms = curve_agreement(reference, case.truth_base, case.closed, case.closed).rms_m
    rclpy_node.spin_until(lambda: probe.diagnostic('reconstruction'), 10, 'the diagnostic')
    status = status_values(probe.diagnostic('reconstruction'))
    print(
        f'{family} seed {seed}: ours RMS {rms * 1e3:.3f} mm, max {worst * 1e3:.3f} mm, '
        f'coverage {coverage:.3f}, closed {status["closed"]}; triangulation RMS '
        f'{reference_rms * 1e3:.3f} mm'
    )
    assert rms < 1e-3 and coverage > 0.9
    assert max_m is None or worst < max_m
    assert status['closed'] == str(case.closed)
    assert rms <= reference_rms
    assert node.alive() and 'Traceback' not in node.output()


SIMULTANEOUS_CALLERS = 20


def test_simultaneous_reconstruct_callers_are_all_answered(spawn, rclpy_node):
    """Twenty callers of ~/reconstruct at once, no capture coming: every one is answered
    (no capture within service_timeout), none lost in a burst of replies."""
    node = spawn([executable('curve_recon_node'), '--ros-args', '-p', 'service_timeout:=2.0'])
    clients = [
        rclpy_node.create_client(Trigger, '/curve_recon_node/reconstruct')
        for _ in range(SIMULTANEOUS_CALLERS)
    ]
    rclpy_node.spin_until(
        lambda: all(c.service_is_ready() for c in clients), 30, 'every client to find the service'
    )
    futures = [c.call_async(Trigger.Request()) for c in clients]
    try:
        rclpy_node.spin_until(lambda: all(f.done() for f in futures), 30, 'every answer')
    except TimeoutError:
        answered = sum(f.done() for f in futures)
        raise AssertionError(
            f'{answered} of {SIMULTANEOUS_CALLERS} callers answered:\n{node.output()[-2000:]}'
        ) from None
    for future in futures:
        answer = future.result()
        assert not answer.success and 'no synchronized capture' in answer.message, answer
    assert node.alive() and 'Traceback' not in node.output()
