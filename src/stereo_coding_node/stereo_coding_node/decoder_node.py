"""stereo_decoding_node: takes the coded left image (``transport``: raw
/stereo/coded/image or JPEG /stereo/coded/image/compressed), and where it finds the
watermark publishes /stereo/decoded/disparity, /stereo/decoded/left/image_rect and the
right view synthesised from both, /stereo/decoded/right/image_rect.

/diagnostics says whether a watermark was found and how confidently; an unmarked or
wrong-key image gives "no watermark" and nothing on the decoded topics (method ours: a
CRC-32 decides). Method thesis is non-blind: it always extracts something, as the
thesis's scheme does; it needs the encoder's ``key_file``."""

from typing import Any

import numpy as np
from sensor_msgs.msg import CompressedImage, Image
from stereo_msgs.msg import DisparityImage

from stereo_coding_node.coding import KeyFile, decode_image
from stereo_coding_node.errors import CodingError
from stereo_coding_node.inputs import GREY_ENCODINGS, compressed_image_size
from stereo_coding_node.settings import CodingSettings, DecoderSettings
from vgm_common.conversions import (
    compressed_to_grey,
    image_to_numpy,
    numpy_to_disparity_image,
    numpy_to_image,
    stamp_to_ns,
)
from vgm_common.diagnostics import CountingPublisher
from vgm_common.errors import VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import (
    CODED_COMPRESSED_TOPIC,
    CODED_IMAGE_TOPIC,
    DECODED_DISPARITY_TOPIC,
    DECODED_LEFT_TOPIC,
    DECODED_RIGHT_TOPIC,
)
from vgm_common.worker import Worker

CODING = ConfigParams(CodingSettings)
DECODER = ConfigParams(DecoderSettings)
PARAMETERS = [*CODING.declarations(), *DECODER.declarations()]


class StereoDecodingNode(GraphNode):
    """Looks for the watermark in each coded image (``transport``), in a worker; where it
    finds one, publishes the decoded disparity, left image and synthesised right view,
    and reports on /diagnostics whether and how confidently it found one."""

    node_name = 'stereo_decoding_node'

    def __init__(self) -> None:
        super().__init__(PARAMETERS)
        self.publishers_ = {
            key: self.create_publisher(kind, topic, DEFAULT_QOS, publisher_class=CountingPublisher)
            for key, kind, topic in (
                ('disparity', DisparityImage, DECODED_DISPARITY_TOPIC),
                ('left', Image, DECODED_LEFT_TOPIC),
                ('right', Image, DECODED_RIGHT_TOPIC),
            )
        }
        self.worker = Worker(self._process, self._on_error, 'stereo decoding')
        if self.params.transport == 'compressed':
            self.create_subscription(
                CompressedImage, CODED_COMPRESSED_TOPIC, self._on_coded, DEFAULT_QOS
            )
        else:
            self.create_subscription(Image, CODED_IMAGE_TOPIC, self._on_coded, DEFAULT_QOS)
        self.key_file = KeyFile()  # method thesis: the encoder's side information
        self.decoded = self.unmarked = self.failed = 0
        self.last: dict[str, Any] = {}  # the latest figures, for the diagnostic
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f'method {self.params.method}: waiting for the coded image ({self.params.transport})'
        )

    def _on_coded(self, msg: Image | CompressedImage) -> None:
        self.worker.submit(msg)

    def _on_error(self, error: Exception) -> None:
        self.failed += 1
        # One of ours says what was wrong; anything else is named by its type.
        reason = error if isinstance(error, VgmError) else f'{type(error).__name__}: {error}'
        self.diagnostics.reject('coded image', reason)

    def _process(self, msg: Image | CompressedImage) -> None:
        if isinstance(msg, CompressedImage):
            width, height = compressed_image_size(bytes(msg.data))
        else:
            width, height = msg.width, msg.height
        if width * height > self.params.max_pixels:  # before any decoding: a memory bound
            raise CodingError(
                f'coded image {width}x{height} has more than max_pixels '
                f'{self.params.max_pixels} pixels',
                key='size',
            )
        if isinstance(msg, CompressedImage):
            coded = compressed_to_grey(msg)
        else:
            if msg.encoding not in GREY_ENCODINGS:
                raise CodingError(
                    f'{CODED_IMAGE_TOPIC} must be mono8, got {msg.encoding!r}', key='encoding'
                )
            coded = image_to_numpy(msg)
        stamp_ns, frame = stamp_to_ns(msg.header.stamp), msg.header.frame_id
        decoded = decode_image(coded, CODING.build(self.params), self.key_file)
        self.last = decoded.figures
        if not decoded.found:
            self.unmarked += 1
            self.diagnostics.publish('watermark', 'warn', 'no watermark', self.last)
            return
        assert decoded.disparity_px is not None and decoded.left is not None
        assert decoded.right is not None  # found: all three
        self.decoded += 1
        self.diagnostics.publish('watermark', 'ok', 'watermark found', self.last)
        disparity = decoded.disparity_px
        known = np.isfinite(disparity)
        out = numpy_to_disparity_image(  # f and t (the baseline) as the user gave them
            disparity,
            stamp_ns,
            frame,
            self.params.focal_px,
            self.params.baseline_m,
            (0.0, float(np.max(disparity[known])) if known.any() else 0.0),
            1.0,
        )
        self.publishers_['disparity'].publish(out)
        self.publishers_['left'].publish(numpy_to_image(decoded.left, 'mono8', stamp_ns, frame))
        self.publishers_['right'].publish(numpy_to_image(decoded.right, 'mono8', stamp_ns, frame))

    def _publish_diagnostics(self) -> None:
        values = {
            'method': self.params.method,
            'decoded': self.decoded,
            'no watermark': self.unmarked,
            'failed': self.failed,
            'dropped (newer input)': self.worker.dropped,
            **self.last,
            **{f'rejected {k}': v for k, v in self.diagnostics.rejected.items()},
        }
        level = 'ok' if self.decoded else 'warn'
        message = (
            f'{self.decoded} images decoded'
            if self.decoded
            else 'no watermarked image decoded yet'
        )
        self.diagnostics.publish('decoding', level, message, values)

    def close(self) -> None:
        """For run_node: stop the worker (a waiting image is not decoded) and log the
        counts."""
        self.worker.close()
        self.get_logger().info(
            f'decoded {self.decoded}, no watermark {self.unmarked}, failed {self.failed}'
        )


def main(args: list[str] | None = None) -> int:
    """Run stereo_decoding_node until SIGINT/SIGTERM; exit status 2 on an unusable
    parameter at start-up (one line)."""
    return run_node(StereoDecodingNode, args)


if __name__ == '__main__':
    main()
