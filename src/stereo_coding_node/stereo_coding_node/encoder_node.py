"""stereo_coding_node: pairs /stereo/left/image_rect with /stereo/disparity by stamp and
publishes the left image carrying its disparity on /stereo/coded/image (mono8) and
/stereo/coded/image/compressed (JPEG, ``jpeg_quality``).

``method: ours`` (default) is blind and keyed (``key``); ``method: thesis`` is the
thesis's non-blind ZIG-ZAG + DFrFT + SVD scheme, whose side information is written to
``key_file`` for the decoder."""

from typing import Any

from sensor_msgs.msg import CompressedImage, Image
from stereo_msgs.msg import DisparityImage

from stereo_coding_node.coding import encode_image
from stereo_coding_node.errors import CodingError
from stereo_coding_node.inputs import GREY_ENCODINGS
from stereo_coding_node.settings import CodingSettings, EncoderSettings
from vgm_common.camera_topics import ImageCaptures
from vgm_common.conversions import grey_to_compressed_jpeg, image_to_numpy, numpy_to_image
from vgm_common.diagnostics import CountingPublisher
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import (
    CODED_COMPRESSED_TOPIC,
    CODED_IMAGE_TOPIC,
    DISPARITY_TOPIC,
    LEFT_RECT_TOPIC,
)
from vgm_common.worker import Worker

CODING = ConfigParams(CodingSettings)
ENCODER = ConfigParams(EncoderSettings)
PARAMETERS = [*CODING.declarations(), *ENCODER.declarations()]
# The image and the disparity it carries, paired by stamp as a capture's images are.
INPUTS = {'image': (Image, LEFT_RECT_TOPIC), 'disparity': (DisparityImage, DISPARITY_TOPIC)}


class StereoCodingNode(GraphNode):
    """Pairs the rectified left image with the disparity of the same stamp, embeds the
    disparity (``method``) in a worker and publishes the coded image, raw and JPEG; method
    thesis also writes its side information to ``key_file``."""

    node_name = 'stereo_coding_node'

    def __init__(self) -> None:
        super().__init__(PARAMETERS)
        self.coded_publisher = self.create_publisher(
            Image, CODED_IMAGE_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self.compressed_publisher = self.create_publisher(
            CompressedImage, CODED_COMPRESSED_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self.worker = Worker(self._process, self._on_error, 'stereo coding')
        self.inputs = ImageCaptures(
            self,
            tuple(INPUTS),
            self._on_pair,
            self.params.sync_max_wait,
            streams=INPUTS,
            on_unpaired=self._on_unpaired,
        )
        self.coded = self.failed = 0
        self.last: dict[str, Any] = {}  # the latest figures, for the diagnostic
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f'method {self.params.method}: waiting for {LEFT_RECT_TOPIC} + {DISPARITY_TOPIC}'
        )

    def _on_unpaired(self, dropped: int) -> None:
        self.diagnostics.reject(
            'input pair',
            InvalidInput(
                'image or disparity without a partner of identical stamp dropped '
                f'({dropped} so far)',
                key='stamp',
            ),
        )

    def _on_pair(self, stamp_ns: int, messages: dict[str, Any]) -> None:
        self.worker.submit((stamp_ns, messages))

    def _on_error(self, error: Exception) -> None:
        self.failed += 1
        # One of ours says what was wrong; anything else is named by its type.
        reason = error if isinstance(error, VgmError) else f'{type(error).__name__}: {error}'
        self.diagnostics.reject('input pair', reason)

    def _process(self, item: tuple[int, dict[str, Any]]) -> None:
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
        coded = encode_image(
            image_to_numpy(image_msg),
            image_to_numpy(disparity_msg.image),
            disparity_msg.min_disparity,
            CODING.build(self.params),
        )
        frame = image_msg.header.frame_id
        self.coded_publisher.publish(numpy_to_image(coded.image, 'mono8', stamp_ns, frame))
        self.compressed_publisher.publish(
            grey_to_compressed_jpeg(coded.image, self.params.jpeg_quality, stamp_ns, frame)
        )
        self.coded += 1
        self.last = coded.figures

    def _publish_diagnostics(self) -> None:
        values = {
            'method': self.params.method,
            'coded': self.coded,
            'failed': self.failed,
            'dropped (newer input)': self.worker.dropped,
            'dropped (no partner)': self.inputs.counts()['dropped'],
            **self.last,
            **{f'rejected {k}': v for k, v in self.diagnostics.rejected.items()},
        }
        level = 'ok' if self.coded else 'warn'
        message = f'{self.coded} images coded' if self.coded else 'no image coded yet'
        self.diagnostics.publish('coding', level, message, values)

    def close(self) -> None:
        """For run_node: stop the worker (a waiting pair is not coded) and log the
        counts."""
        self.worker.close()
        self.get_logger().info(f'coded {self.coded} images, failed {self.failed}')


def main(args: list[str] | None = None) -> int:
    """Run stereo_coding_node until SIGINT/SIGTERM; exit status 2 on an unusable
    parameter at start-up (one line)."""
    return run_node(StereoCodingNode, args)


if __name__ == '__main__':
    main()
