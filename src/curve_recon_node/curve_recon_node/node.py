"""curve_recon_node (INTERFACES.md; ALGORITHMS.md §2): ROS in and out of its task state,
``session.ReconstructionSession``. Callbacks check, convert and hand over; the work runs
on a worker thread; no exception escapes either; ~/reconstruct calls are answered later
from the worker or a timer (``DeferredTriggerService``), never blocking the executor.
"""

from typing import Any, NamedTuple

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from curve_recon_node.pipeline import ReconstructionSettings
from curve_recon_node.scheduler import (
    MAX_WAITING_CALLS,
    CaptureJob,
    CaptureSettings,
    paired_cameras,
)
from curve_recon_node.session import Outcome, ReconstructionSession
from vgm_common import conversions
from vgm_common.camera_topics import CalibratedCameras, ImageCaptures
from vgm_common.deferred_service import DeferredTriggerService
from vgm_common.diagnostics import CountingPublisher, guarded
from vgm_common.errors import InvalidInput
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
PARAMETERS = [*SETTINGS.declarations(), *ConfigParams(CaptureSettings).declarations()]
SERVICE_POLL_PERIOD = 0.1  # [s] how often timed-out ~/reconstruct calls are answered


class _Capture(NamedTuple):
    """A capture for the worker: its job (the calls it answers), images, cameras to use."""

    job: CaptureJob
    messages: dict[str, Image]
    names: tuple[str, ...]


# The worker's other job: publish the last waypoints again, now with depth normals.
_REPUBLISH_WITH_NORMALS = object()


class CurveReconNode(GraphNode):
    """Reconstructs the curve from a capture of the calibrated views (once the calibration
    is ready or changes, and on ``~/reconstruct``) and publishes the waypoints (latched;
    approach axes from /depth/fused normals when available) and the curve points."""

    node_name = 'curve_recon_node'

    def __init__(self) -> None:
        super().__init__(PARAMETERS, on_change={'views': self._on_views_change})
        p = self.params
        self.cameras = CalibratedCameras(
            self, CAMERA_NAMES, self.diagnostics, self._on_calibration_change
        )
        self.session = ReconstructionSession(p)
        self.scheduler = self.session.scheduler
        sensors = MutuallyExclusiveCallbackGroup()
        # all three cameras, so `views` can change at run time; the sync takes the used ones
        self.captures = ImageCaptures(
            self,
            paired_cameras(p.views),
            self._on_capture,
            p.sync_max_wait,
            subscribed=CAMERA_NAMES,
            callback_group=sensors,
            accept=self._accept_image,
        )
        # its own group: behind a backlog of images (served first, in subscription
        # order) a chart pose could come later than CHART_POSE_GRACE
        poses = MutuallyExclusiveCallbackGroup()
        self.create_subscription(
            PoseStamped,
            TARGET_POSE_TOPIC,
            self._on_target_pose,
            DEFAULT_QOS,
            callback_group=poses,
        )
        self.create_subscription(
            Image, FUSED_DEPTH_TOPIC, self._on_depth, DEFAULT_QOS, callback_group=sensors
        )
        self.create_subscription(
            CameraInfo,
            DEPTH_INFO_TOPIC,
            self._on_depth_info,
            DEFAULT_QOS,
            callback_group=sensors,
        )
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
        self.get_logger().info(
            f'ready: method {p.method}, degree {p.degree}, {p.views} views, spacing '
            f'{p.spacing} m; waiting for the calibration and a capture'
        )

    # --- inputs ----------------------------------------------------------------------

    def _on_views_change(self, views: int) -> None:
        self.captures.use(paired_cameras(views))
        self.get_logger().info(
            f'views set to {views}: synchronizing {", ".join(self.captures.names)}'
        )

    @guarded('calibration change')
    def _on_calibration_change(self, name: str) -> None:
        self.scheduler.calibration_changed()

    @guarded(TARGET_POSE_TOPIC)
    def _on_target_pose(self, msg: PoseStamped) -> None:
        self.scheduler.chart_shown(conversions.stamp_to_ns(msg.header.stamp))

    @guarded('image')
    def _accept_image(self, name: str, msg: Image) -> bool:
        try:
            # every image, also those of captures not reconstructed
            conversions.check_grey_image(msg)
        except InvalidInput as error:
            self.diagnostics.reject(IMAGE_TOPICS[name], error)
            return False
        return True

    @guarded('image')
    def _on_capture(self, stamp_ns: int, messages: dict[str, Image]) -> None:
        """A synchronized capture: hand it to the worker if a reconstruction is wanted."""
        calibrated = [n for n in CAMERA_NAMES if self.cameras.get(n) is not None]
        p = self.params
        taken = self.session.take_capture(stamp_ns, calibrated, messages, p.views, p.aux_wait)
        if taken is not None:
            self.worker.submit(_Capture(taken[0], messages, taken[1]))

    @guarded(DEPTH_INFO_TOPIC)
    def _on_depth_info(self, msg: CameraInfo) -> None:
        try:
            conversions.camera_info_to_camera(msg)  # the whole message must be valid
            _, P = conversions.camera_info_rectification(msg)
        except (InvalidInput, ValueError) as error:
            self.diagnostics.reject(DEPTH_INFO_TOPIC, f'P: {error}')
            return
        stamp_ns = conversions.stamp_to_ns(msg.header.stamp)
        self._send(
            self.session.depth_intrinsics(P[:3, :3], int(msg.width), int(msg.height), stamp_ns)
        )

    @guarded(FUSED_DEPTH_TOPIC)
    def _on_depth(self, msg: Image) -> None:
        if msg.encoding != '32FC1':
            error = InvalidInput(
                f'expected 32FC1 depth, got {msg.encoding!r}', key='encoding', value=msg.encoding
            )
            self.diagnostics.reject(FUSED_DEPTH_TOPIC, error)
            return
        depth = conversions.image_to_numpy(msg)
        self._send(self.session.add_depth(depth, conversions.stamp_to_ns(msg.header.stamp)))

    @guarded('reconstruct call')
    def _on_reconstruct_call(self, reply: Any) -> None:
        """A ~/reconstruct call: it waits for the next capture; the worker answers it, or
        _answer_timed_out_requests after ``service_timeout``."""
        refusal = self.scheduler.add_call(reply, self.params.service_timeout)
        if refusal:
            self.diagnostics.reject('reconstruct call', f'{refusal} (at most {MAX_WAITING_CALLS})')
            reply(False, f'refused: {refusal}')

    @guarded('reconstruct timeout')
    def _answer_timed_out_requests(self) -> None:
        expired, message = self.session.expired_calls(
            self.cameras.missing(), self.params.service_timeout
        )
        for call in expired:
            call.reply(False, message)

    # --- work ------------------------------------------------------------------------

    def _serve(self, job: Any) -> None:
        """The worker's job: a capture (its calls answered), or the republish with normals."""
        if job is _REPUBLISH_WITH_NORMALS:
            self._send(self.session.republish(self.cameras.get('left')))
            return
        try:
            success, message = self._reconstruct(job)
        except Exception as error:  # noqa: BLE001 - the calls must get an answer
            self._on_worker_error(error)
            success, message = False, f'reconstruction failed: {error}'
        for call in job.job.calls:
            call.reply(success, message)

    def _on_worker_error(self, error: Exception) -> None:
        self.diagnostics.reject('reconstruction', f'{type(error).__name__}: {error}')

    def _requests_wait_for_the_next(self, job: Any) -> None:
        if job is not _REPUBLISH_WITH_NORMALS:
            self.scheduler.put_back(job.job)

    def _reconstruct(self, capture: _Capture) -> tuple[bool, str]:
        """Reconstruct one capture and publish; returns (success, message) for the calls
        it serves."""
        cameras = {name: self.cameras[name].camera for name in capture.names}
        outcome = self.session.reconstruct(
            capture.job,
            capture.messages,
            lambda msg: conversions.image_to_grey(msg).astype(float),
            cameras,
            SETTINGS.build(self.params),
            self.cameras.get('left'),
        )
        self._send(outcome)
        return outcome.success, outcome.message

    def _send(self, outcome: Outcome) -> None:
        """Reject what an outcome rejects; publish its waypoints and points, log it and
        publish its report; republish the last waypoints if it says so."""
        for what, reason in outcome.rejections:
            self.diagnostics.reject(what, reason)
        if outcome.republish:
            self.worker.submit_if_idle(_REPUBLISH_WITH_NORMALS)
        sent = outcome.publication
        if sent is None:
            return
        self.waypoint_publisher.publish(
            conversions.matrices_to_path(sent.frames_base, sent.stamp_ns, BASE_FRAME)
        )
        self.points_publisher.publish(
            conversions.points_to_pointcloud2(sent.points_base, sent.stamp_ns, BASE_FRAME)
        )
        self.get_logger().info(outcome.log)
        if outcome.report is not None:
            self.diagnostics.publish('reconstruction', *outcome.report)

    @guarded('status')
    def _publish_status(self) -> None:
        self.diagnostics.publish(
            'status',
            *self.session.status(
                self.cameras.missing(),
                self.params.views,
                self.captures.unsynchronized(),
                self.captures.counts(),
                self.worker.dropped,
            ),
        )

    def close(self) -> None:
        """For run_node: stop the worker; every waiting ~/reconstruct call fails."""
        self.session.close()
        self.worker.close()
        for call in self.scheduler.close():
            call.reply(False, 'curve_recon_node is shutting down')
        self.reconstruct_service.flush()


def main(args: list[str] | None = None) -> int:
    """Run curve_recon_node until SIGINT/SIGTERM; exit status 2 on an unusable parameter
    at start-up (one line)."""
    return run_node(CurveReconNode, args, executor_class=lambda: DeferredServiceExecutor(3))


if __name__ == '__main__':
    raise SystemExit(main())
