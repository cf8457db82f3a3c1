"""calib_node: calibrates the stereo pair and the aux camera from the chart on the precision
stage (or held by hand) and publishes latched CameraInfo (the fitted distortion model,
stereo rectification) and camera poses.

Captures are paired by identical stamp (left, right, aux images and the chart's target
pose) and handed to a worker thread, where a ``CalibrationSession`` (calib_node.session,
no ROS) finds the chart, keeps the views and calibrates; the executor keeps taking images
meanwhile. With ``calibration_file`` set, the saved calibration is published at start
instead and no chart is needed.
"""

import dataclasses
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from sensor_msgs.msg import CameraInfo, Image
from std_srvs.srv import Trigger

from calib_node.calibrate import GAOptions
from calib_node.rig_files import FileSettings, read_rig, write_rig
from calib_node.session import (
    Calibration,
    CalibrationSession,
    SessionSettings,
    handheld_notice,
    silent_cameras_advice,
)
from vgm_common.camera_model import PinholeCamera
from vgm_common.camera_topics import ImageCaptures
from vgm_common.conversions import (
    camera_to_camera_info,
    image_to_grey,
    matrix_to_pose_stamped,
    pose_to_matrix,
    stamp_to_ns,
)
from vgm_common.diagnostics import CountingPublisher
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.geometry import FloatArray
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import (
    BASE_FRAME,
    CAMERA_INFO_TOPICS,
    IMAGE_TOPICS,
    OPTICAL_FRAMES,
    POSE_TOPICS,
    TARGET_POSE_TOPIC,
)
from vgm_common.worker import Worker

# The pairing's counters shown in the views status, by their names there.
CAPTURE_COUNTS = {
    'dropped': 'incomplete capture sets (messages)',
    'matched': 'matched capture sets',
}
Rectification = Mapping[str, tuple[FloatArray, FloatArray]]  # {name: (R (3, 3), P (3, 4))}

VIEW_BACKLOG = 30  # image sets waiting for chart detection
SILENT_CAMERA_S = 10.0  # [s] a camera without images while the others send is named
# The session's settings and the thesis method's (ga.*, network.*): their parameters.
SESSION = ConfigParams(SessionSettings)
GA = ConfigParams(GAOptions)


FILES = ConfigParams(FileSettings)
PARAMETERS = [*SESSION.declarations(), *GA.declarations(), *FILES.declarations()]


class CalibNode(GraphNode):
    """Collects chart views from the paired images (and target poses), calibrates the rig
    and publishes latched CameraInfo and camera poses; with ``calibration_file`` set,
    publishes that calibration instead. Services ``~/calibrate`` and ``~/reset``."""

    node_name = 'calib_node'

    def __init__(self) -> None:
        super().__init__(PARAMETERS)
        # Raises InvalidInput (a one-line start-up error) for a symmetric chessboard or an
        # unknown ArUco dictionary.
        self.session = CalibrationSession(self._settings)
        self.names = self.session.names
        self.info_publishers = self._latched_publishers(CameraInfo, CAMERA_INFO_TOPICS)
        self.pose_publishers = self._latched_publishers(PoseStamped, POSE_TOPICS)
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, '~/calibrate', self._on_calibrate, callback_group=services)
        self.create_service(Trigger, '~/reset', self._on_reset, callback_group=services)
        self.file_mode = bool(self.params.calibration_file)
        if self.file_mode:
            self._publish_file(self.params.calibration_file)
        else:
            self._start_collecting()

    def _settings(self) -> SessionSettings:
        return dataclasses.replace(SESSION.build(self.params), ga=GA.build(self.params))

    def _latched_publishers(self, message_type: Any, topics: Mapping[str, str]) -> dict[str, Any]:
        return {
            n: self.create_publisher(
                message_type, topics[n], LATCHED_QOS, publisher_class=CountingPublisher
            )
            for n in self.names
        }

    def _start_collecting(self) -> None:
        # Every stage view counts: when VIEW_BACKLOG wait, a new one is refused and reported.
        self.worker = Worker(
            lambda view: self._process_view(*view),
            lambda error: self.diagnostics.reject('view', f'{type(error).__name__}: {error}'),
            'calibration',
            capacity=VIEW_BACKLOG,
            keep='oldest',
        )
        # Images are paired by stamp; the target pose of a set is looked up by its stamp
        # (it may come a little before or after the images, or never: handheld).
        self.captures = ImageCaptures(
            self,
            self.names,
            self._on_capture,
            self.params.sync_max_wait,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )
        # The poses get their own group: in one group with the images, rclpy's executor
        # serves a backlog of images first (subscription order), and under load a
        # set's pose came later than TARGET_WAIT_S. _on_target only takes the session's lock.
        self.create_subscription(
            PoseStamped,
            TARGET_POSE_TOPIC,
            self._on_target,
            DEFAULT_QOS,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )
        self._silent_said = ''  # the silent-camera warning last logged
        self.create_timer(1.0, self._publish_status)
        self.get_logger().info(self.session.describe())

    # --- inputs -----------------------------------------------------------------------

    def _on_target(self, msg: PoseStamped) -> None:
        if self.session.source == 'handheld':
            return
        try:  # checked as it arrives, whether or not images of its stamp follow
            if msg.header.frame_id != BASE_FRAME:
                got = msg.header.frame_id
                raise InvalidInput(
                    f'target pose must be in {BASE_FRAME}, got {got!r}', key='frame_id'
                )
            T_base_chart = pose_to_matrix(msg.pose)  # InvalidInput: NaN or not a unit quaternion
        except InvalidInput as error:
            self.diagnostics.reject(TARGET_POSE_TOPIC, error)
            return
        self.session.add_target(stamp_to_ns(msg.header.stamp), T_base_chart)

    def _on_capture(self, stamp_ns: int, messages: dict[str, Image]) -> None:
        if not self.worker.submit((stamp_ns, messages, time.monotonic())):
            if self.session.dropped(stamp_ns):
                self.diagnostics.reject('view', 'the calibration worker is behind: view dropped')

    def _process_view(self, stamp_ns: int, messages: dict[str, Image], completed: float) -> None:
        T_base_chart = self.session.chart_pose_of(stamp_ns, completed)
        if T_base_chart is False:
            return
        greys: dict[str, npt.NDArray[np.float32]] = {}
        misses: list[str] = []
        for name in self.names:
            msg = messages[name]
            try:
                grey = image_to_grey(msg)
                self.session.check_image_size(name, (msg.width, msg.height))
            except (InvalidInput, ValueError) as error:
                self.diagnostics.reject(IMAGE_TOPICS[name], error)
                misses.append(f'{name}: unusable image')
                continue
            greys[name] = grey
        outcome = self.session.add_view(T_base_chart, greys, misses)
        if outcome.handheld_started:  # what auto chose must not be a silent switch
            self.get_logger().info(handheld_notice(self.resolve_topic_name(TARGET_POSE_TOPIC)))
        if outcome.status == 'no_chart':
            self.diagnostics.reject('view', outcome.message)
        elif outcome.status == 'kept':
            self.get_logger().info(outcome.message)
        if outcome.calibrate_now:
            self._calibrate()

    # --- calibration ------------------------------------------------------------------

    def _calibrate(self) -> tuple[bool, str]:
        """Calibrate on all views so far and publish; returns (success, message)."""
        attempt = self.session.attempt(self._silent_cameras())
        calibration = attempt.calibration
        if calibration is None:
            if attempt.log:
                getattr(self.get_logger(), attempt.log)(attempt.message)
            if attempt.level:
                self.diagnostics.publish(
                    'calibration', attempt.level, attempt.message, attempt.values
                )
            return False, attempt.message
        stamp_ns = self._publish(calibration.cameras, calibration.rectification)
        if self.params.output_dir:
            self._write(calibration)
        message, values = self.session.record(calibration)
        values['stamp'] = f'{stamp_ns // 10**9}.{stamp_ns % 10**9:09d}'  # of the CameraInfo
        self.get_logger().info(message)
        self.diagnostics.publish('calibration', 'ok', message, values)
        return True, message

    def _write(self, calibration: Calibration) -> None:
        """Write the calibration to output_dir; a failure is logged and reported."""
        output_dir = self.params.output_dir
        try:
            written = write_rig(output_dir, calibration)
        except (OSError, VgmError) as error:
            self.get_logger().error(f'cannot write {output_dir}: {error}')
            self.diagnostics.publish('calibration', 'error', f'cannot write {output_dir}: {error}')
            return
        if written.plots_missing:
            self.get_logger().warning(f'no plots in {output_dir}: {written.plots_missing}')
        self.get_logger().info(written.summary(tuple(calibration.cameras)))

    def _publish(self, cameras: Mapping[str, PinholeCamera], rectification: Rectification) -> int:
        stamp_ns = self.get_clock().now().nanoseconds
        for name, camera in cameras.items():
            R, P = rectification.get(name, (None, None))
            self.info_publishers[name].publish(
                camera_to_camera_info(camera, stamp_ns, OPTICAL_FRAMES[name], R, P)
            )
            self.pose_publishers[name].publish(
                matrix_to_pose_stamped(camera.T_base_camera, stamp_ns, BASE_FRAME)
            )
        return stamp_ns

    def _publish_file(self, path: str) -> None:
        cameras, rectification = read_rig(path, self.names)  # InvalidInput: start-up error
        self._publish(cameras, rectification)
        message = f'published the calibration of {path}'
        self.get_logger().info(message)
        self.diagnostics.publish('calibration', 'ok', message, {'calibration_file': path})

    # --- services and status ----------------------------------------------------------

    def _on_calibrate(self, _: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.file_mode:
            response.success = False
            response.message = 'publishing calibration_file: no chart views are collected'
            return response
        response.success, response.message = self._calibrate()
        return response

    def _on_reset(self, _: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        response.message = f'forgot {self.session.reset()} views'
        self.get_logger().info(response.message)
        return response

    def _silent_cameras(self) -> str:
        silent = self.captures.silent(SILENT_CAMERA_S)
        topic_of = lambda name: self.resolve_topic_name(IMAGE_TOPICS[name])  # noqa: E731
        return silent_cameras_advice(silent, self.names, topic_of, SILENT_CAMERA_S)

    def _publish_status(self) -> None:
        pairing = self.captures.counts()
        message, values = self.session.status(
            {CAPTURE_COUNTS[k]: pairing[k] for k in CAPTURE_COUNTS}
        )
        silent = self._silent_cameras()
        if silent != self._silent_said:  # a user without ros2cli reads the log
            if silent:
                self.get_logger().warning(silent)
            self._silent_said = silent
        if silent:
            values['silent cameras'] = silent
        self.diagnostics.publish('views', 'warn' if silent else 'ok', silent or message, values)

    def close(self) -> None:
        """For run_node: stop waiting for target poses and close the worker (views still
        queued are not processed)."""
        self.session.close()
        if not self.file_mode:
            self.worker.close()


def main(args: list[str] | None = None) -> int:
    """Run calib_node until SIGINT/SIGTERM; exit status 2 on an unusable parameter or
    calibration file at start-up (one line)."""
    return run_node(CalibNode, args, executor_class=lambda: MultiThreadedExecutor(3))


if __name__ == '__main__':
    raise SystemExit(main())
