"""What sfs_stereo_node keeps between pairs, without ROS: which pairs to take (``max_rate``
chooses by stamps, so a replayed bag gives the same frames), the counts, the last
result's figures for /diagnostics, and when to log (one line per kind of warning at most
every WARN_EVERY_S, an INFO line every ``log_every``), and the rectification tables of
the current calibration. The clock is injected."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sfs_stereo_node.pipeline import DepthResult
from sfs_stereo_node.rectify import RectifiedPair, rectification_maps
from vgm_common.errors import InvalidInput
from vgm_common.settings import setting

if TYPE_CHECKING:
    from vgm_common.camera_topics import CalibratedCamera

WARN_EVERY_S = 10.0  # one log line per kind of warning at most this often


@dataclass(frozen=True)
class PairSettings:
    """How sfs_stereo_node pairs, takes and logs its images: the one source of its
    parameters of these names (the depth itself is ``pipeline.DepthConfig``)."""

    sync_max_wait: float = setting(
        1.0,
        'Longest wait for the other image of a pair.',
        unit='s',
        range=(0.01, 60.0),
        read_only=True,
    )
    log_every: float = setting(
        10.0,
        'Seconds between INFO lines on processed frames (the first frame is always logged).',
        range=(0.0, 3600.0),
    )
    max_rate: float = setting(
        0.0,
        'Process at most this many pairs per second of image time: the first pair of each '
        '1/max_rate slot of stamps [Hz]; 0 = as fast as they come. Frees the CPU for other '
        'nodes (make demo uses 0.25); chosen by stamps, so a replayed bag gives the same '
        'frames.',
        range=(0.0, 100.0),
    )


class DepthSession:
    """The pairs taken, processed and failed, and the last result's figures."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self.processed = self.failed = self.throttled = self.before_calibration = 0
        self._last_slot: int | None = None  # max_rate: the stamp slot of the last pair
        self.last_timings: dict[str, float] = {}
        self.last_density = float('nan')
        self.last_confidence: dict[str, float | int] = {}
        self.last_fusion = ''
        self.last_warnings: tuple[str, ...] = ()
        self._last_warned: dict[str, float] = {}  # kind of warning -> its last log line
        self._last_log = -float('inf')
        self._rectification: tuple[object, RectifiedPair] | None = None  # (key, tables)

    def waiting_for_calibration(self) -> bool:
        """Count a pair that came before the calibration; True for the first (worth a
        log line: a wait, not bad input)."""
        self.before_calibration += 1
        return self.before_calibration == 1

    def take(self, stamp_ns: int, max_rate: float) -> bool:
        """Whether to process the pair of ``stamp_ns``: with ``max_rate`` [Hz] > 0, only
        the first pair of each 1/max_rate slot of stamps."""
        if max_rate > 0:
            slot = int(stamp_ns * max_rate) // 1_000_000_000
            if slot == self._last_slot:
                self.throttled += 1
                return False
            self._last_slot = slot
        return True

    def rectification(
        self,
        calibration_version: int,
        left: CalibratedCamera,
        right: CalibratedCamera,
        image_shape: tuple[int, int],
    ) -> RectifiedPair:
        """The remap tables of the calibrated pair for images of ``image_shape`` (rows,
        cols), made again only when the calibration or the image size changes. Raises
        InvalidInput when a camera_info's size is not the images'."""
        key = (calibration_version, image_shape)
        if self._rectification is not None and self._rectification[0] == key:
            return self._rectification[1]
        for name, calibrated in (('left', left), ('right', right)):
            size = (calibrated.camera.height, calibrated.camera.width)
            if size != image_shape:
                raise InvalidInput(
                    f'{name} camera_info is {size[1]}x{size[0]} but the '
                    f'images are {image_shape[1]}x{image_shape[0]}',
                    key='size',
                )
        tables = rectification_maps(
            left.camera.K,
            left.camera.D,
            left.R,
            left.P,
            right.camera.K,
            right.camera.D,
            right.R,
            right.P,
            (image_shape[1], image_shape[0]),
            (left.camera.distortion_model, right.camera.distortion_model),
        )
        self._rectification = (key, tables)
        return tables

    def record(self, result: DepthResult, log_every: float) -> tuple[list[str], bool]:
        """Keep ``result``'s figures; the warnings to log now (one per kind per
        WARN_EVERY_S) and whether an INFO line is due (the first frame, then every
        ``log_every`` [s])."""
        self.processed += 1
        self.last_timings = result.timings
        self.last_density = result.density
        self.last_confidence = result.confidence
        self.last_fusion = result.fusion or 'none'
        self.last_warnings = result.warnings
        now = self._clock()
        to_log = []
        for warning in result.warnings:
            kind = warning.split(':')[0]
            if now - self._last_warned.get(kind, -float('inf')) >= WARN_EVERY_S:
                self._last_warned[kind] = now
                to_log.append(warning)
        info_due = self.processed == 1 or now - self._last_log >= log_every
        if info_due:
            self._last_log = now
        return to_log, info_due

    def status(
        self, missing_cameras: list[str], counts: Mapping[str, int]
    ) -> tuple[str, str, dict[str, object]]:
        """(level, message, values) of the depth diagnostic; ``counts`` (dropped pairs,
        rejected input) join the session's own."""
        values: dict[str, object] = {
            'frames processed': self.processed,
            'frames dropped (busy)': counts.get('dropped', 0),
            'frames skipped (max_rate)': self.throttled,
            'pairs before calibration': self.before_calibration,
            'pairs failed': self.failed,
            'unpaired images dropped': counts.get('unpaired', 0),
            'match density': f'{self.last_density:.4f}',
            'fused by': self.last_fusion,
            **{
                k: f'{v:.4f}' if isinstance(v, float) else v
                for k, v in self.last_confidence.items()
            },
            'warnings': ' | '.join(self.last_warnings),
            **{f'time {k} [ms]': f'{v * 1000:.1f}' for k, v in self.last_timings.items()},
            **{k: v for k, v in counts.items() if k.startswith('rejected ')},
        }
        if missing_cameras:
            return 'warn', f'no calibration for {", ".join(missing_cameras)}', values
        if not self.processed:
            return 'warn', 'no pair processed yet', values
        if self.last_warnings:
            return 'warn', self.last_warnings[0], values
        return 'ok', f'{self.processed} pairs processed', values
