"""A calibration session without ROS: it takes capture sets (grey images by camera and
the chart's target poses by stamp), keeps the chart views, decides when enough are there,
calibrates the rig and reports the result. calib_node only converts messages, publishes
and logs what the session returns; the session is unit-tested on plain arrays.

Stage views carry the chart pose of their stamp (the target pose, which may arrive a
little before or after the images); handheld views carry none and are kept only when
they add coverage (camera_calibration's rule). ``chart.source: auto`` takes stage views
once a target pose has arrived, handheld ones before.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np

from calib_node.bundle import bundle_adjust_selected
from calib_node.calibrate import (
    LM_STARTS,
    METHODS,
    MODEL_CHOICES,
    CalibrationError,
    CameraFit,
    GAOptions,
    calibrate_rig,
    stage_uncertainty,
)
from calib_node.chart_detection import CharucoChart, Detection, chart_points, detect_chessboard
from calib_node.coverage import Coverage, view_parameters
from calib_node.cross_validation import (
    MIN_HALF_VIEWS,
    CrossValidation,
    compare_halves,
    split_chart_views,
)
from calib_node.uncertainty import Uncertainty, working_range
from vgm_common.calibration_io import stereo_rectification
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray, make_transform, quaternion_to_matrix, rpy_to_matrix
from vgm_common.settings import setting
from vgm_common.topics import BASE_FRAME, CAMERA_NAMES

CHART_SOURCES = ('auto', 'stage', 'handheld')
CHART_PATTERNS = ('chessboard', 'charuco')
TARGET_WAIT_S = 1.0  # [s] how long an image set waits for a target pose of its stamp
RECENT_TARGETS = 200  # target poses kept by stamp until their images arrive
RESERVE_VIEWS = 100  # handheld views like a kept one, held for when the kept ones fall short


def rig_pose_check(value: tuple[float, ...] | list[float]) -> str | None:
    """Why ``rig_pose`` is unusable, or None."""
    if len(value) not in (6, 7) or not all(np.isfinite(value)):
        return 'expected 6 (x y z roll pitch yaw) or 7 (x y z qx qy qz qw) finite numbers'
    if len(value) == 7 and abs(np.linalg.norm(value[3:]) - 1) > 1e-3:
        return 'the quaternion must have unit norm'
    return None


def _cameras_check(value: tuple[str, ...] | list[str]) -> str | None:
    if {'left', 'right'} <= set(value) <= set(CAMERA_NAMES) and len(set(value)) == len(value):
        return None
    return f'expected left, right and optionally aux, got {list(value)}'


@dataclass(frozen=True)
class SessionSettings:
    """The session's settings, the one source of calib_node's parameters of the same
    names (``chart_rows`` is ``chart.rows``), read again at every use, so a changed
    parameter applies to the next view or calibration. The chart and the cameras are
    fixed for a session."""

    chart_pattern: str = setting(
        'chessboard',
        'chessboard (found whole), or charuco (cv2.aruco ChArUco board of the same squares: '
        'its markers identify the corners, so partial and occluded views count).',
        choices=CHART_PATTERNS,
        read_only=True,
        name='chart.pattern',
    )
    chart_rows: int = setting(
        6,
        'Inner corners along the chart y axis; for a chessboard rows + cols must be odd (the '
        'board must not be symmetric under a half turn).',
        range=(2, 100),
        read_only=True,
        name='chart.rows',
    )
    chart_cols: int = setting(
        9,
        'Inner corners along the chart x axis.',
        range=(2, 100),
        read_only=True,
        name='chart.cols',
    )
    chart_spacing: float = setting(
        0.025,
        'Square size (chessboard and ChArUco).',
        unit='m',
        range=(1e-4, 10.0),
        read_only=True,
        name='chart.spacing',
    )
    chart_dictionary: str = setting(
        'DICT_5X5_100',
        "charuco: the board's predefined ArUco dictionary (a cv2.aruco DICT_* name; an "
        'unknown one is a start-up error listing the valid ones).',
        read_only=True,
        name='chart.dictionary',
    )
    chart_marker_size: float = setting(
        0.0,
        'charuco: the side of its ArUco markers; 0: 0.75 chart.spacing.',
        unit='m',
        range=(0.0, 10.0),
        read_only=True,
        name='chart.marker_size',
    )
    chart_min_corners: int = setting(
        6,
        'charuco: fewest identified corners a camera needs for its view to count (not all '
        'on one line).',
        range=(4, 10000),
        read_only=True,
        name='chart.min_corners',
    )
    chart_source: str = setting(
        'auto',
        'stage: views need a /calibration/target_pose of their stamp; handheld: target '
        'poses are ignored, chart poses are estimated; auto: stage once target poses '
        'arrive, handheld before.',
        choices=CHART_SOURCES,
        read_only=True,
        name='chart.source',
    )
    rig_pose: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        'The left camera optical frame in base_link when no view has a target pose: x y z '
        '[m] roll pitch yaw [rad], or x y z qx qy qz qw.',
        check=rig_pose_check,
    )
    cameras: tuple[str, ...] = setting(
        CAMERA_NAMES,
        "The rig's cameras: left and right, aux optional; a two-camera rig is [left, right].",
        check=_cameras_check,
        read_only=True,
    )
    min_coverage: float = setting(
        0.5,
        "Handheld: each of x, y, size and skew must reach this fraction of camera_calibration's "
        'ranges (0.7, 0.7, 0.4, 0.5) before calibrating.',
        range=(0.0, 1.0),
    )
    select_views: bool = setting(
        True,
        'Handheld: keep a view only if its (x, y, size, skew) differ from every kept '
        "view's by 0.2 (camera_calibration's rule); false keeps every view.",
    )
    min_views: int = setting(
        3,
        'Fewest views a calibration is tried on (a view: a capture in which at least one '
        'camera found the chart; the very same images again are no new view); 3 is '
        "Zhang's minimum per camera. Whether the views suffice is max_projection_std_px's "
        'call.',
        range=(1, 10000),
    )
    max_projection_std_px: float = setting(
        3.0,
        'A calibration is accepted only when its predicted projection uncertainty (standard '
        'deviation, from the adjustment covariance, of where a point at the working range '
        'lands) is at most this over the whole image in every camera; lm only (the other '
        'methods give no covariance). 3 px: a figure in pixels means the same on any rig, '
        "and a collection spread over camera_calibration's ranges reaches it even with the "
        "corner noise of real photographs (OpenCV's 13 pairs at 0.36 px RMS: 2.1-2.3 px), "
        'while one that leaves the image corners to extrapolation (their first 3-4 views: '
        '3.0-3.1 px) does not.',
        unit='px',
        range=(0.0, 1e6),
    )
    auto_calibrate: bool = setting(
        True,
        'Calibrate as soon as min_views views are collected and max_projection_std_px is '
        'met, and again with every later view (the calibrate service recalibrates on all '
        'views so far).',
    )
    method: str = setting(
        'lm',
        'lm (ours: DLT or GA start + Levenberg-Marquardt, distortion_model), lxpm_ga (the thesis: '
        'GA + network refinement) or opencv (cv2.calibrateCamera, the reference).',
        choices=METHODS,
    )
    lm_start: str = setting(
        'dlt',
        'Start of lm: the closed-form DLT, or ga (the thesis GA + network).',
        choices=LM_STARTS,
    )
    seed: int = setting(0, 'Random seed of the GA.', range=(0, 2**31 - 1))
    ga: GAOptions = GAOptions()  # the ga.* and network.* parameters (GAOptions' own)
    fit_tangential: bool = setting(True, 'Estimate p1, p2 (else 0).')
    select_model: bool = setting(
        True,
        'lm: with fit_tangential, fit with and without p1, p2 and keep them only where they '
        'pay by BIC (n ln(RSS0/RSS1) > 2 ln n; per camera in stage mode, over the rig '
        'handheld); they otherwise trade against the principal point.',
    )
    fit_k3: bool = setting(False, 'Estimate k3 (else 0).')
    distortion_model: str = setting(
        'auto',
        'lm (stage and handheld): the lens model fitted and published, plumb_bob, '
        'rational_polynomial (k1..k6, p1, p2: wide lenses) or equidistant (cv2.fisheye '
        'k1..k4: fisheye lenses); auto: with select_model each camera fitted with all three '
        'and the lowest BIC kept, as for p1, p2, left and right one model (without '
        'select_model: plumb_bob). The other methods fit plumb_bob.',
        choices=MODEL_CHOICES,
    )
    max_rms_px: float = setting(
        2.0,
        'A calibration whose reprojection RMS exceeds this in any camera is refused (not '
        'published).',
        unit='px',
        range=(0.0, 1e6),
    )
    max_blur_px: float = setting(
        4.0,
        'Chart detections whose edge width (cv2.estimateChessboardSharpness) exceeds this '
        'are rejected as blurred.',
        unit='px',
        range=(0.5, 100.0),
    )


def rig_pose_matrix(value: tuple[float, ...] | list[float]) -> FloatArray:
    """``rig_pose`` (x y z roll pitch yaw [m, rad] or x y z qx qy qz qw) -> T_base_left."""
    value = [float(v) for v in value]
    R = rpy_to_matrix(*value[3:]) if len(value) == 6 else quaternion_to_matrix(value[3:])
    return make_transform(R, value[:3])


class ViewOutcome(NamedTuple):
    """What became of a capture set: ``kept`` (a new view; ``message`` is its log line),
    ``similar`` (handheld, like a kept view), ``repeat`` (the very images of an earlier
    view, republished) or ``no_chart`` (``message`` says why).
    ``handheld_started``: the first
    handheld view of ``chart_source: auto`` (worth a log line); ``calibrate_now``: the
    view completed what automatic calibration waits for."""

    status: str
    message: str = ''
    handheld_started: bool = False
    calibrate_now: bool = False


class NotReady(CalibrationError):
    """Too few views, (``coverage`` true) a handheld collection that lacks coverage, or
    (``uncertain`` true) views that do not determine the cameras to max_projection_std_px."""

    def __init__(self, message: str, coverage: bool = False, uncertain: bool = False) -> None:
        super().__init__(message)
        self.coverage = coverage
        self.uncertain = uncertain


class Calibration(NamedTuple):
    """A calibrated rig: cameras in base_link, stereo rectification {name: (R, P)}, the
    per-camera fits, the frame the poses were solved in and the solver's time."""

    cameras: dict[str, PinholeCamera]
    rectification: dict[str, tuple[FloatArray, FloatArray]]
    fits: dict[str, CameraFit]
    reference: str
    seconds: float
    views: int
    handheld: bool
    camera_views: dict[str, int]  # views in which each camera saw the chart
    uncertainty: Uncertainty | None  # None: the method gives no covariance (lxpm_ga, opencv)
    # {name: [(observed corners (N, 2), observed - projected (N, 2)) per view it saw]} [px]
    residuals: dict[str, list[tuple[FloatArray, FloatArray]]]
    # The two halves of the views against each other; None: fewer than 2 * MIN_HALF_VIEWS
    # views, or a half that does not calibrate (a camera missing from it).
    cross_validation: CrossValidation | None = None
    # [(left (N, 2), right (N, 2)) corners of each view both saw, NaN rows for unseen] [px]
    stereo_corners: tuple[tuple[FloatArray, FloatArray], ...] = ()

    def quality(self) -> dict[str, dict[str, float | int]]:
        """Per camera: reprojection RMS [px], corner count, views and the predicted
        projection uncertainty at the working range (the file's record); the baseline's
        standard deviation with the right camera."""
        quality: dict[str, dict[str, float | int]] = {
            name: {'rms_px': fit.rms_px, 'points': fit.points, 'views': self.camera_views[name]}
            for name, fit in self.fits.items()
        }
        if self.uncertainty is not None:
            u = self.uncertainty
            for name, entry in quality.items():
                entry['projection_std_worst_px'] = u.worst_px[name]
                entry['projection_std_median_px'] = u.median_px[name]
                entry['working_range_m'] = u.range_m[name]
            quality['right']['baseline_std_m'] = u.baseline_std_m
        if self.cross_validation is not None:
            for name, entry in quality.items():
                entry['cross_validation_worst_px'] = self.cross_validation.worst_px[name]
                entry['cross_validation_median_px'] = self.cross_validation.median_px[name]
        return quality


class Attempt(NamedTuple):
    """What a calibration attempt gives the node: ``calibration`` to publish (None: refused,
    ``message`` says why), the diagnostic to publish for a refusal (``level`` '' for
    none, with ``values``) and the logger level of its message ('' for none)."""

    calibration: Calibration | None
    message: str = ''
    level: str = ''
    values: dict[str, Any] = {}  # noqa: RUF012 (a NamedTuple default, never mutated)
    log: str = ''


class _Fit(NamedTuple):
    """A calibration of some views before it is judged: the fits, the frame they were
    solved in, the solver's time, the uncertainty (None: no covariance) and every view's
    chart pose in base_link (given or estimated)."""

    fits: dict[str, CameraFit]
    reference: str
    seconds: float
    uncertainty: Uncertainty | None
    T_base_chart: list[FloatArray]


# A view: the chart pose in base_link (None: handheld) and the corners {camera: (N, 2)}.
View = tuple[FloatArray | None, dict[str, FloatArray]]


class CalibrationSession:
    """Chart views collected from capture sets, and the rig calibrated from them.

    Thread-safe: capture sets are processed on a worker thread while target poses, the
    services and the status come from the executor's. ``clock`` is a monotonic clock [s]
    (injected for tests); ``settings`` returns the current settings."""

    def __init__(
        self,
        settings: Callable[[], SessionSettings],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._settings = settings
        self._clock = clock
        first = settings()
        self.pattern = first.chart_pattern
        self.charuco: CharucoChart | None = None
        if self.pattern == 'charuco':  # the markers' ids fix the orientation
            try:
                self.charuco = CharucoChart(
                    first.chart_rows,
                    first.chart_cols,
                    first.chart_spacing,
                    first.chart_marker_size,
                    first.chart_dictionary,
                    first.chart_min_corners,
                )
            except ValueError as error:
                raise InvalidInput(f'chart.dictionary: {error}', key='chart.dictionary') from None
        elif (first.chart_rows + first.chart_cols) % 2 == 0:
            raise InvalidInput(
                'parameters chart.rows + chart.cols must be odd (the '
                'board must not be symmetric under a half turn)',
                key='chart.rows',
            )
        self.names = tuple(n for n in CAMERA_NAMES if n in first.cameras)
        self.source = first.chart_source
        self.rows, self.cols = first.chart_rows, first.chart_cols
        self.chart = chart_points(self.rows, self.cols, first.chart_spacing)  # (N, 3) [m]
        self._lock = threading.Lock()  # views, image sizes, counters, targets
        self._target_arrived = threading.Condition(self._lock)
        self._calibration_lock = threading.Lock()  # one calibration at a time
        self._detection_pool = ThreadPoolExecutor(len(self.names))
        self.views: list[View] = []
        # select_views: views like a kept one, used when the kept ones miss
        # max_projection_std_px (the newest RESERVE_VIEWS)
        self.reserve: list[View] = []
        self.last_projection_std: tuple[str, float] | None = None  # the latest attempt's worst
        self.coverage = Coverage()
        self._targets: dict[int, FloatArray] = {}  # stamp_ns -> T_base_chart, most recent
        self._target_seen = False  # auto: a target pose arrived (the stage is in use)
        self._handheld_said = False
        # name -> (width, height), fixed by the first good image
        self.image_sizes: dict[str, tuple[int, int]] = {}
        self.rejected_views = 0
        self.similar_views = 0  # handheld views like a kept one (select_views), or dropped
        self.unposed_sets = 0  # stage: image sets without a target pose of their stamp
        self.repeated_views = 0  # the same images again (a folder republished in a loop)
        self._seen_images: set[bytes] = set()  # digests of the images of the views taken
        self.calibrations = 0
        self.last_result: dict[str, Any] | None = None
        self._stopping = threading.Event()

    def describe(self) -> str:
        """The log line of a session starting to collect views."""
        settings = self._settings()
        return (
            f'collecting chart views ({settings.method}, {self.rows}x{self.cols} '
            f'{self.pattern}, chart.source {self.source}, cameras '
            f'{", ".join(self.names)}, min_views {settings.min_views})'
        )

    # --- inputs -------------------------------------------------------------------------

    def add_target(self, stamp_ns: int, T_base_chart: FloatArray) -> None:
        """The chart pose of the capture set of ``stamp_ns`` (ignored when handheld)."""
        if self.source == 'handheld':
            return
        with self._lock:
            self._targets[stamp_ns] = T_base_chart
            while len(self._targets) > RECENT_TARGETS:
                del self._targets[next(iter(self._targets))]
            self._target_seen = True
            self._target_arrived.notify_all()

    def dropped(self, stamp_ns: int) -> bool:
        """Account for a capture set dropped before processing (the queue was full);
        True if it was a stage view (worth reporting), False for a handheld one (a
        stream outrunning detection loses views like a kept one)."""
        with self._lock:
            posed = stamp_ns in self._targets
            if not posed:
                self.similar_views += 1
        return posed

    def check_image_size(self, name: str, size: tuple[int, int]) -> None:
        """InvalidInput if camera ``name``'s image (width, height) differs from its first."""
        with self._lock:
            expected = self.image_sizes.setdefault(name, size)
        if size != expected:
            raise InvalidInput(
                f'image size {size[0]}x{size[1]} differs from this '
                f"camera's earlier {expected[0]}x{expected[1]}",
                key='size',
            )

    def add_view(
        self,
        T_base_chart: FloatArray | None,
        greys: Mapping[str, np.ndarray],
        misses: list[str],
    ) -> ViewOutcome:
        """Find the chart in a capture set and keep the view if it is one: its chart pose
        (from :meth:`chart_pose_of`; None when handheld), the grey images of the cameras
        whose image was usable (``misses`` says why the others were not)."""
        handheld_started = False
        if T_base_chart is None and self.source == 'auto' and not self._handheld_said:
            self._handheld_said = handheld_started = True
        digest = _images_digest(greys)
        with self._lock:
            if digest in self._seen_images:  # one photograph is one view, however often sent
                self.repeated_views += 1
                return ViewOutcome('repeat', handheld_started=handheld_started)
        settings = self._settings()
        # OpenCV's detector releases the GIL: the cameras' images are searched in parallel.
        detections = dict(
            zip(
                greys,
                self._detection_pool.map(
                    lambda grey: self._detect(grey, settings), greys.values()
                ),
            )
        )
        misses = list(misses)
        corners = {}
        for name, detection in detections.items():
            if detection.corners is None:
                misses.append(f'{name}: {detection.reason}')
            else:
                corners[name] = detection.corners
        if not corners:
            with self._lock:
                self.rejected_views += 1
            return ViewOutcome(
                'no_chart',
                'chart not found in any camera (' + '; '.join(misses) + ')',
                handheld_started,
            )
        with self._lock:
            self._seen_images.add(digest)  # a view, kept or like a kept one
            if T_base_chart is None:
                first = next(n for n in self.names if n in corners)
                parameters = view_parameters(
                    corners[first], self.rows, self.cols, greys[first].shape[::-1]
                )
                if settings.select_views and not self.coverage.is_new(parameters):
                    self.similar_views += 1
                    self.reserve.append((T_base_chart, corners))
                    del self.reserve[:-RESERVE_VIEWS]
                    return ViewOutcome('similar', handheld_started=handheld_started)
                self.coverage.add(parameters)
            self.views.append((T_base_chart, corners))
            count = len(self.views)
            coverage = self.coverage.summary() if T_base_chart is None else ''
            # What to move next, in the log too: a user without ros2cli cannot read
            # /diagnostics.
            still = (
                self.coverage.missing(settings.min_coverage)
                if T_base_chart is None and not self.calibrations
                else ''
            )
            # Every new view from min_views on: until max_projection_std_px is met, then
            # to refine what was published.
            calibrate_now = (
                settings.auto_calibrate
                and count >= settings.min_views
                and not self._coverage_missing(self.views, settings)
            )
        message = (
            f'view {count}: chart found in {", ".join(corners)}'
            + (f' (not in {"; ".join(misses)})' if misses else '')
            + (f'; coverage {coverage}' if coverage else '')
            + (f' (still: {still})' if still else '')
        )
        return ViewOutcome('kept', message, handheld_started, calibrate_now)

    def _detect(self, grey: np.ndarray, settings: SessionSettings) -> Detection:
        """The chart's corners in one image (N, 2) in chart order, NaN rows for a
        ChArUco board's corners not seen."""
        if self.charuco is not None:
            return self.charuco.detect(grey)
        return detect_chessboard(grey, self.rows, self.cols, settings.max_blur_px)

    def chart_pose_of(self, stamp_ns: int, completed: float) -> FloatArray | None | Literal[False]:
        """The chart pose T_base_chart of the capture set of ``stamp_ns``, waiting for it
        as the source asks until TARGET_WAIT_S after ``completed`` (the monotonic time
        [s] the set was complete: a backlog adds no wait); None: a handheld view; False:
        a stage set without a pose (not a view, counted)."""
        if self.source == 'handheld':
            return None
        deadline = completed + TARGET_WAIT_S  # a backlog of sets adds no wait
        with self._lock:
            while stamp_ns not in self._targets and not self._stopping.is_set():
                remaining = deadline - self._clock()
                if remaining <= 0:
                    break
                self._target_arrived.wait(remaining)
            target = self._targets.pop(stamp_ns, None)
            if target is None and (self.source == 'stage' or self._target_seen):
                self.unposed_sets += 1  # outside the stage's chart phase: not a view
                return False
        return target

    # --- calibration --------------------------------------------------------------------

    def _coverage_missing(self, views: list[View], settings: SessionSettings) -> str:
        """What a handheld collection lacks ('' if enough, or if every view is posed)."""
        if all(T is not None for T, _ in views):
            return ''
        return self.coverage.missing(settings.min_coverage)

    def calibrate(self) -> Calibration:
        """Calibrate on all views so far. NotReady when there are too few views or too
        little coverage; CalibrationError (its message names the view count) when the
        views give no calibration or a camera's RMS exceeds ``max_rms_px``."""
        settings = self._settings()
        with self._lock:
            views = list(self.views)
            missing = self._coverage_missing(views, settings) if views else ''
            summary = self.coverage.summary()
        if missing:  # say what to do with the chart first: more views alike would not help
            raise NotReady(
                f'not enough coverage in {len(views)} views ({summary}'
                f'; need {100 * settings.min_coverage:.0f} % each, and min_views '
                f'{settings.min_views}): {missing}',
                coverage=True,
            )
        if len(views) < settings.min_views:
            raise NotReady(f'{len(views)} views collected, min_views is {settings.min_views}')
        with self._lock:
            reserve = list(self.reserve)
        with self._calibration_lock:
            try:
                fit = self._fit(views, settings)
                if reserve and _too_uncertain(fit.uncertainty, settings):
                    # The kept views fall short: the ones select_views set aside may not.
                    views = views + reserve
                    fit = self._fit(views, settings)
                fits, uncertainty = fit.fits, fit.uncertainty
                cameras = {name: fit.camera(self.image_sizes[name]) for name, fit in fits.items()}
                rectification = stereo_rectification(cameras['left'], cameras['right'])
            except (CalibrationError, InvalidInput, ValueError, np.linalg.LinAlgError) as error:
                raise CalibrationError(
                    f'calibration failed on {len(views)} views: {error}'
                ) from error
        if uncertainty is not None:
            with self._lock:
                self.last_projection_std = uncertainty.worst()
        if _too_uncertain(uncertainty, settings):
            assert uncertainty is not None
            name, worst = uncertainty.worst()
            raise NotReady(
                f'{len(views)} views do not determine the cameras yet: predicted projection '
                f'uncertainty {worst:.2f} px in {name} at {uncertainty.range_m[name]:.2f} m '
                f'(max_projection_std_px {settings.max_projection_std_px:g}): show the chart '
                'in more places, nearer the image corners and tilted',
                uncertain=True,
            )
        handheld = any(T is None for T, _ in views)
        camera_views = {n: sum(n in corners for _, corners in views) for n in fits}
        residuals: dict[str, list[tuple[FloatArray, FloatArray]]] = {n: [] for n in fits}
        seen: dict[str, list[FloatArray]] = {n: [] for n in fits}  # corners in the camera [m]
        for T, (_, corners) in zip(fit.T_base_chart, views):
            points = self.chart @ T[:3, :3].T + T[:3, 3]
            for name, observed in corners.items():
                visible = np.isfinite(observed[:, 0])  # a ChArUco view's corners seen
                projected = cameras[name].project(points[visible])[0]
                residuals[name].append((observed[visible], observed[visible] - projected))
                seen[name].append(cameras[name].to_camera(points[visible]))
        ranges = {n: working_range(np.concatenate(seen[n])) for n in fits}
        with self._calibration_lock:
            cross_validation = self._cross_validate(views, settings, ranges)
        return Calibration(
            cameras,
            rectification,
            fits,
            fit.reference,
            fit.seconds,
            len(views),
            handheld,
            camera_views,
            uncertainty,
            residuals,
            cross_validation,
            tuple(
                (corners['left'], corners['right'])
                for _, corners in views
                if 'left' in corners and 'right' in corners
            ),
        )

    def _cross_validate(
        self, views: list[View], settings: SessionSettings, ranges_m: dict[str, float]
    ) -> CrossValidation | None:
        """The views' two halves calibrated apart and compared at ``ranges_m`` (the full
        calibration's working ranges); None when there are too few views or a half does
        not calibrate."""
        if len(views) < 2 * MIN_HALF_VIEWS:
            return None
        corners = [c for _, c in views]
        halves = split_chart_views(corners, self.names, self.rows, self.cols, self.image_sizes)
        handheld = any(T is None for T, _ in views)  # each half in its own left camera frame
        try:
            solutions = [self._fit([views[i] for i in half], settings) for half in halves]
            if any(set(s.fits) != set(ranges_m) for s in solutions):
                return None
            cameras = [
                {n: f.camera(self.image_sizes[n]) for n, f in s.fits.items()} for s in solutions
            ]
            return compare_halves(
                cameras[0],
                cameras[1],
                ranges_m,
                (len(halves[0]), len(halves[1])),
                handheld,
                (solutions[0].uncertainty, solutions[1].uncertainty),
            )
        except (CalibrationError, InvalidInput, ValueError, np.linalg.LinAlgError):
            return None  # a half that does not calibrate: the full calibration stands

    def attempt(self, silent: str = '') -> Attempt:
        """:meth:`calibrate`, its refusals turned into what the node reports: a refusal
        for too few views or too little coverage is the service's answer (coverage also
        a WARN diagnostic), one for too much uncertainty also a log line (what to show
        next), a failed calibration an error line and diagnostic. ``silent``: what the
        node knows about cameras that send nothing, which comes first in a refusal."""
        try:
            return Attempt(self.calibrate())
        except NotReady as refusal:
            if silent:  # why there are no views comes first
                return Attempt(None, f'{refusal}; {silent}')
            if refusal.coverage:
                _, values = self.status({})
                coverage = {'views': values['views'], 'coverage': values.get('coverage', '')}
                return Attempt(None, str(refusal), 'warn', coverage)
            return Attempt(None, str(refusal), log='info' if refusal.uncertain else '')
        except CalibrationError as error:
            with self._lock:
                views = len(self.views)
            values = {'views': views, 'method': self._settings().method}
            return Attempt(None, str(error), 'error', values, 'error')

    def _observations(
        self, views: list[View]
    ) -> dict[str, tuple[FloatArray, FloatArray, tuple[int, int]]]:
        observations, missing = {}, []
        for name in self.names:
            pairs = [  # stage views only: every T is known
                (T, corners[name]) for T, corners in views if name in corners and T is not None
            ]
            if not pairs:
                missing.append(name)
                continue
            seen = [np.isfinite(uv[:, 0]) for _, uv in pairs]  # a ChArUco view's corners seen
            observations[name] = (
                np.concatenate(
                    [(self.chart @ T[:3, :3].T + T[:3, 3])[s] for (T, _), s in zip(pairs, seen)]
                ),
                np.concatenate([uv[s] for (_, uv), s in zip(pairs, seen)]),
                self.image_sizes[name],
            )
        if missing:
            raise CalibrationError(f'the chart was never found in {", ".join(missing)}')
        return observations

    def _calibrate_handheld(
        self, views: list[View], settings: SessionSettings
    ) -> tuple[dict[str, CameraFit], str, Uncertainty, list[FloatArray]]:
        """Bundle adjustment over the views: {name: CameraFit} with poses in base_link,
        the reference frame, the uncertainty and every view's chart pose in base_link."""
        if settings.method != 'lm':
            raise CalibrationError(
                f'method {settings.method} needs target poses (the '
                'stage); handheld views calibrate with lm'
            )
        result = bundle_adjust_selected(
            self.chart,
            [corners for _, corners in views],
            {n: self.image_sizes[n] for n in self.names},
            [T for T, _ in views],
            self.names,
            settings.fit_tangential,
            settings.fit_k3,
            settings.select_model,
            settings.distortion_model,
        )
        T_base_ref = (
            rig_pose_matrix(settings.rig_pose) if result.reference != BASE_FRAME else np.eye(4)
        )
        fits = {
            n: f._replace(T_base_camera=T_base_ref @ f.T_base_camera)
            for n, f in result.fits.items()
        }
        T_base_chart = [T_base_ref @ T for T in result.T_ref_chart]
        return fits, result.reference, result.uncertainty, T_base_chart

    def _fit(self, views: list[View], settings: SessionSettings) -> _Fit:
        """The views' calibration, handheld or stage; CalibrationError when a camera's
        RMS exceeds max_rms_px."""
        started = time.perf_counter()
        uncertainty: Uncertainty | None
        if any(T is None for T, _ in views):
            fits, reference, uncertainty, T_base_chart = self._calibrate_handheld(views, settings)
            seconds = time.perf_counter() - started
        else:
            reference = BASE_FRAME
            T_base_chart = [T for T, _ in views if T is not None]
            observations = self._observations(views)
            result = calibrate_rig(
                observations,
                settings.method,
                settings.seed,
                settings.lm_start,
                settings.ga,
                settings.fit_tangential,
                settings.fit_k3,
                settings.select_model,
                # views of equal size share out the noise levels; ChArUco views differ
                len(self.chart) if self.charuco is None else None,
                settings.distortion_model,
            )
            fits, seconds = result.fits, result.seconds
            uncertainty = stage_uncertainty(fits, observations)
        worst = max(fits, key=lambda n: fits[n].rms_px)
        if fits[worst].rms_px > settings.max_rms_px:
            raise CalibrationError(
                f'{worst}: reprojection RMS {fits[worst].rms_px:.3g} px '
                f'exceeds max_rms_px {settings.max_rms_px:g}'
            )
        return _Fit(fits, reference, seconds, uncertainty, T_base_chart)

    def record(self, calibration: Calibration) -> tuple[str, dict[str, Any]]:
        """Count ``calibration`` as published; its one-line summary and diagnostic values."""
        settings = self._settings()
        fits, cameras = calibration.fits, calibration.cameras
        rms = ' '.join(f'{n}={f.rms_px:.3f}' for n, f in fits.items())
        baseline = np.linalg.norm(cameras['left'].centre_base - cameras['right'].centre_base)
        mode = 'handheld' if calibration.handheld else 'stage'
        message = (
            f'calibrated {len(cameras)} cameras from {calibration.views} views: rms '
            f'{rms} px, baseline {baseline:.4f} m ({settings.method}, {mode}, '
            f'{calibration.seconds:.2f} s)'
        )
        values: dict[str, Any] = {
            'views': calibration.views,
            'method': settings.method,
            'chart source': mode,
            'reference frame': calibration.reference,
            'time_s': f'{calibration.seconds:.3f}',
            'baseline_m': f'{baseline:.6f}',
        }
        with self._lock:
            if calibration.handheld:
                values['coverage'] = self.coverage.summary()
            for name, fit in fits.items():
                values[f'rms_px {name}'] = f'{fit.rms_px:.4f}'
                values[f'points {name}'] = fit.points
                values[f'views {name}'] = calibration.camera_views[name]
            values.update(_uncertainty_values(calibration.uncertainty))
            values.update(_cross_validation_values(calibration.cross_validation))
            self.calibrations += 1
            self.last_result = values
        return message, values

    # --- control and status -------------------------------------------------------------

    def reset(self) -> int:
        """Forget every view (and the image sizes); returns how many were forgotten."""
        with self._lock:
            forgotten = len(self.views)
            self.views.clear()
            self.reserve.clear()
            self.last_projection_std = None
            self.coverage.clear()
            self.image_sizes.clear()
            self._seen_images.clear()
        return forgotten

    def status(self, capture_counts: Mapping[str, int]) -> tuple[str, dict[str, object]]:
        """The collection's one-line status and its values (``capture_counts``: the
        pairing's counters, shown beside the session's)."""
        settings = self._settings()
        with self._lock:
            values: dict[str, object] = {
                'views': len(self.views),
                'rejected views': self.rejected_views,
                'calibrations': self.calibrations,
                'similar views skipped': self.similar_views,
                'repeated images skipped': self.repeated_views,
                'image sets without a target pose': self.unposed_sets,
                **capture_counts,
            }
            if self.last_result:  # the latest calibration's quality, repeated at 1 Hz
                values.update(
                    {
                        k: v
                        for k, v in self.last_result.items()
                        if k.startswith(
                            ('rms_px', 'projection_std', 'baseline_std', 'cross_validation')
                        )
                    }
                )
            if self.last_projection_std:  # the latest attempt's, accepted or not
                name, worst = self.last_projection_std
                values['latest projection_std_worst_px'] = f'{worst:.3f} ({name})'
            handheld = any(T is None for T, _ in self.views)
            if handheld:
                values['coverage'] = self.coverage.summary()
            missing = self._coverage_missing(self.views, settings) if handheld else ''
        message = (
            f'{values["views"]} views, {self.calibrations} calibrations'
            if self.calibrations or values['views']
            else 'waiting for chart views'
        )
        if handheld:
            message += f'; coverage {values["coverage"]}'
            if missing and not self.calibrations:
                message += f' (still: {missing})'
        return message, values

    def close(self) -> None:
        """Stop waiting for target poses (a capture set waiting for one is dropped)."""
        self._stopping.set()
        with self._lock:
            self._target_arrived.notify_all()
        self._detection_pool.shutdown(wait=False)


def _too_uncertain(uncertainty: Uncertainty | None, settings: SessionSettings) -> bool:
    return uncertainty is not None and uncertainty.worst()[1] > settings.max_projection_std_px


def _uncertainty_values(uncertainty: Uncertainty | None) -> dict[str, str]:
    """The diagnostic values of an :class:`Uncertainty` ({} for None)."""
    if uncertainty is None:
        return {}
    values = {'baseline_std_m': f'{uncertainty.baseline_std_m:.3g}'}
    for name in uncertainty.worst_px:
        values[f'projection_std_worst_px {name}'] = f'{uncertainty.worst_px[name]:.3f}'
        values[f'projection_std_median_px {name}'] = f'{uncertainty.median_px[name]:.3f}'
        values[f'working_range_m {name}'] = f'{uncertainty.range_m[name]:.3f}'
    return values


def _cross_validation_values(cross_validation: CrossValidation | None) -> dict[str, str]:
    """The diagnostic values of a :class:`CrossValidation` ({} for None)."""
    if cross_validation is None:
        return {}
    values = {'cross_validation_views': '%d / %d' % cross_validation.halves}
    for name in cross_validation.worst_px:
        values[f'cross_validation_worst_px {name}'] = f'{cross_validation.worst_px[name]:.3f}'
        values[f'cross_validation_median_px {name}'] = f'{cross_validation.median_px[name]:.3f}'
    return values


def _images_digest(greys: Mapping[str, np.ndarray]) -> bytes:
    """A digest of a capture set's images (names, sizes and pixels)."""
    digest = hashlib.blake2b(digest_size=16)
    for name in sorted(greys):
        grey = np.ascontiguousarray(greys[name])
        digest.update(f'{name}:{grey.shape}:{grey.dtype}'.encode())
        digest.update(grey.data)
    return digest.digest()


def handheld_notice(target_topic: str) -> str:
    """The log line of ``chart_source: auto`` taking its first view as handheld (what auto
    chose must not be a silent switch)."""
    return (
        f'chart.source auto: no target pose on {target_topic} '
        f'for this view within {TARGET_WAIT_S} s: views are taken as handheld (chart '
        'poses estimated) until a target pose arrives'
    )


def silent_cameras_advice(
    silent: Sequence[str], names: Sequence[str], topic_of: Callable[[str], str], after_s: float
) -> str:
    """'' or what to do about the cameras ``silent`` that sent no image for ``after_s`` [s]
    while the others of ``names`` did (no capture set can complete: 0 views however long
    the chart is shown); ``topic_of`` names a camera's image topic as resolved."""
    if not silent:
        return ''
    sending = [n for n in names if n not in silent]
    advice = (
        f'a {len(sending)}-camera rig is cameras: [{", ".join(sending)}]'
        if {'left', 'right'} <= set(sending)
        else f'check that {", ".join(silent)} publishes on '
        + ', '.join(topic_of(n) for n in silent)
    )
    return (
        f'no image from {", ".join(silent)} in {after_s:g} s while '
        f'{", ".join(sending)} send images: {advice}'
    )
