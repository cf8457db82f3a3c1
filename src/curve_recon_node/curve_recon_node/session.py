"""curve_recon_node's task state without ROS: which captures are reconstructed (the
``CaptureScheduler``), the fused depth for the approach axes (``FusedDepth``), the last
published reconstruction, and what each capture, depth image or depth intrinsics makes
the node publish, reject or log. The node converts messages to arrays, hands them here
and sends what comes back; unit-tested in tests/unit/test_curve_session.py with the
injected clock of the scheduler.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from curve_recon_node.fused_depth import FusedDepth
from curve_recon_node.pipeline import (
    NoCurve,
    Reconstruction,
    ReconstructionSettings,
    reconstruct_capture,
)
from curve_recon_node.report import capture_status, reconstruction_report
from curve_recon_node.scheduler import CaptureJob, CaptureScheduler, WaitingCall
from curve_recon_node.waypoints import DEPTH_RANGE_M, waypoint_frames
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.geometry import FloatArray
from vgm_common.topics import DEPTH_INFO_TOPIC, FUSED_DEPTH_TOPIC, IMAGE_TOPICS

CHART_POSE_GRACE = 0.5  # [s] a capture waits this long for a target pose of its stamp


class SessionParameters(Protocol):
    """The node's parameters the session reads at every use (a set_parameters call may
    change them while it runs): never copied."""

    use_depth_normals: bool
    normal_window_px: int
    method: str
    degree: int


class RectifiedCamera(Protocol):
    """The left camera, whose rectified frame the fused depth lives in (a
    ``vgm_common.camera_topics.CalibratedCamera``): the camera with its pose and its
    rectification R (x_rect = R x_left)."""

    @property
    def camera(self) -> PinholeCamera:
        """The camera with its pose in base_link."""

    @property
    def R(self) -> np.ndarray:
        """The rectification (3, 3)."""


@dataclass(frozen=True)
class Publication:
    """What the node publishes for a reconstruction: the waypoint frames (M, 4, 4) in
    base_link, the raw points (K, 3) [m], the capture's stamp, and where the approach
    axes came from (for the log)."""

    stamp_ns: int
    frames_base: FloatArray
    points_base: FloatArray
    normals_source: str


@dataclass
class Outcome:
    """What one input leads to: inputs to reject (what, reason) with a diagnostic, the
    publication if any, the reconstruction diagnostic (level, message, values) to log
    and publish, the answer to the ~/reconstruct calls a capture served, the INFO line to
    log, and whether the last waypoints are to be republished with the new depth."""

    rejections: list[tuple[str, Exception | str]] = field(default_factory=list)
    publication: Publication | None = None
    report: tuple[str, str, dict[str, Any]] | None = None
    success: bool = False
    message: str = ''
    log: str = ''  # the INFO line of a publication
    republish: bool = False  # the last waypoints again, now with depth normals

    def reject(self, what: str, reason: Exception | str) -> Outcome:
        """Add a rejection; returns the outcome."""
        self.rejections.append((what, reason))
        return self


class ReconstructionSession:
    """The captures to reconstruct and what is published from them.

    Args:
        parameters: the node's live parameters (``SessionParameters``).
        clock: monotonic seconds for the scheduler (``time.monotonic``; a test's own).
        wait: waits up to the given seconds for the target pose of a capture's stamp,
            returns early (True) when the session is closing (``threading.Event.wait``;
            a test's own moves its clock instead).
    """

    def __init__(
        self,
        parameters: SessionParameters,
        clock: Callable[[], float] = time.monotonic,
        wait: Callable[[float], bool] | None = None,
    ) -> None:
        self.parameters = parameters
        self.scheduler = CaptureScheduler(clock)
        self.fused_depth = FusedDepth()
        self._stopping = threading.Event()
        self._wait = self._stopping.wait if wait is None else wait
        # (stamp_ns, reconstruction) last published, for republishing with normals
        self.last: tuple[int, Reconstruction] | None = None
        self.normals_published = False

    # --- captures --------------------------------------------------------------------

    def take_capture(
        self,
        stamp_ns: int,
        calibrated: Sequence[str],
        complete: Collection[str],
        views: int,
        aux_wait: float,
    ) -> tuple[CaptureJob, tuple[str, ...]] | None:
        """A synchronized capture of the cameras ``complete``: the job to reconstruct (with
        the calls it answers) and the cameras to use, given those ``calibrated`` and the
        ``views`` and ``aux_wait`` parameters (``CaptureScheduler.cameras_to_use``); None
        if no reconstruction is wanted now, the rig is not calibrated, or ``views``
        changed while this capture was completed."""
        names = self.scheduler.cameras_to_use(calibrated, views, aux_wait)
        if names is None or not set(names) <= set(complete):
            return None
        job = self.scheduler.take(stamp_ns)
        return None if job is None else (job, names)

    def reconstruct(
        self,
        job: CaptureJob,
        images: Mapping[str, Any],
        decode: Callable[[Any], FloatArray],
        cameras: Mapping[str, PinholeCamera],
        settings: ReconstructionSettings,
        left: RectifiedCamera | None,
    ) -> Outcome:
        """A capture the scheduler took (``job``): ``images`` of the cameras {name:
        camera} (view 1 first) as they came, each made a grey (H, W) array by ``decode``
        (the node's message conversion; InvalidInput: the image is rejected) only once
        the capture is known not to show the calibration chart: its target pose,
        stamped like its images, may come after them, so it gets CHART_POSE_GRACE to
        come first (a chart capture puts its calls back to wait for the next one).
        ``left``: for the approach axes from fused depth."""
        self._wait(CHART_POSE_GRACE)
        if self.scheduler.is_chart(job):
            return Outcome(message='chart capture')
        outcome = Outcome()
        names = tuple(cameras)
        grey = {}
        for name in names:
            try:
                grey[name] = decode(images[name])
            except InvalidInput as error:
                outcome.message = f'{IMAGE_TOPICS[name]}: {error}'
                return outcome.reject(IMAGE_TOPICS[name], error)
        for name, camera in cameras.items():
            if grey[name].shape != (camera.height, camera.width):
                size_error = InvalidInput(
                    f'{name} image is {grey[name].shape[1]}x{grey[name].shape[0]} but its '
                    f'camera_info says {camera.width}x{camera.height}',
                    key='size',
                )
                outcome.message = str(size_error)
                return outcome.reject(IMAGE_TOPICS[name], size_error)
        try:
            result = reconstruct_capture(grey, cameras, settings, names)
            publication = self._publication(job.stamp_ns, result, left, outcome)
        except NoCurve as error:
            outcome.message = f'no curve: {error}'
            return outcome.reject('no curve', error)
        except (VgmError, np.linalg.LinAlgError, ValueError) as error:
            outcome.message = f'reconstruction failed: {error}'
            return outcome.reject('reconstruction', error)
        self.last = (job.stamp_ns, result)
        self.scheduler.succeeded()
        parameters = {'method': self.parameters.method, 'degree': self.parameters.degree}
        outcome.report = reconstruction_report(
            result, names, job.stamp_ns, publication.normals_source, parameters
        )
        outcome.publication, outcome.success = publication, True
        outcome.message = outcome.report[1]
        outcome.log = f'{outcome.message}; approach from {publication.normals_source}'
        return outcome

    def republish(self, left: RectifiedCamera | None) -> Outcome:
        """The last waypoints again, now with depth normals (once they came): the
        publication only if they are now known."""
        outcome = Outcome()
        if self.last is None or self.normals_published:
            return outcome
        stamp_ns, result = self.last
        publication = self._publication(stamp_ns, result, left, outcome)
        if self.normals_published:
            outcome.publication, outcome.success = publication, True
            outcome.log = (
                f'fused depth arrived: republished {len(result.waypoints_base)} waypoints '
                f'with {publication.normals_source}'
            )
        return outcome

    def _publication(
        self, stamp_ns: int, result: Reconstruction, left: RectifiedCamera | None, outcome: Outcome
    ) -> Publication:
        approach = self._approach_directions(result.waypoints_base, left, outcome)
        frames = waypoint_frames(result.waypoints_base, result.closed, approach)
        self.normals_published = approach is not None
        if approach is None:
            source = 'base -z (no depth normals)'
        else:
            known = int(np.all(np.isfinite(approach), axis=1).sum())
            source = f'depth normals at {known}/{len(approach)} waypoints'
        return Publication(stamp_ns, frames, result.points_base, source)

    def _approach_directions(
        self, waypoints_base: FloatArray, left: RectifiedCamera | None, outcome: Outcome
    ) -> FloatArray | None:
        """Approach directions (N, 3) into the surface from the fused depth, or None (no
        depth, or none usable at the waypoints: see normals_from_depth)."""
        if not self.parameters.use_depth_normals or left is None:
            return None
        try:
            return self.fused_depth.approach_directions(
                waypoints_base, left.camera.T_base_camera, left.R, self.parameters.normal_window_px
            )
        except InvalidInput as error:  # checked on arrival: only a changed rig gets here
            outcome.reject(FUSED_DEPTH_TOPIC, error)
            return None

    # --- fused depth -----------------------------------------------------------------

    def depth_intrinsics(
        self, K_rect: FloatArray, width: int, height: int, stamp_ns: int
    ) -> Outcome:
        """The depth camera_info's K (3, 3): a depth image that waited for intrinsics of
        its stamp is added now (``add_depth``)."""
        outcome = Outcome()
        try:
            waiting = self.fused_depth.set_intrinsics(K_rect, width, height)
        except (InvalidInput, ValueError) as error:
            return outcome.reject(DEPTH_INFO_TOPIC, f'P: {error}')
        if waiting is None:
            return outcome
        if waiting.stamp_ns != stamp_ns:
            return outcome.reject(
                FUSED_DEPTH_TOPIC, f'no {DEPTH_INFO_TOPIC} of its stamp came: not used'
            )
        return self.add_depth(waiting.depth_m, waiting.stamp_ns)

    def add_depth(self, depth_m: npt.ArrayLike, stamp_ns: int) -> Outcome:
        """A fused depth image [m]; ``republish`` when it is the first usable depth after
        waypoints without normals (a capture that is waiting will use it anyway)."""
        outcome = Outcome()
        first = self.fused_depth.latest is None
        try:
            removed = self.fused_depth.add(depth_m, stamp_ns)
        except InvalidInput as error:
            return outcome.reject(FUSED_DEPTH_TOPIC, error)
        if removed is None:
            return outcome  # waits for its camera_info
        if any(removed.values()):
            # the rest of the image still serves; these pixels never give a normal
            outcome.reject(
                'depth values',
                f'{FUSED_DEPTH_TOPIC}: ignored for approach axes: '
                f'{removed["not_positive"]} zero or negative, {removed["too_far"]} '
                f'beyond {DEPTH_RANGE_M[1]:g} m, {removed["too_near"]} nearer than '
                f'{DEPTH_RANGE_M[0]:g} m',
            )
        outcome.republish = (
            first
            and self.last is not None
            and self.parameters.use_depth_normals
            and not self.normals_published
        )
        return outcome

    # --- status ----------------------------------------------------------------------

    def expired_calls(
        self, uncalibrated: Sequence[str], timeout: float
    ) -> tuple[list[WaitingCall], str]:
        """The ~/reconstruct calls past their deadline (no longer waiting) and the failure
        they are answered with, given the cameras still ``uncalibrated``."""
        message = f'no synchronized capture within {timeout:g} s' + (
            f' (not calibrated: {", ".join(uncalibrated)})' if uncalibrated else ''
        )
        return self.scheduler.expired(), message

    def status(
        self,
        uncalibrated: Sequence[str],
        views: int,
        unsynchronized: int,
        capture_counts: Mapping[str, int],
        dropped_work: int,
    ) -> tuple[str, str, dict[str, Any]]:
        """(level, message, values) of the 'status' diagnostic (``capture_status``), with
        the image streams' counts (``ImageCaptures``) and the worker's drops."""
        level, message = capture_status(uncalibrated, views, unsynchronized, bool(self.last))
        values = {
            **capture_counts,
            'skipped_chart_captures': self.scheduler.skipped_chart,
            'dropped_work': dropped_work,
            'waiting_requests': self.scheduler.waiting,
            'depth': 'yes' if self.fused_depth.latest is not None else 'no',
        }
        return level, message, values

    def close(self) -> None:
        """Stop waiting for chart poses (a capture that waits goes on at once)."""
        self._stopping.set()
