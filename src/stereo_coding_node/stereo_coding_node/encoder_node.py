"""stereo_coding_node: pairs /stereo/left/image_rect with /stereo/disparity by stamp and
publishes the left image carrying its disparity on /stereo/coded/image (mono8) and
/stereo/coded/image/compressed (JPEG, ``jpeg_quality``).

``method: ours`` (default) is blind and keyed (``key``); ``method: thesis`` is the
thesis's non-blind ZIG-ZAG + DFrFT + SVD scheme, whose side information is written to
``key_file`` for the decoder."""

import os
import time

import numpy as np
from sensor_msgs.msg import CompressedImage, Image
from stereo_msgs.msg import DisparityImage

from stereo_coding_node import blind, thesis
from stereo_coding_node.errors import CodingError
from stereo_coding_node.inputs import known_disparity
from vgm_common.conversions import (
    grey_to_compressed_jpeg,
    image_to_numpy,
    numpy_to_image,
    stamp_to_ns,
)
from vgm_common.diagnostics import CountingPublisher
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import Param
from vgm_common.qos import DEFAULT_QOS
from vgm_common.sync import ExactTimeSync
from vgm_common.topics import (
    CODED_COMPRESSED_TOPIC,
    CODED_IMAGE_TOPIC,
    DISPARITY_TOPIC,
    LEFT_RECT_TOPIC,
)
from vgm_common.worker import Worker

METHODS = ('ours', 'thesis')
GREY_ENCODINGS = ('mono8', '8UC1')


def _two_finite_angles(angles):
    if len(angles) != 2:
        return 'needs two angles'
    return None if all(np.isfinite(angles)) else 'angles must be finite'


def common_params():
    """The parameters both coding nodes declare (they must agree on them)."""
    return [
        Param(
            'method',
            'ours',
            'ours = blind keyed QIM in the 8x8 DCT mid band; thesis = '
            'ZIG-ZAG + DFrFT + SVD, non-blind (key_file).',
            choices=METHODS,
        ),
        Param(
            'key',
            'vgm-stereo',
            'Shared secret of method ours: seeds where and how the bits are hidden.',
            check=lambda v: None if v else 'must not be empty',
        ),
        Param(
            'strength',
            0.0,
            "Embedding strength; 0 = the method's default. thesis: "
            'alpha_w (0.45); ours: QIM step [grey levels] (28, about 43 dB).',
            range=(0.0, 128.0),
        ),
        Param(
            'key_file',
            '',
            'method thesis: the side information (.npz) the encoder writes and the decoder reads.',
        ),
        Param(
            'frft_angles',
            list(thesis.DEFAULT_ANGLES),
            'method thesis: DFrFT angles (a, b) [rad] (order 2a/pi), not given by the thesis.',
            check=_two_finite_angles,
        ),
        Param(
            'watermark_scale',
            'pixels',
            'method thesis: how the disparity becomes the '
            'watermark (unstated in the thesis): pixels, full_range [0, 255], unit [0, 1].',
            choices=thesis.WATERMARK_SCALES,
        ),
    ]


def effective_strength(params):
    """The embedding strength of the nodes' ``params``: ``strength`` when > 0, else the
    method's default (thesis: alpha_w; ours: the QIM step [grey levels])."""
    if params.strength > 0:
        return params.strength
    return thesis.THESIS_STRENGTH if params.method == 'thesis' else blind.DEFAULT_STEP


PARAMETERS = common_params() + [
    Param(
        'jpeg_quality',
        90,
        'JPEG quality of /stereo/coded/image/compressed.',
        range=(1, 100),
    ),
    Param(
        'sync_max_wait',
        1.0,
        'Longest wait for the image or disparity of a stamp [s].',
        range=(0.01, 60.0),
        read_only=True,
    ),
]


class StereoCodingNode(GraphNode):
    """Pairs the rectified left image with the disparity of the same stamp, embeds the
    disparity (``method``) in a worker and publishes the coded image, raw and JPEG; method
    thesis also writes its side information to ``key_file``."""

    node_name = 'stereo_coding_node'

    def __init__(self):
        super().__init__(PARAMETERS)
        self.coded_publisher = self.create_publisher(
            Image, CODED_IMAGE_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self.compressed_publisher = self.create_publisher(
            CompressedImage, CODED_COMPRESSED_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self.sync = ExactTimeSync(
            ('image', 'disparity'),
            self._on_pair,
            queue_size=10,
            max_wait=self.params.sync_max_wait,
        )
        self.sync_dropped_reported = 0
        self.worker = Worker(self._process, self._on_error, 'stereo coding')
        self.create_subscription(
            Image, LEFT_RECT_TOPIC, lambda m: self._on_input('image', m), DEFAULT_QOS
        )
        self.create_subscription(
            DisparityImage, DISPARITY_TOPIC, lambda m: self._on_input('disparity', m), DEFAULT_QOS
        )
        self.coded = self.failed = 0
        self.last = {}
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f'method {self.params.method}: waiting for {LEFT_RECT_TOPIC} + {DISPARITY_TOPIC}'
        )

    def _on_input(self, key, msg):
        stamp = stamp_to_ns(msg.header.stamp)
        self.sync.add(key, stamp, msg, time.monotonic())
        if self.sync.dropped > self.sync_dropped_reported:
            self.sync_dropped_reported = self.sync.dropped
            self.diagnostics.reject(
                'input pair',
                InvalidInput(
                    'image or disparity without a partner of identical stamp dropped '
                    f'({self.sync.dropped} so far)',
                    key='stamp',
                ),
            )

    def _on_pair(self, stamp_ns, messages):
        self.worker.submit((stamp_ns, messages))

    def _on_error(self, error):
        self.failed += 1
        if not isinstance(error, VgmError):
            error = f'{type(error).__name__}: {error}'
        self.diagnostics.reject('input pair', error)

    def _process(self, item):
        stamp_ns, messages = item
        image_msg, disparity_msg = messages['image'], messages['disparity']
        if image_msg.encoding not in GREY_ENCODINGS:
            raise CodingError(
                f'{LEFT_RECT_TOPIC} must be mono8, got {image_msg.encoding!r}', key='encoding'
            )
        if disparity_msg.image.encoding != '32FC1':
            raise CodingError(
                f'{DISPARITY_TOPIC} image must be 32FC1, got {disparity_msg.image.encoding!r}',
                key='encoding',
            )
        left = image_to_numpy(image_msg)
        disparity = image_to_numpy(disparity_msg.image).astype(float)
        if disparity.shape != left.shape:
            raise CodingError(
                f'disparity {disparity.shape[1]}x{disparity.shape[0]} and image '
                f'{left.shape[1]}x{left.shape[0]} differ in size',
                key='size',
            )
        disparity = known_disparity(disparity, disparity_msg.min_disparity)
        started = time.perf_counter()
        p = self.params
        if p.method == 'thesis':
            if not p.key_file:
                raise CodingError(
                    'method thesis needs key_file (where the side information is written)',
                    key='key_file',
                )
            coded, key = thesis.encode(
                left, disparity, tuple(p.frft_angles), effective_strength(p), p.watermark_scale
            )
            self._write_key(key, p.key_file)
            reference = thesis.zigzag_degrade(left)
        else:
            coded = blind.encode(left, disparity, p.key, effective_strength(p))
            reference = left
        elapsed = time.perf_counter() - started
        frame = image_msg.header.frame_id
        self.coded_publisher.publish(numpy_to_image(coded, 'mono8', stamp_ns, frame))
        self.compressed_publisher.publish(
            grey_to_compressed_jpeg(coded, p.jpeg_quality, stamp_ns, frame)
        )
        mse = float(np.mean((coded.astype(float) - reference) ** 2))
        self.coded += 1
        self.last = {
            'psnr [dB]': f'{10 * np.log10(255**2 / max(mse, 1e-12)):.2f}',
            'encode [ms]': f'{1000 * elapsed:.1f}',
        }
        if p.method == 'ours':
            self.last['payload bits'] = blind.payload_bits(left.shape)
            self.last['fine payload bits'] = blind.fine_payload_bits(left.shape)  # 0: too small

    def _write_key(self, key, path):
        # Written whole, then renamed: a decoder never reads half a key.
        temporary = f'{path}.tmp{os.getpid()}'
        try:
            key.save(temporary)
            os.replace(temporary, path)
        except OSError as error:
            raise CodingError(
                f'cannot write key_file {path}: {error.strerror}', key='key_file'
            ) from None

    def _publish_diagnostics(self):
        values = {
            'method': self.params.method,
            'coded': self.coded,
            'failed': self.failed,
            'dropped (newer input)': self.worker.dropped,
            'dropped (no partner)': self.sync.dropped,
            **self.last,
            **{f'rejected {k}': v for k, v in self.diagnostics.rejected.items()},
        }
        level = 'ok' if self.coded else 'warn'
        message = f'{self.coded} images coded' if self.coded else 'no image coded yet'
        self.diagnostics.publish('coding', level, message, values)

    def close(self):
        """For run_node: stop the worker (a waiting pair is not coded) and log the
        counts."""
        self.worker.close()
        self.get_logger().info(f'coded {self.coded} images, failed {self.failed}')


def main(args=None):
    """Run stereo_coding_node until SIGINT/SIGTERM; exit status 2 on an unusable
    parameter at start-up (one line)."""
    return run_node(StereoCodingNode, args)


if __name__ == '__main__':
    main()
