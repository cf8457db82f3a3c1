"""calib_node: calibrates the stereo pair and the aux camera from the chart on the precision
stage and publishes latched CameraInfo (plumb_bob, stereo rectification) and camera poses.

Captures are paired by identical stamp (left, right, aux images and the chart's target
pose). Chart detection and calibration run in a worker thread, so the executor keeps
taking images while a view is processed. With ``calibration_file`` set, the saved
calibration is published at start instead and no chart is needed.
"""

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from sensor_msgs.msg import CameraInfo
from std_srvs.srv import Trigger

from calib_node.bundle import bundle_adjust_selected
from calib_node.calibrate import LM_STARTS, METHODS, CalibrationError, GAOptions, calibrate_rig
from calib_node.chart_detection import chart_points, detect_chessboard
from calib_node.coverage import Coverage, view_parameters
from calib_node.lxpm_ga import LX_DRAWS, LX_VARIANTS
from calib_node.thesis import NETWORK_ACCEPT, NETWORK_WEIGHTS
from vgm_common.calibration_io import read_calibration, stereo_rectification, write_calibration
from vgm_common.camera_model import PinholeCamera
from vgm_common.camera_topics import subscribe_images
from vgm_common.conversions import (
    camera_to_camera_info,
    image_to_grey,
    matrix_to_pose_stamped,
    pose_to_matrix,
    stamp_to_ns,
)
from vgm_common.diagnostics import CountingPublisher
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.geometry import make_transform, quaternion_to_matrix, rpy_to_matrix
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams, Param, ParameterError
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.sync import ExactTimeSync
from vgm_common.topics import (
    BASE_FRAME,
    CAMERA_INFO_TOPICS,
    CAMERA_NAMES,
    IMAGE_TOPICS,
    OPTICAL_FRAMES,
    POSE_TOPICS,
    TARGET_POSE_TOPIC,
)
from vgm_common.worker import Worker

CHART_SOURCES = ('auto', 'stage', 'handheld')
TARGET_WAIT_S = 1.0  # [s] how long an image set waits for a target pose of its stamp
RECENT_TARGETS = 200  # target poses kept by stamp until their images arrive
VIEW_BACKLOG = 30  # image sets waiting for chart detection
# The thesis method's settings: network_* fields are network.* parameters, the rest ga.*.
GA = ConfigParams(
    GAOptions,
    renamed={
        name: name.replace('network_', 'network.', 1)
        if name.startswith('network_')
        else f'ga.{name}'
        for name in GAOptions._fields
    },
)


def _rig_pose_check(value):
    if len(value) not in (6, 7) or not all(np.isfinite(value)):
        return 'expected 6 (x y z roll pitch yaw) or 7 (x y z qx qy qz qw) finite numbers'
    if len(value) == 7 and abs(np.linalg.norm(value[3:]) - 1) > 1e-3:
        return 'the quaternion must have unit norm'
    return None


def rig_pose_matrix(value):
    """``rig_pose`` (x y z roll pitch yaw [m, rad] or x y z qx qy qz qw) -> T_base_left."""
    value = [float(v) for v in value]
    R = rpy_to_matrix(*value[3:]) if len(value) == 6 else quaternion_to_matrix(value[3:])
    return make_transform(R, value[:3])


def _target_matrix(msg):
    """The chart pose of a target pose message as a 4x4 matrix; InvalidInput if it is not
    in base_link or not a valid pose."""
    if msg.header.frame_id != BASE_FRAME:
        raise InvalidInput(
            f'target pose must be in {BASE_FRAME}, got {msg.header.frame_id!r}', key='frame_id'
        )
    return pose_to_matrix(msg.pose)


PARAMETERS = [
    Param(
        'chart.rows',
        6,
        'Inner corners along the chart y axis (rows + cols odd).',
        range=(2, 100),
        read_only=True,
    ),
    Param(
        'chart.cols',
        9,
        'Inner corners along the chart x axis.',
        range=(2, 100),
        read_only=True,
    ),
    Param(
        'chart.spacing',
        0.025,
        'Chessboard square size [m].',
        range=(1e-4, 10.0),
        read_only=True,
    ),
    Param(
        'chart.pattern',
        'chessboard',
        'Chart pattern.',
        choices=('chessboard',),
        read_only=True,
    ),
    Param(
        'chart.source',
        'auto',
        'stage: views need a /calibration/target_pose '
        'of their stamp; handheld: target poses are ignored, chart poses are '
        'estimated; auto: stage once target poses arrive, handheld before.',
        choices=CHART_SOURCES,
        read_only=True,
    ),
    Param(
        'rig_pose',
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        'The left camera optical '
        'frame in base_link when no view has a target pose: x y z [m] roll pitch '
        'yaw [rad], or x y z qx qy qz qw.',
        check=_rig_pose_check,
    ),
    Param(
        'cameras',
        list(CAMERA_NAMES),
        "The rig's cameras (left and right, aux optional).",
        check=lambda v: None
        if ({'left', 'right'} <= set(v) <= set(CAMERA_NAMES) and len(set(v)) == len(v))
        else f'expected left, right and optionally aux, got {v}',
        read_only=True,
    ),
    Param(
        'min_coverage',
        0.5,
        'Handheld: each of x, y, size and skew must cover '
        "this fraction of camera_calibration's ranges before calibrating.",
        range=(0.0, 1.0),
    ),
    Param(
        'select_views',
        True,
        'Handheld: keep a view only if it differs from the '
        "kept ones (camera_calibration's rule); false keeps every view.",
    ),
    Param(
        'min_views',
        10,
        'Views (captures with the chart found in at least one camera) needed to calibrate.',
        range=(1, 10000),
    ),
    Param(
        'auto_calibrate',
        True,
        'Calibrate as soon as min_views views are '
        'collected (the calibrate service recalibrates on all views so far).',
    ),
    Param(
        'calibration_file',
        '',
        'A calibration.yaml (or its directory) to publish '
        'at start instead of calibrating; empty: calibrate from the chart.',
        read_only=True,
    ),
    Param(
        'output_dir',
        '',
        'Where calibration.yaml and left/right/aux.yaml '
        '(camera_calibration_parsers) are written; empty: not written.',
    ),
    Param(
        'method',
        'lm',
        'lm: DLT (or GA) start + Levenberg-Marquardt, plumb_bob '
        '(ours); lxpm_ga: the thesis GA + network refinement; opencv: '
        'cv2.calibrateCamera reference.',
        choices=METHODS,
    ),
    Param(
        'lm_start',
        'dlt',
        'Start of the lm method: closed-form DLT or the GA.',
        choices=LM_STARTS,
    ),
    Param('seed', 0, 'Random seed of the GA.', range=(0, 2**31 - 1)),
    Param(
        'ga.population',
        GA.defaults.population,
        'GA population (thesis 240).',
        range=(4, 100000),
    ),
    Param(
        'ga.generations',
        GA.defaults.generations,
        'GA generations (thesis 200).',
        range=(1, 100000),
    ),
    Param(
        'ga.crossover',
        GA.defaults.crossover,
        'Laplace crossover probability per pair (thesis 0.9).',
        range=(0.0, 1.0),
    ),
    Param(
        'ga.mutation',
        GA.defaults.mutation,
        'Power mutation probability per gene (thesis 0.005).',
        range=(0.0, 1.0),
    ),
    Param(
        'ga.pm_index',
        GA.defaults.pm_index,
        'Power mutation index p, s = s1^(1/p) (not in the thesis; ALGORITHMS.md A4.4).',
        range=(1e-3, 100.0),
    ),
    Param(
        'ga.lx_variant',
        GA.defaults.lx_variant,
        'Laplace crossover: as printed in the thesis, or the symmetric Laplace quantile (A4.5).',
        choices=LX_VARIANTS,
    ),
    Param(
        'ga.lx_draw',
        GA.defaults.lx_draw,
        'Laplace spread phi drawn per gene (A4.5) or per parent pair.',
        choices=LX_DRAWS,
    ),
    Param(
        'ga.tournament',
        GA.defaults.tournament,
        'Tournament size of the selection [C] (A4.6).',
        range=(1, 1000),
    ),
    Param(
        'ga.elitism',
        GA.defaults.elitism,
        'Best individuals carried over each generation [C] (A4.6).',
        range=(0, 1000),
    ),
    Param(
        'ga.max_distance',
        GA.defaults.max_distance,
        'Bound of the GA translation genes: camera to chart-centroid distance [m].',
        range=(0.01, 1000.0),
    ),
    Param(
        'network.epochs',
        GA.defaults.network_epochs,
        'Gradient-descent epochs of the thesis network refinement.',
        range=(0, 1000000),
    ),
    Param(
        'network.weights',
        GA.defaults.network_weights,
        'structured: train only the entries of '
        'D = [A | 0] and B = [R T; 0 1] that stand for parameters (ALGORITHMS.md '
        '3.5); free: every weight, read out by RQ of D B.',
        choices=NETWORK_WEIGHTS,
    ),
    Param(
        'network.accept',
        GA.defaults.network_accept,
        'if_better: keep the network camera only '
        'if its full-model RMS is below the GA camera; always: keep it.',
        choices=NETWORK_ACCEPT,
    ),
    Param('fit_tangential', True, 'Estimate p1, p2 (else 0).'),
    Param(
        'select_model',
        True,
        'lm: keep p1, p2 only where they lower the residual '
        'enough (BIC); they otherwise trade against the principal point.',
    ),
    Param('fit_k3', False, 'Estimate k3 (else 0).'),
    Param(
        'max_rms_px',
        2.0,
        'A calibration whose reprojection RMS exceeds this in '
        'any camera is refused (not published) [px].',
        range=(0.0, 1e6),
    ),
    Param(
        'max_blur_px',
        4.0,
        'Chart views whose edge width exceeds this are rejected as blurred [px].',
        range=(0.5, 100.0),
    ),
    Param(
        'sync_max_wait',
        5.0,
        'Incomplete capture sets are dropped after this [s].',
        range=(0.01, 60.0),
        read_only=True,
    ),
]


class CalibNode(GraphNode):
    """Collects chart views from the paired images (and target poses), calibrates the rig
    and publishes latched CameraInfo and camera poses; with ``calibration_file`` set,
    publishes that calibration instead. Services ``~/calibrate`` and ``~/reset``."""

    node_name = 'calib_node'

    def __init__(self):
        super().__init__(PARAMETERS)
        self.chart = self._chart()
        self.names = tuple(n for n in CAMERA_NAMES if n in self._param('cameras'))
        self.source = self._param('chart.source')
        self._create_publishers()
        self._init_state()
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, '~/calibrate', self._on_calibrate, callback_group=services)
        self.create_service(Trigger, '~/reset', self._on_reset, callback_group=services)
        self.file_mode = bool(self.params.calibration_file)
        if self.file_mode:
            self._publish_file(self.params.calibration_file)
        else:
            self._start_collecting()

    def _chart(self):
        """The chart's (N, 3) corner points [m], from chart.rows, cols, spacing."""
        if (self._param('chart.rows') + self._param('chart.cols')) % 2 == 0:
            raise ParameterError(
                'parameters chart.rows + chart.cols must be odd (the '
                'board must not be symmetric under a half turn)',
                key='chart.rows',
            )
        return chart_points(
            self._param('chart.rows'), self._param('chart.cols'), self._param('chart.spacing')
        )

    def _create_publishers(self):
        self.info_publishers = {
            n: self.create_publisher(
                CameraInfo, CAMERA_INFO_TOPICS[n], LATCHED_QOS, publisher_class=CountingPublisher
            )
            for n in self.names
        }
        self.pose_publishers = {
            n: self.create_publisher(
                PoseStamped, POSE_TOPICS[n], LATCHED_QOS, publisher_class=CountingPublisher
            )
            for n in self.names
        }

    def _init_state(self):
        self.lock = threading.Lock()  # views, image sizes, counters, targets
        self.detection_pool = ThreadPoolExecutor(len(self.names))
        self.calibration_lock = threading.Lock()  # one calibration at a time
        # [(T_base_chart (4, 4) or None for a handheld view, {name: pixels (N, 2)})]
        self.views = []
        self.coverage = Coverage()
        self.targets = {}  # stamp_ns -> PoseStamped, the most recent RECENT_TARGETS
        self.target_seen = False  # auto: a target pose arrived (the stage is in use)
        self.handheld_said = False  # auto: the switch to handheld views was logged
        self.target_arrived = threading.Condition(self.lock)
        # name -> (width, height), fixed by the first good image
        self.image_sizes: dict[str, tuple[int, int]] = {}
        self.rejected_views = 0
        self.similar_views = 0  # handheld views like a kept one (select_views)
        self.unposed_sets = 0  # stage: image sets without a target pose of their stamp
        self.calibrations = 0
        self.last_result = None
        self.auto_done_at = None  # view count of the last automatic calibration
        self.stopping = threading.Event()

    def _start_collecting(self):
        p = self.params
        # Every stage view counts: when VIEW_BACKLOG wait, a new one is refused and reported.
        self.worker = Worker(
            lambda view: self._process_view(*view),
            self._on_worker_error,
            'calibration',
            capacity=VIEW_BACKLOG,
            keep='oldest',
        )
        # Images are paired by stamp; the target pose of a set is looked up by its stamp
        # (it may come a little before or after the images, or never: handheld).
        self.sync = ExactTimeSync(
            self.names, self._on_capture, queue_size=10, max_wait=p.sync_max_wait
        )
        inputs = MutuallyExclusiveCallbackGroup()  # the sync is not thread-safe
        subscribe_images(self, self.names, self._offer, inputs)
        # The poses get their own group: in one group with the images, rclpy's executor
        # serves a backlog of images first (subscription order), and under load a
        # set's pose came later than TARGET_WAIT_S. _on_target only takes self.lock.
        self.create_subscription(
            PoseStamped,
            TARGET_POSE_TOPIC,
            self._on_target,
            DEFAULT_QOS,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )
        self.create_timer(1.0, self._publish_status)
        self.get_logger().info(
            f'collecting chart views ({p.method}, {self._param("chart.rows")}x'
            f'{self._param("chart.cols")} chessboard, chart.source {self.source}, cameras '
            f'{", ".join(self.names)}, min_views {p.min_views})'
        )

    def _param(self, name):
        return getattr(self.params, name)  # dotted names too

    # --- inputs -----------------------------------------------------------------------

    def _offer(self, key, msg):
        self.sync.add(key, stamp_to_ns(msg.header.stamp), msg, time.monotonic())

    def _on_target(self, msg):
        if self.source == 'handheld':
            return
        try:  # checked as it arrives, whether or not images of its stamp follow
            _target_matrix(msg)
        except InvalidInput as error:
            self.diagnostics.reject(TARGET_POSE_TOPIC, error)
            return
        with self.lock:
            self.targets[stamp_to_ns(msg.header.stamp)] = msg
            while len(self.targets) > RECENT_TARGETS:
                del self.targets[next(iter(self.targets))]
            self.target_seen = True
            self.target_arrived.notify_all()

    def _on_capture(self, stamp_ns, messages):
        if not self.worker.submit((stamp_ns, messages, time.monotonic())):
            with self.lock:
                posed = stamp_ns in self.targets
                if not posed:  # a handheld stream outruns detection: take what it can
                    self.similar_views += 1
            if posed:
                self.diagnostics.reject('view', 'the calibration worker is behind: view dropped')

    def _on_worker_error(self, error):
        self.diagnostics.reject('view', f'{type(error).__name__}: {error}')

    def _target_of(self, stamp_ns, completed):
        """The target pose message of ``stamp_ns``, waiting for it as the source asks
        until TARGET_WAIT_S after the image set was ``completed`` [monotonic s]; None: a
        handheld view; False: a stage view without a pose (dropped)."""
        if self.source == 'handheld':
            return None
        deadline = completed + TARGET_WAIT_S  # a backlog of sets adds no wait
        with self.lock:
            while stamp_ns not in self.targets and not self.stopping.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self.target_arrived.wait(remaining)
            target = self.targets.pop(stamp_ns, None)
            if target is None and (self.source == 'stage' or self.target_seen):
                self.unposed_sets += 1  # outside the stage's chart phase: not a view
                return False
        return target

    def _process_view(self, stamp_ns, messages, completed):
        target = self._target_of(stamp_ns, completed)
        if target is False:
            return
        if target is None and self.source == 'auto' and not self.handheld_said:
            self.handheld_said = True  # what auto chose must not be a silent switch
            topic = self.resolve_topic_name(TARGET_POSE_TOPIC)
            self.get_logger().info(
                f'chart.source auto: no target pose on {topic} '
                f'for this view within {TARGET_WAIT_S} s: views are taken as handheld (chart '
                'poses estimated) until a target pose arrives'
            )
        T_base_chart = None if target is None else _target_matrix(target)  # checked
        corners, misses, greys = {}, [], {}
        for name in self.names:
            msg = messages[name]
            try:
                greys[name] = image_to_grey(msg)
                size = (msg.width, msg.height)
                with self.lock:
                    expected = self.image_sizes.setdefault(name, size)
                if size != expected:
                    raise InvalidInput(
                        f'image size {size[0]}x{size[1]} differs from this '
                        f"camera's earlier {expected[0]}x{expected[1]}",
                        key='size',
                    )
            except (InvalidInput, ValueError) as error:
                self.diagnostics.reject(IMAGE_TOPICS[name], error)
                misses.append(f'{name}: unusable image')
                greys.pop(name, None)
        rows, cols = self._param('chart.rows'), self._param('chart.cols')
        # OpenCV's detector releases the GIL: the cameras' images are searched in parallel.
        detections = dict(
            zip(
                greys,
                self.detection_pool.map(
                    lambda grey: detect_chessboard(grey, rows, cols, self.params.max_blur_px),
                    greys.values(),
                ),
            )
        )
        for name, detection in detections.items():
            if detection.corners is None:
                misses.append(f'{name}: {detection.reason}')
                continue
            corners[name] = detection.corners
        if not corners:
            self._reject_view('view', 'chart not found in any camera (' + '; '.join(misses) + ')')
            return
        with self.lock:
            if T_base_chart is None:
                first = next(n for n in self.names if n in corners)
                parameters = view_parameters(corners[first], rows, cols, self.image_sizes[first])
                if self.params.select_views and not self.coverage.is_new(parameters):
                    self.similar_views += 1
                    return
                self.coverage.add(parameters)
            self.views.append((T_base_chart, corners))
            count = len(self.views)
            coverage = self.coverage.summary() if T_base_chart is None else ''
            # What to move next, in the log too: a user without ros2cli cannot read
            # /diagnostics.
            still = (
                self.coverage.missing(self.params.min_coverage)
                if T_base_chart is None and not self.calibrations
                else ''
            )
        self.get_logger().info(
            f'view {count}: chart found in {", ".join(corners)}'
            + (f' (not in {"; ".join(misses)})' if misses else '')
            + (f'; coverage {coverage}' if coverage else '')
            + (f' (still: {still})' if still else '')
        )
        if (
            self.params.auto_calibrate
            and count >= self.params.min_views
            and self.auto_done_at is None
            and not self._coverage_missing(self.views)
        ):
            self.auto_done_at = count
            self._calibrate()

    def _reject_view(self, what, error):
        with self.lock:
            self.rejected_views += 1
        self.diagnostics.reject(what, error)

    # --- calibration ------------------------------------------------------------------

    def _coverage_missing(self, views):
        """What a handheld collection lacks ('' if enough, or if every view is posed)."""
        if all(T is not None for T, _ in views):
            return ''
        with self.lock:
            return self.coverage.missing(self.params.min_coverage)

    def _observations(self, views):
        observations, missing = {}, []
        for name in self.names:
            pairs = [(T, corners[name]) for T, corners in views if name in corners]
            if not pairs:
                missing.append(name)
                continue
            observations[name] = (
                np.concatenate([self.chart @ T[:3, :3].T + T[:3, 3] for T, _ in pairs]),
                np.concatenate([uv for _, uv in pairs]),
                self.image_sizes[name],
            )
        if missing:
            raise CalibrationError(f'the chart was never found in {", ".join(missing)}')
        return observations

    def _calibrate_handheld(self, views):
        """Bundle adjustment over the views; {name: CameraFit} with poses in base_link."""
        if self.params.method != 'lm':
            raise CalibrationError(
                f'method {self.params.method} needs target poses (the '
                'stage); handheld views calibrate with lm'
            )
        known = [T for T, _ in views]
        result = bundle_adjust_selected(
            self.chart,
            [corners for _, corners in views],
            {n: self.image_sizes[n] for n in self.names},
            known,
            self.names,
            self.params.fit_tangential,
            self.params.fit_k3,
            self.params.select_model,
        )
        T_base_ref = (
            rig_pose_matrix(self._param('rig_pose'))
            if result.reference != BASE_FRAME
            else np.eye(4)
        )
        return {
            n: f._replace(T_base_camera=T_base_ref @ f.T_base_camera)
            for n, f in result.fits.items()
        }, result.reference

    def _calibrate(self):
        """Calibrate on all views so far; returns (success, message)."""
        with self.lock:
            views = list(self.views)
        refusal = self._not_ready(views)
        if refusal:
            return False, refusal
        with self.calibration_lock:
            try:
                fits, reference, seconds = self._fit(views)
                cameras = {
                    name: PinholeCamera(*self.image_sizes[name], fit.K, fit.D, fit.T_base_camera)
                    for name, fit in fits.items()
                }
                rectification = stereo_rectification(cameras['left'], cameras['right'])
            except (CalibrationError, InvalidInput, ValueError, np.linalg.LinAlgError) as error:
                message = f'calibration failed on {len(views)} views: {error}'
                self.get_logger().error(message)
                self.diagnostics.publish(
                    'calibration',
                    'error',
                    message,
                    {'views': len(views), 'method': self.params.method},
                )
                return False, message
            self._publish(cameras, rectification)
            return True, self._report(views, fits, cameras, rectification, reference, seconds)

    def _not_ready(self, views):
        """Why ``views`` cannot be calibrated yet (coverage, then min_views), or ''."""
        p = self.params
        missing = self._coverage_missing(views) if views else ''
        if missing:  # say what to do with the chart first: more views alike would not help
            message = (
                f'not enough coverage in {len(views)} views ({self.coverage.summary()}'
                f'; need {100 * p.min_coverage:.0f} % each, and min_views '
                f'{p.min_views}): {missing}'
            )
            self.diagnostics.publish(
                'calibration',
                'warn',
                message,
                {'views': len(views), 'coverage': self.coverage.summary()},
            )
            return message
        if len(views) < p.min_views:
            return f'{len(views)} views collected, min_views is {p.min_views}'
        return ''

    def _fit(self, views):
        """(fits {name: CameraFit}, reference frame, seconds) of the views: handheld or
        stage; CalibrationError when a camera's RMS exceeds max_rms_px."""
        p = self.params
        started = time.perf_counter()
        if any(T is None for T, _ in views):
            fits, reference = self._calibrate_handheld(views)
            seconds = time.perf_counter() - started
        else:
            reference = BASE_FRAME
            result = calibrate_rig(
                self._observations(views),
                p.method,
                p.seed,
                p.lm_start,
                GA.build(self.params),
                p.fit_tangential,
                p.fit_k3,
                p.select_model,
            )
            fits, seconds = result.fits, result.seconds
        worst = max(fits, key=lambda n: fits[n].rms_px)
        if fits[worst].rms_px > p.max_rms_px:
            raise CalibrationError(
                f'{worst}: reprojection RMS {fits[worst].rms_px:.3g} px '
                f'exceeds max_rms_px {p.max_rms_px:g}'
            )
        return fits, reference, seconds

    def _report(self, views, fits, cameras, rectification, reference, seconds):
        """Writes the calibration to output_dir (if set), logs it and publishes its
        diagnostics; returns the message."""
        p = self.params
        quality = {
            name: {
                'rms_px': fit.rms_px,
                'points': fit.points,
                'views': sum(name in corners for _, corners in views),
            }
            for name, fit in fits.items()
        }
        if p.output_dir:
            try:
                written = write_calibration(
                    p.output_dir, cameras, OPTICAL_FRAMES, rectification, quality
                )
            except (OSError, VgmError) as error:
                self.get_logger().error(f'cannot write {p.output_dir}: {error}')
                self.diagnostics.publish(
                    'calibration', 'error', f'cannot write {p.output_dir}: {error}'
                )
            else:  # where the files are is the first thing a user looks for
                written = written.resolve()
                self.get_logger().info(
                    f'wrote {written} and {", ".join(f"{n}.yaml" for n in cameras)} '
                    f'beside it (calibration_file:={written} publishes it again)'
                )
        self.calibrations += 1
        rms = ' '.join(f'{n}={f.rms_px:.3f}' for n, f in fits.items())
        baseline = np.linalg.norm(cameras['left'].centre_base - cameras['right'].centre_base)
        handheld = any(T is None for T, _ in views)
        mode = 'handheld' if handheld else 'stage'
        message = (
            f'calibrated {len(cameras)} cameras from {len(views)} views: rms '
            f'{rms} px, baseline {baseline:.4f} m ({p.method}, {mode}, '
            f'{seconds:.2f} s)'
        )
        self.get_logger().info(message)
        values = {
            'views': len(views),
            'method': p.method,
            'chart source': mode,
            'reference frame': reference,
            'time_s': f'{seconds:.3f}',
            'baseline_m': f'{baseline:.6f}',
        }
        if handheld:
            values['coverage'] = self.coverage.summary()
        for name, fit in fits.items():
            values[f'rms_px {name}'] = f'{fit.rms_px:.4f}'
            values[f'points {name}'] = fit.points
            values[f'views {name}'] = quality[name]['views']
        self.last_result = values
        self.diagnostics.publish('calibration', 'ok', message, values)
        return message

    def _publish(self, cameras, rectification, stamp_ns=None):
        stamp_ns = self.get_clock().now().nanoseconds if stamp_ns is None else stamp_ns
        for name, camera in cameras.items():
            R, P = rectification.get(name, (None, None))
            self.info_publishers[name].publish(
                camera_to_camera_info(camera, stamp_ns, OPTICAL_FRAMES[name], R, P)
            )
            self.pose_publishers[name].publish(
                matrix_to_pose_stamped(camera.T_base_camera, stamp_ns, BASE_FRAME)
            )

    def _publish_file(self, path):
        rig = read_calibration(path)  # InvalidInput -> one-line start-up error
        missing = [name for name in self.names if name not in rig]
        if missing:
            raise InvalidInput(
                f'calibration_file {path} lacks {", ".join(missing)}', key='calibration_file'
            )
        cameras = {name: rig[name][0] for name in self.names}
        # As the harness and every consumer expect: left/right re-rectified from the
        # cameras, aux as stored.
        rectification = {
            **{n: rig[n][1:] for n in self.names if n not in ('left', 'right')},
            **stereo_rectification(cameras['left'], cameras['right']),
        }
        self._publish(cameras, rectification)
        message = f'published the calibration of {path}'
        self.get_logger().info(message)
        self.diagnostics.publish('calibration', 'ok', message, {'calibration_file': path})

    # --- services and status ----------------------------------------------------------

    def _on_calibrate(self, request, response):
        if self.file_mode:
            response.success = False
            response.message = 'publishing calibration_file: no chart views are collected'
            return response
        response.success, response.message = self._calibrate()
        return response

    def _on_reset(self, request, response):
        with self.lock:
            forgotten = len(self.views)
            self.views.clear()
            self.coverage.clear()
            self.image_sizes.clear()
            self.auto_done_at = None
        response.success = True
        response.message = f'forgot {forgotten} views'
        self.get_logger().info(response.message)
        return response

    def _publish_status(self):
        with self.lock:
            values: dict[str, object] = {
                'views': len(self.views),
                'rejected views': self.rejected_views,
                'calibrations': self.calibrations,
                'similar views skipped': self.similar_views,
                'image sets without a target pose': self.unposed_sets,
                'incomplete capture sets (messages)': self.sync.dropped,
                'matched capture sets': self.sync.matched,
            }
            if self.last_result:  # the latest calibration's quality, repeated at 1 Hz
                values.update(
                    {k: v for k, v in self.last_result.items() if k.startswith('rms_px')}
                )
            handheld = any(T is None for T, _ in self.views)
            if handheld:
                values['coverage'] = self.coverage.summary()
        level = 'ok'
        message = (
            f'{values["views"]} views, {self.calibrations} calibrations'
            if self.calibrations or values['views']
            else 'waiting for chart views'
        )
        if handheld:
            message += f'; coverage {values["coverage"]}'
            missing = self._coverage_missing(self.views)
            if missing and not self.calibrations:
                message += f' (still: {missing})'
        self.diagnostics.publish('views', level, message, values)

    def close(self):
        """For run_node: stop waiting for target poses and close the worker (views still
        queued are not processed)."""
        self.stopping.set()
        if not self.file_mode:
            self.worker.close()


def main(args=None):
    """Run calib_node until SIGINT/SIGTERM; exit status 2 on an unusable parameter or
    calibration file at start-up (one line)."""
    return run_node(CalibNode, args, executor_class=lambda: MultiThreadedExecutor(3))


if __name__ == '__main__':
    raise SystemExit(main())
