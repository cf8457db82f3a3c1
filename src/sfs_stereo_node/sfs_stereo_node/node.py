"""sfs_stereo_node: dense depth of the stereo rig's view by semi-global stereo (or the
thesis's SSD) + shape from shading, fused (thesis chapter 5). Subscribes the raw
left/right images and the latched calibration; publishes /stereo/disparity, /depth/stereo,
/depth/sfs (while subscribed), /depth/fused, /depth/confidence, /depth/points and
/depth/camera_info in the rectified left frame (see README.md).

Only the newest synchronized pair is processed, in a worker thread: pairs arriving while
one is processed replace the waiting one and are counted as dropped, so there is never a
backlog, whatever the per-frame time.
"""

from collections.abc import Mapping
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from stereo_msgs.msg import DisparityImage

from sfs_stereo_node.pipeline import DepthConfig, DepthResult, process_pair
from sfs_stereo_node.session import DepthSession, PairSettings
from vgm_common.camera_model import PinholeCamera
from vgm_common.camera_topics import CalibratedCameras, ImageCaptures
from vgm_common.conversions import (
    camera_to_camera_info,
    depth_to_pointcloud2,
    image_to_grey,
    numpy_to_disparity_image,
    numpy_to_image,
)
from vgm_common.diagnostics import CountingPublisher
from vgm_common.errors import InvalidInput
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import (
    DEPTH_CONFIDENCE_TOPIC,
    DEPTH_INFO_TOPIC,
    DEPTH_POINTS_TOPIC,
    DISPARITY_TOPIC,
    FUSED_DEPTH_TOPIC,
    LEFT_RECT_TOPIC,
    OPTICAL_FRAMES,
    SFS_DEPTH_TOPIC,
    STEREO_DEPTH_TOPIC,
)
from vgm_common.worker import Worker

DEPTH_FRAME = OPTICAL_FRAMES['left']  # the rectified left frame: R_left from the optical
# Every DepthConfig field but full_band_layers is a parameter (DepthConfig says how).
DEPTH = ConfigParams(DepthConfig)


def _ordered_ranges(values: Mapping[str, Any]) -> str | None:
    """A reason if a searched range is empty (every pair would then fail), else None."""
    if values['max_disparity'] and values['min_disparity'] >= values['max_disparity']:
        return 'min_disparity must be below max_disparity (or max_disparity 0: automatic)'
    if values['max_depth'] and values['min_depth'] >= values['max_depth']:
        return 'min_depth must be below max_depth (or max_depth 0: no limit)'
    return None


PARAMETERS = [*DEPTH.declarations(), *ConfigParams(PairSettings).declarations()]


class SfsStereoNode(GraphNode):
    """Rectifies the newest synchronized left/right pair, matches it, fuses it with the
    shading, in a worker; publishes the disparity, the depth maps, their confidence, the
    point cloud, the rectified left image and /depth/camera_info (rectified left
    frame)."""

    node_name = 'sfs_stereo_node'
    # Their names before the advanced parameters were grouped by stage (CHANGELOG.md).
    renamed_parameters = {
        'texture_snr': 'ssd.texture_snr',
        'min_texture': 'ssd.min_texture',
        'uniqueness': 'ssd.uniqueness',
        'left_right_check': 'ssd.left_right_check',
        'min_support': 'ssd.min_support',
        'sfs_iterations': 'sfs.iterations',
        'sfs_max_step': 'sfs.max_step',
        'sfs_downsample': 'sfs.downsample',
        'refine_shading_sigma': 'refine.shading_sigma',
        'refine_stereo_sigma': 'refine.stereo_sigma',
        'refine_curvature_sigma': 'refine.curvature_sigma',
        'refine_finest_steps': 'refine.finest_steps',
        'mlp_epochs': 'mlp_rows.epochs',
        'seed': 'mlp_rows.seed',
        'fusion_sigma': 'local_affine.sigma',
        'fusion_weight': 'least_squares.weight',
    }

    def __init__(self) -> None:
        super().__init__(PARAMETERS)
        self.params.add_check(_ordered_ranges)
        self.cameras = CalibratedCameras(self, ('left', 'right'), self.diagnostics)
        self.publishers_ = {
            key: self.create_publisher(kind, topic, DEFAULT_QOS, publisher_class=CountingPublisher)
            for key, kind, topic in (
                ('disparity', DisparityImage, DISPARITY_TOPIC),
                ('stereo', Image, STEREO_DEPTH_TOPIC),
                ('sfs', Image, SFS_DEPTH_TOPIC),
                ('fused', Image, FUSED_DEPTH_TOPIC),
                ('info', CameraInfo, DEPTH_INFO_TOPIC),
                ('confidence', Image, DEPTH_CONFIDENCE_TOPIC),
                ('points', PointCloud2, DEPTH_POINTS_TOPIC),
                ('left_rect', Image, LEFT_RECT_TOPIC),
            )
        }
        self.captures = ImageCaptures(
            self,
            ('left', 'right'),
            self._on_pair,
            self.params.sync_max_wait,
            on_unpaired=self._on_unpaired,
        )
        self.session = DepthSession()
        # the newest pair only: pairs arriving while one is processed replace the waiting
        # one (worker.dropped)
        self.worker = Worker(lambda pair: self._process(*pair), self._on_pair_error, 'depth')
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            'waiting for calibrated camera_info + pose of left and right, and image pairs'
        )

    # --- input ------------------------------------------------------------------------

    def _on_unpaired(self, dropped: int) -> None:
        self.diagnostics.reject(
            'stereo pair',
            InvalidInput(
                f'image without a partner of identical stamp dropped ({dropped} so far)',
                key='stamp',
            ),
        )

    def _on_pair(self, stamp_ns: int, messages: dict[str, Image]) -> None:
        if not self.cameras.ready:  # expected at start-up: a wait, not bad input
            if self.session.waiting_for_calibration():
                self.get_logger().info(
                    'image pairs arrive before the calibration: skipped until camera_info '
                    f'+ pose of {", ".join(self.cameras.missing())} arrive'
                )
            return
        if self.session.take(stamp_ns, self.params.max_rate):
            self.worker.submit((stamp_ns, messages))

    def _on_pair_error(self, error: Exception) -> None:
        self.session.failed += 1
        self.diagnostics.reject(
            'stereo pair',
            error if isinstance(error, InvalidInput) else f'{type(error).__name__}: {error}',
        )

    def _process(self, stamp_ns: int, messages: dict[str, Image]) -> None:
        for name in ('left', 'right'):  # before any conversion: a bound on memory
            msg = messages[name]
            if msg.width * msg.height > self.params.max_pixels:
                raise InvalidInput(
                    f'{name} image {msg.width}x{msg.height} has more than '
                    f'max_pixels {self.params.max_pixels} pixels',
                    key='size',
                )
        left, right = (image_to_grey(messages[n]) for n in ('left', 'right'))
        if left.shape[:2] != right.shape[:2]:
            raise InvalidInput(
                f'left {left.shape[1]}x{left.shape[0]} and right '
                f'{right.shape[1]}x{right.shape[0]} images differ in size',
                key='size',
            )
        if not self.cameras.ready:
            raise InvalidInput(
                f'no calibration yet for {", ".join(self.cameras.missing())} (camera_info + pose)',
                key='camera_info',
            )
        pair = self.session.rectification(
            self.cameras.version, self.cameras['left'], self.cameras['right'], left.shape[:2]
        )
        # SFS alone is a by-product the fusion does not need: made while someone listens
        want_sfs = self.publishers_['sfs'].get_subscription_count() > 0
        result = process_pair(
            left,
            right,
            pair,
            (left.shape[1], left.shape[0]),
            DEPTH.build(self.params),
            want_sfs=want_sfs,
        )
        self._publish(stamp_ns, result)
        warnings, info_due = self.session.record(result, self.params.log_every)
        frame = self.session.processed
        for warning in warnings:
            self.get_logger().warning(f'frame {frame}: {warning}')
        if info_due:
            self.get_logger().info(
                f'frame {frame}: {result.depth_stereo.shape[1]}x'
                f'{result.depth_stereo.shape[0]}, match density {result.density:.3f}, '
                f'fused by {self.session.last_fusion}, '
                f'{result.timings["total"] * 1000:.0f} ms, {self.worker.dropped} dropped'
            )

    def _publish(self, stamp_ns: int, result: DepthResult) -> None:
        h, w = result.depth_stereo.shape
        disparity = numpy_to_disparity_image(
            result.disparity,
            stamp_ns,
            DEPTH_FRAME,
            result.focal_px,
            result.baseline_m,
            result.disparity_range,
            result.disparity_step,
            result.valid_window,
        )
        camera = PinholeCamera(w, h, result.P[:3, :3], np.zeros(5), np.eye(4))
        info = camera_to_camera_info(camera, stamp_ns, DEPTH_FRAME, np.eye(3), result.P)
        # The info first: a subscriber pairing depth with its info by stamp then has both
        # (topics are not ordered across one another by DDS; this is the likely order).
        self.publishers_['info'].publish(info)
        self.publishers_['disparity'].publish(disparity)
        for key, depth in (
            ('stereo', result.depth_stereo),
            ('sfs', result.depth_sfs),
            ('fused', result.depth_fused),
            ('confidence', result.depth_confidence),
        ):
            if depth is None:  # nothing to scale it: the reason is in /diagnostics
                continue
            self.publishers_[key].publish(numpy_to_image(depth, '32FC1', stamp_ns, DEPTH_FRAME))
        if result.depth_fused is not None:
            self.publishers_['points'].publish(
                depth_to_pointcloud2(
                    result.depth_fused, result.P[:3, :3], result.left_rect, stamp_ns, DEPTH_FRAME
                )
            )
        # The host image of the stereo coding nodes: the disparity's grid and stamp.
        self.publishers_['left_rect'].publish(
            numpy_to_image(result.left_rect, 'mono8', stamp_ns, DEPTH_FRAME)
        )

    def _publish_diagnostics(self) -> None:
        level, message, values = self.session.status(
            [] if self.cameras.ready else self.cameras.missing(),
            {
                'dropped': self.worker.dropped,
                'unpaired': self.captures.counts()['dropped'],
                **{f'rejected {k}': v for k, v in self.diagnostics.rejected.items()},
            },
        )
        self.diagnostics.publish('depth', level, message, values)

    def close(self) -> None:
        """For run_node: stop the worker (a waiting pair is not processed) and log the
        pairs processed, dropped and failed."""
        self.worker.close()
        self.get_logger().info(
            f'processed {self.session.processed} pairs, dropped {self.worker.dropped}, '
            f'failed {self.session.failed}'
        )


def main(args: list[str] | None = None) -> int:
    """Run sfs_stereo_node until SIGINT/SIGTERM; exit status 2 on an unusable parameter
    at start-up (one line)."""
    return run_node(SfsStereoNode, args)


if __name__ == '__main__':
    main()
