"""A handheld calibration chart: poses a hand would show the cameras, around the stage
poses, spread over the image so that a handheld calibration's coverage rule (the board's
position, size and tilt in the image, as camera_calibration's) is met. No rclpy."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import ScenarioError
from vgm_common.geometry import FloatArray

LATERAL_M = 0.15  # [m] how far the hand moves the board's centre sideways
NEARER_M = (-0.25, 0.3)  # [m] and away from / towards the cameras (base z)
TILT_SIGMA_RAD = 0.35  # [rad] spread of its tilt about the stage orientation
MARGIN_PX = 12.0  # every corner this far inside every image
MIN_FACING = 0.35  # |cos| of the angle between the board's normal and each line of sight
CANDIDATES = 400
MAX_DRAWS = 50_000


def handheld_chart_poses(
    T_base_stage: Sequence[FloatArray],
    corners_chart: FloatArray,
    cameras: Mapping[str, PinholeCamera],
    count: int,
    seed: int,
    reference: str = 'left',
) -> tuple[FloatArray, ...]:
    """``count`` chart poses T_base_chart (4x4) a hand could show: drawn (seeded) around
    the mean stage pose, each seeing every corner (``corners_chart`` (N, 3) in the chart
    frame) inside every camera's image and facing it, then chosen one by one as far as
    possible (farthest point) from the chosen ones in the ``reference`` camera's terms:
    the board's centre (x, y), its apparent size and its tilt. Raises ScenarioError if
    the stage poses leave no room for such poses."""
    rng = np.random.default_rng(seed)
    stage = np.stack(T_base_stage)
    centre_stage = stage[:, :3, 3].mean(axis=0) + stage[0, :3, :3] @ corners_chart.mean(axis=0)
    candidates = []
    for _ in range(MAX_DRAWS):
        T = np.eye(4)
        T[:3, :3] = (
            Rotation.from_rotvec(rng.normal(size=3) * TILT_SIGMA_RAD).as_matrix()
            @ (stage[0, :3, :3])
        )
        offset = rng.uniform(
            [-LATERAL_M, -LATERAL_M, NEARER_M[0]], [LATERAL_M, LATERAL_M, NEARER_M[1]]
        )
        T[:3, 3] = centre_stage + offset - T[:3, :3] @ corners_chart.mean(axis=0)
        if _seen_by_all(T, corners_chart, cameras):
            candidates.append(T)
            if len(candidates) == CANDIDATES:
                break
    if len(candidates) < count:
        raise ScenarioError(
            f'calibration.motion handheld: only {len(candidates)} chart poses around the '
            f'stage poses are seen whole by every camera ({count} needed)',
            key='calibration.motion',
        )
    features = np.array([_features(T, corners_chart, cameras[reference]) for T in candidates])
    chosen = [int(np.argmin(features[:, 2]))]  # the farthest (smallest) board first
    distance = np.linalg.norm(features - features[chosen[0]], axis=1)
    while len(chosen) < count:
        nearest_new = int(np.argmax(distance))
        chosen.append(nearest_new)
        distance = np.minimum(distance, np.linalg.norm(features - features[nearest_new], axis=1))
    return tuple(candidates[i] for i in chosen)


def _seen_by_all(
    T_base_chart: FloatArray, corners_chart: FloatArray, cameras: Mapping[str, PinholeCamera]
) -> bool:
    points = corners_chart @ T_base_chart[:3, :3].T + T_base_chart[:3, 3]
    for camera in cameras.values():
        pixels, depth = camera.project(points)
        size = np.array([camera.width, camera.height])
        if np.any(depth <= 0) or np.any(pixels < MARGIN_PX) or np.any(pixels > size - MARGIN_PX):
            return False
        sight = points.mean(axis=0) - camera.T_base_camera[:3, 3]
        if abs(T_base_chart[:3, 2] @ sight) < MIN_FACING * np.linalg.norm(sight):
            return False
    return True


def _features(
    T_base_chart: FloatArray, corners_chart: FloatArray, camera: PinholeCamera
) -> FloatArray:
    """(4,): the board's centre in the image (fractions of width, height), its apparent
    size (square root of its area over the image's, tripled: the scarcest to cover)
    and its tilt from the camera's axis (over TILT_SIGMA_RAD * 2)."""
    points = corners_chart @ T_base_chart[:3, :3].T + T_base_chart[:3, 3]
    pixels, _ = camera.project(points)
    area = _outline_area(pixels, corners_chart)
    tilt = np.arccos(min(1.0, abs(T_base_chart[:3, 2] @ camera.T_base_camera[:3, 2])))
    return np.array(
        [
            pixels[:, 0].mean() / camera.width,
            pixels[:, 1].mean() / camera.height,
            3.0 * np.sqrt(area / (camera.width * camera.height)),
            tilt / (2.0 * TILT_SIGMA_RAD),
        ]
    )


def _outline_area(pixels: FloatArray, corners_chart: FloatArray) -> float:
    """Area [px²] of the quadrilateral of the board's four extreme corners."""
    extremes = [
        int(np.argmin(corners_chart[:, 0] + corners_chart[:, 1])),
        int(np.argmax(corners_chart[:, 0] - corners_chart[:, 1])),
        int(np.argmax(corners_chart[:, 0] + corners_chart[:, 1])),
        int(np.argmin(corners_chart[:, 0] - corners_chart[:, 1])),
    ]
    x, y = pixels[extremes, 0], pixels[extremes, 1]
    return float(0.5 * abs(x @ np.roll(y, 1) - y @ np.roll(x, 1)))
