"""curve_recon_node: reconstruct the curve drawn on the surface from its three calibrated
views and publish tool waypoints (INTERFACES.md; ALGORITHMS.md §2).

Inputs: the three images (exact-time sync), the calibrated rig (latched camera_info and
pose topics), optionally /depth/fused + /depth/camera_info for surface normals.
Outputs: /curve/waypoints (latched Path), /curve/points (PointCloud2), diagnostics.
The work runs on a worker thread (``vgm_common.worker.Worker``); callbacks only check and
hand over. No exception escapes a callback or the worker (each is reported once,
throttled, with a diagnostic, and the node keeps serving).
~/reconstruct never blocks an executor thread: its requests are answered later, from the
worker or the timeout timer (``DeferredTriggerService``).
"""

import threading
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from curve_recon_node.fused_depth import FusedDepth
from curve_recon_node.pipeline import NoCurve, ReconstructionSettings, reconstruct_capture
from curve_recon_node.report import capture_status, reconstruction_report
from curve_recon_node.scheduler import (
    MAX_WAITING_CALLS,
    CaptureJob,
    CaptureScheduler,
    CaptureSettings,
)
from curve_recon_node.waypoints import (
    DEPTH_RANGE_M,
    waypoint_frames,
)
from vgm_common.camera_topics import CalibratedCameras, ImageCaptures
from vgm_common.conversions import (
    camera_info_rectification,
    camera_info_to_camera,
    check_grey_image,
    image_to_grey,
    image_to_numpy,
    matrices_to_path,
    points_to_pointcloud2,
    stamp_to_ns,
)
from vgm_common.deferred_service import DeferredTriggerService
from vgm_common.diagnostics import CountingPublisher, guarded
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import DeferredServiceExecutor, run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import (
    BASE_FRAME,
    CAMERA_NAMES,
    CURVE_POINTS_TOPIC,
    DEPTH_INFO_TOPIC,
    FUSED_DEPTH_TOPIC,
    IMAGE_TOPICS,
    TARGET_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)
from vgm_common.worker import Worker

# The parameters that shape a reconstruction (ReconstructionSettings says how).
SETTINGS = ConfigParams(ReconstructionSettings)

CHART_POSE_GRACE = 0.5  # [s] a capture waits this long for a target pose of its stamp
SERVICE_POLL_PERIOD = 0.1  # [s] how often timed-out ~/reconstruct calls are answered


@dataclass
class _Capture:
    """A synchronized capture for the worker, with the ~/reconstruct calls it answers."""

    job: CaptureJob
    messages: dict  # camera name -> Image
    names: tuple  # the cameras to use


# The worker's other job: publish the last waypoints again, now with depth normals.
_REPUBLISH_WITH_NORMALS = object()


PARAMETERS = [*SETTINGS.declarations(), *ConfigParams(CaptureSettings).declarations()]


class CurveReconNode(GraphNode):
    """Reconstructs the curve from a synchronized capture of the calibrated views (once
    the calibration is ready or changes, and on ``/curve_recon_node/reconstruct``) and
    publishes the waypoints (latched; approach axes from /depth/fused normals when
    available) and the curve points."""

    node_name = 'curve_recon_node'

    def __init__(self):
        super().__init__(PARAMETERS, on_change={'views': self._on_views_change})
        p = self.params
        self.cameras = CalibratedCameras(
            self, CAMERA_NAMES, self.diagnostics, self._on_calibration_change
        )
        self._init_state()
        sensors = self._subscribe_inputs()
        self._create_outputs(sensors)
        self.get_logger().info(
            f'ready: method {p.method}, degree {p.degree}, {p.views} views, spacing '
            f'{p.spacing} m; waiting for the calibration and a capture'
        )

    def _init_state(self):
        self.scheduler = CaptureScheduler()
        self.fused_depth = FusedDepth()
        self.last_result = None  # (stamp_ns, reconstruction) for republishing with normals
        self.normals_published = False
        self.stopping = threading.Event()

    def _subscribe_inputs(self):
        """Subscribes to the cameras, chart poses and fused depth; returns their group."""
        sensors = MutuallyExclusiveCallbackGroup()
        # all three cameras, so `views` can change at run time; the sync takes the used ones
        self.captures = ImageCaptures(
            self,
            _paired_cameras(self.params.views),
            self._on_capture,
            self.params.sync_max_wait,
            subscribed=CAMERA_NAMES,
            callback_group=sensors,
            accept=self._accept_image,
        )
        # its own group: behind a backlog of images (served first, in subscription
        # order) a chart pose could come later than CHART_POSE_GRACE
        self.create_subscription(
            PoseStamped,
            TARGET_POSE_TOPIC,
            self._on_target_pose,
            DEFAULT_QOS,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )
        self.create_subscription(
            Image, FUSED_DEPTH_TOPIC, self._on_depth, DEFAULT_QOS, callback_group=sensors
        )
        self.create_subscription(
            CameraInfo, DEPTH_INFO_TOPIC, self._on_depth_info, DEFAULT_QOS, callback_group=sensors
        )
        return sensors

    def _create_outputs(self, sensors):
        """Publishers, the reconstruct service, the timers and the worker."""
        self.waypoint_publisher = self.create_publisher(
            Path, WAYPOINTS_TOPIC, LATCHED_QOS, publisher_class=CountingPublisher
        )
        self.points_publisher = self.create_publisher(
            PointCloud2, CURVE_POINTS_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self.reconstruct_service = DeferredTriggerService(
            self,
            '/curve_recon_node/reconstruct',
            self._on_reconstruct_call,
            lambda: self.params.service_timeout + 2 * SERVICE_POLL_PERIOD + 1.0,
            MAX_WAITING_CALLS,
            self.diagnostics,
        )
        self.create_timer(1.0, self._publish_status, callback_group=sensors)
        self.create_timer(
            SERVICE_POLL_PERIOD, self._answer_timed_out_requests, callback_group=sensors
        )
        # The newest capture waits while one is reconstructed; one it replaces hands its
        # service calls on to the next.
        self.worker = Worker(
            self._serve,
            self._on_worker_error,
            'reconstruction',
            on_drop=self._requests_wait_for_the_next,
        )

    # --- inputs ----------------------------------------------------------------------

    def _on_views_change(self, views):
        self.captures.use(_paired_cameras(views))
        self.get_logger().info(
            f'views set to {views}: synchronizing {", ".join(self.captures.names)}'
        )

    @guarded('calibration change')
    def _on_calibration_change(self, name):
        self.scheduler.calibration_changed()

    @guarded(TARGET_POSE_TOPIC)
    def _on_target_pose(self, msg):
        self.scheduler.chart_shown(stamp_to_ns(msg.header.stamp))

    @guarded('image')
    def _accept_image(self, name, msg):
        try:
            check_grey_image(msg)  # every image, also those of captures not reconstructed
        except InvalidInput as error:
            self.diagnostics.reject(IMAGE_TOPICS[name], error)
            return False
        return True

    @guarded('image')
    def _on_capture(self, stamp_ns, messages):
        """A synchronized capture: hand it to the worker if a reconstruction is wanted."""
        calibrated = [n for n in CAMERA_NAMES if self.cameras.get(n) is not None]
        names = self.scheduler.cameras_to_use(calibrated, self.params.views, self.params.aux_wait)
        if names is None or not set(names) <= set(messages):
            return  # not calibrated, or `views` changed while this capture was completed
        job = self.scheduler.take(stamp_ns)
        if job is not None:
            self.worker.submit(_Capture(job, messages, names))

    @guarded(DEPTH_INFO_TOPIC)
    def _on_depth_info(self, msg):
        try:
            camera_info_to_camera(msg)  # the whole message must be a valid CameraInfo
            _, P = camera_info_rectification(msg)
            waiting = self.fused_depth.set_intrinsics(P[:3, :3], int(msg.width), int(msg.height))
        except (InvalidInput, ValueError) as error:
            self.diagnostics.reject(DEPTH_INFO_TOPIC, f'P: {error}')
            return
        if waiting is None:
            return
        if waiting.stamp_ns == stamp_to_ns(msg.header.stamp):
            self._add_depth(waiting.depth_m, waiting.stamp_ns)
        else:
            self.diagnostics.reject(
                FUSED_DEPTH_TOPIC, f'no {DEPTH_INFO_TOPIC} of its stamp came: not used'
            )

    @guarded(FUSED_DEPTH_TOPIC)
    def _on_depth(self, msg):
        if msg.encoding != '32FC1':
            self.diagnostics.reject(
                FUSED_DEPTH_TOPIC,
                InvalidInput(
                    f'expected 32FC1 depth, got {msg.encoding!r}',
                    key='encoding',
                    value=msg.encoding,
                ),
            )
            return
        self._add_depth(image_to_numpy(msg), stamp_to_ns(msg.header.stamp))

    def _add_depth(self, depth, stamp_ns):
        first = self.fused_depth.latest is None
        try:
            removed = self.fused_depth.add(depth, stamp_ns)
        except InvalidInput as error:
            self.diagnostics.reject(FUSED_DEPTH_TOPIC, error)
            return
        if removed is None:
            return  # waits for its camera_info
        if any(removed.values()):
            # the rest of the image still serves; these pixels never give a normal
            self.diagnostics.reject(
                'depth values',
                f'{FUSED_DEPTH_TOPIC}: ignored for approach axes: '
                f'{removed["not_positive"]} zero or negative, {removed["too_far"]} '
                f'beyond {DEPTH_RANGE_M[1]:g} m, {removed["too_near"]} nearer than '
                f'{DEPTH_RANGE_M[0]:g} m',
            )
        if (
            first
            and self.last_result is not None
            and self.params.use_depth_normals
            and not self.normals_published
        ):
            # (a capture that is waiting will use the depth anyway)
            self.worker.submit_if_idle(_REPUBLISH_WITH_NORMALS)

    @guarded('reconstruct call')
    def _on_reconstruct_call(self, reply):
        """A ~/reconstruct call: it waits for the next capture; the worker answers it, or
        _answer_timed_out_requests after ``service_timeout``."""
        refusal = self.scheduler.add_call(reply, self.params.service_timeout)
        if refusal:
            self.diagnostics.reject('reconstruct call', f'{refusal} (at most {MAX_WAITING_CALLS})')
            reply(False, f'refused: {refusal}')

    @guarded('reconstruct timeout')
    def _answer_timed_out_requests(self):
        expired = self.scheduler.expired()
        if not expired:
            return
        missing = self.cameras.missing()
        message = f'no synchronized capture within {self.params.service_timeout:g} s' + (
            f' (not calibrated: {", ".join(missing)})' if missing else ''
        )
        for call in expired:
            call.reply(False, message)

    # --- work ------------------------------------------------------------------------

    def _serve(self, job):
        """The worker's job: a capture to reconstruct (its service calls answered with the
        outcome), or the waypoints to republish with depth normals."""
        if job is _REPUBLISH_WITH_NORMALS:
            self._republish_with_normals()
            return
        try:
            success, message = self._run_capture(job)
        except Exception as error:  # noqa: BLE001 - the calls must get an answer
            self._on_worker_error(error)
            success, message = False, f'reconstruction failed: {error}'
        for call in job.job.calls:
            call.reply(success, message)

    def _on_worker_error(self, error):
        self.diagnostics.reject('reconstruction', f'{type(error).__name__}: {error}')

    def _requests_wait_for_the_next(self, job):
        if job is not _REPUBLISH_WITH_NORMALS:
            self.scheduler.put_back(job.job)

    def _run_capture(self, job):
        """Reconstruct one capture; returns (success, message) for the requests it serves
        (a chart capture puts its requests back to wait for the next one)."""
        # The chart's pose, stamped like its images, may arrive after them: give it
        # CHART_POSE_GRACE before taking a capture for one of the scene.
        self.stopping.wait(CHART_POSE_GRACE)
        if self.scheduler.is_chart(job.job):  # its calls wait for the next capture
            return False, 'chart capture'
        success, message = self._reconstruct(job.job.stamp_ns, job.messages, job.names)
        if success:
            self.scheduler.succeeded()
        return success, message

    def _reconstruct(self, stamp_ns, messages, names):
        """Reconstruct one capture and publish; returns (success, message)."""
        try:
            images = {}
            for name in names:
                try:
                    images[name] = image_to_grey(messages[name]).astype(float)
                except InvalidInput as error:
                    self.diagnostics.reject(IMAGE_TOPICS[name], error)
                    return False, f'{IMAGE_TOPICS[name]}: {error}'
            cameras = {name: self.cameras[name].camera for name in names}
            for name in names:
                camera = cameras[name]
                if images[name].shape != (camera.height, camera.width):
                    size_error = InvalidInput(
                        f'{name} image is {images[name].shape[1]}x{images[name].shape[0]}'
                        f' but its camera_info says {camera.width}x{camera.height}',
                        key='size',
                    )
                    self.diagnostics.reject(IMAGE_TOPICS[name], size_error)
                    return False, str(size_error)
            result = reconstruct_capture(images, cameras, SETTINGS.build(self.params), names)
            normals_source = self._publish(stamp_ns, result)
        except NoCurve as error:
            self.diagnostics.reject('no curve', error)
            return False, f'no curve: {error}'
        except (VgmError, np.linalg.LinAlgError, ValueError) as error:
            self.diagnostics.reject('reconstruction', error)
            return False, f'reconstruction failed: {error}'
        self.last_result = (stamp_ns, result, names)
        level, message, values = reconstruction_report(
            result,
            names,
            stamp_ns,
            normals_source,
            {'method': self.params.method, 'degree': self.params.degree},
        )
        self.get_logger().info(f'{message}; approach from {normals_source}')
        self.diagnostics.publish('reconstruction', level, message, values)
        return True, message

    def _approach_directions(self, waypoints):
        """Approach directions (N, 3) into the surface from the fused depth, or None (no
        depth, or none usable at the waypoints: see normals_from_depth)."""
        left = self.cameras.get('left')
        if not self.params.use_depth_normals or left is None:
            return None
        try:
            return self.fused_depth.approach_directions(
                waypoints, left.camera.T_base_camera, left.R, self.params.normal_window_px
            )
        except InvalidInput as error:  # checked on arrival: only a changed rig gets here
            self.diagnostics.reject(FUSED_DEPTH_TOPIC, error)
            return None

    def _publish(self, stamp_ns, result):
        approach = self._approach_directions(result.waypoints_base)
        frames = waypoint_frames(result.waypoints_base, result.closed, approach)
        self.waypoint_publisher.publish(matrices_to_path(frames, stamp_ns, BASE_FRAME))
        self.points_publisher.publish(
            points_to_pointcloud2(result.points_base, stamp_ns, BASE_FRAME)
        )
        self.normals_published = approach is not None
        if approach is None:
            return 'base -z (no depth normals)'
        known = int(np.all(np.isfinite(approach), axis=1).sum())
        return f'depth normals at {known}/{len(approach)} waypoints'

    def _republish_with_normals(self):
        if self.last_result is None or self.normals_published:
            return
        stamp_ns, result, names = self.last_result
        source = self._publish(stamp_ns, result)
        if self.normals_published:
            self.get_logger().info(
                f'fused depth arrived: republished '
                f'{len(result.waypoints_base)} waypoints with {source}'
            )

    @guarded('status')
    def _publish_status(self):
        missing = self.cameras.missing()
        values = {
            **self.captures.counts(),
            'skipped_chart_captures': self.scheduler.skipped_chart,
            'dropped_work': self.worker.dropped,
            'waiting_requests': self.scheduler.waiting,
            'depth': 'yes' if self.fused_depth.latest is not None else 'no',
        }
        level, message = capture_status(
            missing, self.params.views, self.captures.unsynchronized(), bool(self.last_result)
        )
        self.diagnostics.publish('status', level, message, values)

    def close(self):
        """For run_node: stop the worker and answer every waiting ~/reconstruct call with
        a failure."""
        self.stopping.set()
        self.worker.close()
        for call in self.scheduler.close():
            call.reply(False, 'curve_recon_node is shutting down')
        self.reconstruct_service.flush()


def _paired_cameras(views):
    return CAMERA_NAMES if views == 3 else CAMERA_NAMES[:2]


def main(args=None):
    """Run curve_recon_node until SIGINT/SIGTERM; exit status 2 on an unusable parameter
    at start-up (one line)."""
    return run_node(CurveReconNode, args, executor_class=lambda: DeferredServiceExecutor(3))


if __name__ == '__main__':
    raise SystemExit(main())
