"""sensor_sim's cameras without ROS: the settings that are the one source of its camera
parameters, the capture schedule (the chart at every stage pose first, then the scene),
the noisy images of one capture, and the ground-truth files for tests and benchmarks."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import yaml

from sensor_sim.curves import curve_polylines
from sensor_sim.render import SceneRenderer, add_noise
from sensor_sim.scenario import CAMERA_NAMES, CHART_MOTIONS, Calibration, Scenario
from vgm_common.calibration_io import write_calibration
from vgm_common.camera_model import OPENCV_MODELS
from vgm_common.geometry import FloatArray
from vgm_common.settings import setting
from vgm_common.topics import OPTICAL_FRAMES


@dataclass(frozen=True)
class SimSettings:
    """What sensor_sim simulates and how fast: the one source of these parameters."""

    scenario: str = setting(
        'default', 'Scenario file, or the name of a shipped one.', read_only=True
    )
    calibration_phase: bool = setting(
        True,
        'Show the chart at every stage pose (captures_per_pose captures each) before the scene.',
        read_only=True,
    )
    chart_motion: str = setting(
        '',
        'How the chart is shown in the calibration phase: stage (at the stage poses, with '
        "/calibration/target_pose) or handheld (a hand's poses around them, spread over the "
        "images, no target pose: calib_node's handheld calibration with its defaults); empty "
        "takes the scenario's calibration.motion.",
        choices=('', *CHART_MOTIONS),
        read_only=True,
    )
    rate: float = setting(
        0.0,
        "Camera frame rate (0: the scenario's rate).",
        unit='Hz',
        range=(0.0, 200.0),
        read_only=True,
    )
    joint_state_rate: float = setting(
        200.0,
        'Arm simulation (its own thread), /joint_states and /tool/pressure rate.',
        unit='Hz',
        range=(100.0, 1000.0),
        read_only=True,
    )
    ground_truth_dir: str = setting(
        '',
        'If set, the true cameras (cameras.yaml, and as a calibration file '
        'true_calibration/calibration.yaml unless a camera is division), curve '
        '(curve_base.npz, one array per polyline), depth maps (depth_<camera>.npy, metres, '
        'NaN off the surface) and chart poses (T_base_chart.npy) are written there for '
        'tests and benchmarks; no pipeline node reads them. Empty: not written.',
        read_only=True,
    )


class Capture(NamedTuple):
    """One capture of the schedule: its frame index (the noise seed's), the chart pose it
    shows (None: the scene) and the chart's pose to publish as the target pose (a stage's
    is measured; None for a hand's, and for the scene)."""

    frame_index: int
    pose_index: int | None
    T_base_target: FloatArray | None  # (4, 4)
    ends_calibration: bool  # the last chart capture


class CaptureSchedule:
    """Which capture comes next: with ``calibration_phase`` (and a scenario calibration)
    ``captures_per_pose`` captures of the chart at each of its poses, then the scene for
    good. Thread-safe: ``next()`` may be called from any thread."""

    def __init__(self, calibration: Calibration | None, calibration_phase: bool) -> None:
        self._calibration = calibration if calibration_phase else None
        self.chart_frames = (
            0
            if self._calibration is None
            else len(self._calibration.T_base_chart) * self._calibration.captures_per_pose
        )
        self._lock = threading.Lock()
        self.frame_index = 0  # the next capture's

    @property
    def phase(self) -> str:
        """'calibration' while chart captures remain, then 'scene'."""
        return 'calibration' if self.frame_index < self.chart_frames else 'scene'

    def next(self) -> Capture:
        """The next capture (and count it)."""
        with self._lock:
            k = self.frame_index
            self.frame_index += 1
        if k >= self.chart_frames or self._calibration is None:
            return Capture(k, None, None, False)
        pose_index = k // self._calibration.captures_per_pose
        measured = self._calibration.motion == 'stage'
        T_base_target = self._calibration.T_base_chart[pose_index] if measured else None
        return Capture(k, pose_index, T_base_target, k + 1 == self.chart_frames)


def capture_images(
    renderer: SceneRenderer, scenario: Scenario, capture: Capture
) -> dict[str, npt.NDArray[np.uint8]]:
    """Camera name -> the mono8 (height, width) image of ``capture``: the clean image
    (the chart at its pose, or the scene) with the scenario's pixel noise. Same scenario,
    seed and frame index: the same images, bit for bit."""
    images = {}
    for camera_index, name in enumerate(CAMERA_NAMES):
        clean = (
            renderer.scene_image(name)
            if capture.pose_index is None
            else renderer.chart_image(name, capture.pose_index)
        )
        rng = np.random.default_rng([scenario.seed, capture.frame_index, camera_index])
        images[name] = add_noise(clean, scenario.noise.image_sigma, rng)
    return images


def render_everything(
    renderer: SceneRenderer, scenario: Scenario, schedule: CaptureSchedule
) -> None:
    """Render every clean image the schedule will show now, so captures keep their rate
    from the first."""
    calibration = scenario.calibration
    for name in CAMERA_NAMES:
        renderer.scene_image(name)
        if schedule.chart_frames and calibration is not None:
            for pose_index in range(len(calibration.T_base_chart)):
                renderer.chart_image(name, pose_index)


def write_ground_truth(directory: Path, scenario: Scenario, renderer: SceneRenderer) -> None:
    """Write the true cameras, curve, depth maps and chart poses to ``directory`` (files
    only: no pipeline node reads them; see ``SimSettings.ground_truth_dir``)."""
    directory.mkdir(parents=True, exist_ok=True)
    cameras = {
        name: {
            'width': cam.width,
            'height': cam.height,
            'K': cam.K.tolist(),
            'distortion_model': cam.distortion_model,
            'D': cam.D.tolist(),
            'T_base_camera': cam.T_base_camera.tolist(),
        }
        for name, cam in scenario.cameras.items()
    }
    (directory / 'cameras.yaml').write_text(yaml.safe_dump(cameras))
    if all(c.distortion_model in OPENCV_MODELS for c in scenario.cameras.values()):
        # The true rig as a calibration file: calib_node's `calibration_file` loads it.
        write_calibration(directory / 'true_calibration', scenario.cameras, OPTICAL_FRAMES)
    pieces = curve_polylines(scenario.curve, scenario.surface)
    np.savez(directory / 'curve_base.npz', *pieces)
    for name in CAMERA_NAMES:
        np.save(directory / f'depth_{name}.npy', renderer.depth(name))
    if scenario.calibration is not None:
        np.save(directory / 'T_base_chart.npy', np.stack(scenario.calibration.T_base_chart))
