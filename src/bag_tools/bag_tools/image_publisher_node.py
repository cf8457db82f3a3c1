"""image_publisher: a folder of one's own left/right(/aux) images published to the
graph, as image_publisher does for one camera: each set of images with one stamp on the
cameras' image topics (mono8), and, from a calibration file, the cameras' CameraInfo
and poses on the latched topics calib_node would publish.

The folder holds, per camera, files named ``<camera>*`` (``left01.png``, ``right01.png``)
or a sub-folder ``<camera>/``; the n-th file of each camera in name order forms set n.

    ros2 run bag_tools image_publisher --ros-args -p folder:=my_images -p rate:=1.0
"""

from __future__ import annotations

import threading

from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from bag_tools.image_folder import (
    ImageFolderSettings,
    ImageSetError,
    SetCycle,
    image_sets,
    read_grey,
)
from vgm_common.calibration_io import read_calibration, stereo_rectification
from vgm_common.conversions import camera_to_camera_info, matrix_to_pose_stamped, numpy_to_image
from vgm_common.diagnostics import CountingPublisher
from vgm_common.errors import InvalidInput
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.subscriber_gate import SubscriberGate
from vgm_common.topics import (
    BASE_FRAME,
    CAMERA_INFO_TOPICS,
    IMAGE_TOPICS,
    OPTICAL_FRAMES,
    POSE_TOPICS,
)

FOLDER = ConfigParams(ImageFolderSettings)
PARAMETERS = FOLDER.declarations()


class ImagePublisher(GraphNode):
    """Publishes the folder's image sets at ``rate`` and the calibration file's cameras."""

    node_name = 'image_publisher'

    def __init__(self) -> None:
        super().__init__(PARAMETERS)
        p = FOLDER.build(self.params)
        if not p.folder:
            raise ImageSetError('parameter folder is required (-p folder:=<images>)')
        self.cameras = list(p.cameras)
        self.sets = image_sets(p.folder, self.cameras)
        self.cycle = SetCycle(len(self.sets), p.loop)
        self.exit_when_done = p.exit_when_done
        self.exit_requested = threading.Event()
        self.image_publishers = {
            name: self.create_publisher(
                Image, IMAGE_TOPICS[name], DEFAULT_QOS, publisher_class=CountingPublisher
            )
            for name in self.cameras
        }
        if p.calibration_file:
            self._publish_calibration(p.calibration_file)
        self.gate = SubscriberGate(self, self.image_publishers.values(), 1, p.wait_for_subscribers)
        self.create_timer(1.0 / p.rate, self._publish_next)
        self.get_logger().info(
            f'{len(self.sets)} image sets of {", ".join(self.cameras)} from {p.folder} '
            f'at {p.rate:g} Hz'
            + (f', calibration {p.calibration_file}' if p.calibration_file else '')
        )

    def _publish_calibration(self, path: str) -> None:
        rig = read_calibration(path)  # InvalidInput: a one-line start-up error
        missing = [name for name in self.cameras if name not in rig]
        if missing:
            raise InvalidInput(
                f'calibration_file {path} lacks {", ".join(missing)}', key='calibration_file'
            )
        # As calib_node publishes a saved calibration: left/right re-rectified.
        rectification = {name: rig[name][1:] for name in rig}
        if 'left' in rig and 'right' in rig:
            rectification.update(stereo_rectification(rig['left'][0], rig['right'][0]))
        stamp_ns = self.get_clock().now().nanoseconds
        for name, (camera, _, _) in rig.items():
            R, P = rectification[name]
            info = self.create_publisher(
                CameraInfo,
                CAMERA_INFO_TOPICS[name],
                LATCHED_QOS,
                publisher_class=CountingPublisher,
            )
            pose = self.create_publisher(
                PoseStamped, POSE_TOPICS[name], LATCHED_QOS, publisher_class=CountingPublisher
            )
            info.publish(camera_to_camera_info(camera, stamp_ns, OPTICAL_FRAMES[name], R, P))
            pose.publish(matrix_to_pose_stamped(camera.T_base_camera, stamp_ns, BASE_FRAME))

    def _publish_next(self) -> None:
        if self.exit_requested.is_set() or not self.gate.is_open():
            return
        index = self.cycle.next()
        if index is None:  # each set was shown
            return
        try:
            images = {name: read_grey(path) for name, path in self.sets[index].items()}
        except ImageSetError as error:
            self.diagnostics.reject('image set', error)
            images = {}
        stamp_ns = self.get_clock().now().nanoseconds  # one stamp per set
        for name, image in images.items():
            self.image_publishers[name].publish(
                numpy_to_image(image, 'mono8', stamp_ns, OPTICAL_FRAMES[name])
            )
        if self.cycle.done:
            self.get_logger().info(f'published all {len(self.sets)} image sets')
            if self.exit_when_done:
                self.exit_requested.set()


def main(args: list[str] | None = None) -> int:
    """Run image_publisher; exit status 2 on a missing folder, unusable image sets or
    calibration file (one line)."""
    return run_node(ImagePublisher, args)


if __name__ == '__main__':
    raise SystemExit(main())
