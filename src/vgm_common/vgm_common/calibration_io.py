"""Calibration files. No rclpy.

Two formats:

- ``<name>.yaml`` per camera (``left.yaml``, ``right.yaml``, ``aux.yaml``): the
  camera_calibration_parsers format that ROS camera drivers load (image size, camera
  name, K, distortion model and D, R, P). It carries no pose.
- ``calibration.yaml``: the whole rig in one file, what calib_node's
  ``calibration_file`` loads. ``cameras: {left: {...}, right: ..., aux: ...}`` where each
  entry is the camera_calibration_parsers mapping plus ``frame_id`` and
  ``pose_in_base_link: {position: [x, y, z], orientation: [x, y, z, w]}`` (the optical
  frame in base_link), and optional ``quality`` (e.g. reprojection RMS per camera).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import yaml

from vgm_common.camera_model import (
    COEFFICIENT_NAMES,
    DISTORTION_SIZES,
    OPENCV_MODELS,
    PinholeCamera,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import (
    FloatArray,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
)

RIG_FILE = 'calibration.yaml'
CAMERA_NAMES_IN_FILES = {'left': 'stereo_left', 'right': 'stereo_right', 'aux': 'aux'}
CameraEntry = tuple[PinholeCamera, FloatArray, FloatArray]  # (camera, R 3x3, P 3x4) as read
Rectification = tuple[npt.ArrayLike, npt.ArrayLike]  # (R 3x3, P 3x4) to write


def _matrix(rows: int, cols: int, values: npt.ArrayLike) -> dict[str, int | list[float]]:
    return {'rows': rows, 'cols': cols, 'data': [float(v) for v in np.ravel(values)]}


def camera_yaml_dict(
    camera: PinholeCamera,
    camera_name: str,
    R: npt.ArrayLike | None = None,
    P: npt.ArrayLike | None = None,
) -> dict[str, object]:
    """The camera_calibration_parsers mapping of a PinholeCamera of a CameraInfo model
    (``OPENCV_MODELS``: plumb_bob, rational_polynomial, equidistant)."""
    if camera.distortion_model not in OPENCV_MODELS:
        raise InvalidInput(
            f'{camera_name}: only {", ".join(OPENCV_MODELS)} cameras can be written, got '
            f'{camera.distortion_model!r}',
            key='distortion_model',
        )
    R = np.eye(3) if R is None else np.asarray(R, dtype=float)
    P = np.hstack([camera.K, np.zeros((3, 1))]) if P is None else np.asarray(P, dtype=float)
    return {
        'image_width': int(camera.width),
        'image_height': int(camera.height),
        'camera_name': camera_name,
        'camera_matrix': _matrix(3, 3, camera.K),
        'distortion_model': camera.distortion_model,
        'distortion_coefficients': _matrix(1, len(camera.D), camera.D),
        'rectification_matrix': _matrix(3, 3, R),
        'projection_matrix': _matrix(3, 4, P),
    }


def _read_matrix(entry: Mapping[str, Any], key: str, shape: tuple[int, ...] | None) -> FloatArray:
    try:
        value = entry[key]
        data = np.array(value['data'], dtype=float)
        if shape is not None:
            data = data.reshape(shape)
    except (KeyError, TypeError, ValueError) as error:
        raise InvalidInput(
            f'{key}: expected {{rows, cols, data}} of shape {shape} ({error})', key=key
        ) from None
    if not np.all(np.isfinite(data)):
        raise InvalidInput(f'{key}: non-finite values', key=key)
    return data


def camera_from_yaml_dict(entry: object, T_base_camera: FloatArray | None = None) -> CameraEntry:
    """camera_calibration_parsers mapping -> (PinholeCamera, R (3x3), P (3x4))."""
    if not isinstance(entry, dict):
        raise InvalidInput('camera entry must be a mapping', key='camera')
    model = entry.get('distortion_model', 'plumb_bob')
    if model not in OPENCV_MODELS:
        raise InvalidInput(
            f'unsupported distortion model {model!r} (expected one of {", ".join(OPENCV_MODELS)})',
            key='distortion_model',
        )
    K = _read_matrix(entry, 'camera_matrix', (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1:
        raise InvalidInput(
            f'camera_matrix is not an intrinsic matrix: {K.tolist()}', key='camera_matrix'
        )
    try:
        width, height = int(entry['image_width']), int(entry['image_height'])
    except (KeyError, TypeError, ValueError):
        raise InvalidInput(
            'image_width and image_height are required integers', key='image_width'
        ) from None
    if width <= 0 or height <= 0:
        raise InvalidInput('image size must be positive', key='image_width')
    D = _read_matrix(entry, 'distortion_coefficients', None)
    size = DISTORTION_SIZES[model]
    if len(D) != size if model != 'plumb_bob' else len(D) > size:
        raise InvalidInput(
            f'distortion_coefficients: {model} takes {size} ({COEFFICIENT_NAMES[model]}), '
            f'got {len(D)}',
            key='distortion_coefficients',
        )
    R = _read_matrix(entry, 'rectification_matrix', (3, 3))
    P = _read_matrix(entry, 'projection_matrix', (3, 4))
    T = np.eye(4) if T_base_camera is None else T_base_camera
    return PinholeCamera(width, height, K, D, T, model), R, P


def write_camera_yaml(
    path: str | Path,
    camera: PinholeCamera,
    camera_name: str,
    R: npt.ArrayLike | None = None,
    P: npt.ArrayLike | None = None,
) -> None:
    """Write the camera_calibration_parsers file of a ``camera`` (no pose) to ``path``;
    default R = I, P = [K | 0]. Raises InvalidInput for a model CameraInfo has not
    (division)."""
    Path(path).write_text(
        yaml.safe_dump(camera_yaml_dict(camera, camera_name, R, P), sort_keys=False)
    )


def read_camera_yaml(path: str | Path) -> CameraEntry:
    """camera_calibration_parsers file -> (PinholeCamera (pose = identity), R, P)."""
    return camera_from_yaml_dict(yaml.safe_load(Path(path).read_text()))


def write_calibration(
    directory: str | Path,
    cameras: Mapping[str, PinholeCamera],
    frame_ids: Mapping[str, str],
    rectification: Mapping[str, Rectification] | None = None,
    quality: Mapping[str, Mapping[str, float]] | None = None,
) -> Path:
    """Write ``calibration.yaml`` and one camera_calibration_parsers file per camera.

    Args:
        directory: created if missing.
        cameras: {name: PinholeCamera (a CameraInfo model) with its pose in base_link}.
        frame_ids: {name: optical frame id}.
        rectification: {name: (R, P)}; default R = I, P = [K | 0].
        quality: {name: {key: number}} stored beside each camera (e.g. rms_px).

    Returns:
        Path of ``calibration.yaml``.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    rectification = rectification or {}
    rig: dict[str, dict[str, object]] = {}
    for name, camera in cameras.items():
        R, P = rectification.get(name, (None, None))
        camera_name = CAMERA_NAMES_IN_FILES.get(name, name)
        write_camera_yaml(directory / f'{name}.yaml', camera, camera_name, R, P)
        entry = camera_yaml_dict(camera, camera_name, R, P)
        T = camera.T_base_camera
        entry['frame_id'] = frame_ids[name]
        entry['pose_in_base_link'] = {
            'position': [float(v) for v in T[:3, 3]],
            'orientation': [float(v) for v in matrix_to_quaternion(T[:3, :3])],
        }
        if quality and name in quality:
            entry['quality'] = {k: float(v) for k, v in quality[name].items()}
        rig[name] = entry
    path = directory / RIG_FILE
    path.write_text(yaml.safe_dump({'cameras': rig}, sort_keys=False))
    return path


def read_calibration(path: str | Path) -> dict[str, CameraEntry]:
    """``calibration.yaml`` (or the directory holding it) -> {name: (PinholeCamera with
    pose, R, P)}. Raises InvalidInput naming what is wrong."""
    path = Path(path)
    if path.is_dir():
        path = path / RIG_FILE
    try:
        document = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as error:
        raise InvalidInput(
            f'cannot read calibration file {path}: {error}', key='calibration_file'
        ) from None
    if not isinstance(document, dict) or not isinstance(document.get('cameras'), dict):
        raise InvalidInput(
            f'{path}: expected a top-level "cameras" mapping', key='calibration_file'
        )
    rig: dict[str, CameraEntry] = {}
    for name, entry in document['cameras'].items():
        try:
            pose = entry['pose_in_base_link']
            position = np.array(pose['position'], dtype=float).reshape(3)
            quaternion = np.array(pose['orientation'], dtype=float).reshape(4)
        except (KeyError, TypeError, ValueError):
            raise InvalidInput(
                f'{path}: cameras.{name}.pose_in_base_link needs position [3] '
                'and orientation [x, y, z, w]',
                key=f'cameras.{name}',
            ) from None
        if not (
            np.all(np.isfinite(position))
            and np.all(np.isfinite(quaternion))
            and abs(np.linalg.norm(quaternion) - 1) < 1e-6
        ):
            raise InvalidInput(
                f'{path}: cameras.{name}.pose_in_base_link is not a finite '
                'pose with a unit quaternion',
                key=f'cameras.{name}',
            )
        T = make_transform(quaternion_to_matrix(quaternion), position)
        try:
            rig[name] = camera_from_yaml_dict(entry, T)
        except InvalidInput as error:
            raise InvalidInput(f'{path}: cameras.{name}: {error}', key=f'cameras.{name}') from None
    return rig


def stereo_rectification(
    left: PinholeCamera, right: PinholeCamera, alpha: float = 0.0
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The rectified stereo pair of two PinholeCameras with poses (ROS convention, as
    cv2.stereoRectify computes it): {'left': (R1, P1), 'right': (R2, P2)} where R rotates
    the camera's optical frame into the rectified frame and the right P carries
    Tx = -fx * baseline [m] in P[0, 3]. ``alpha`` 0 crops to valid pixels only.

    plumb_bob and rational_polynomial cameras (in any mix) go to cv2.stereoRectify; a
    pair of equidistant cameras is rectified to the pinhole window of its central focal
    length (cv2.stereoRectify of the pair without distortion; its images remapped by
    cv2.fisheye.initUndistortRectifyMap). Raises InvalidInput for an equidistant camera
    paired with another model and for a model CameraInfo has not, naming them."""
    models = (left.distortion_model, right.distortion_model)
    T_right_left = right.T_camera_base @ left.T_base_camera
    size = (int(left.width), int(left.height))
    if any(m not in OPENCV_MODELS for m in models) or (
        'equidistant' in models and models != ('equidistant', 'equidistant')
    ):
        raise InvalidInput(
            f'stereo rectification of a {models[0]} left and a {models[1]} right camera: '
            'supported are plumb_bob and rational_polynomial in any mix, or two equidistant',
            key='distortion_model',
        )
    # A fisheye pair: the rotations do not depend on the lenses; the rectified cameras are
    # the pinhole window of the pair's central focal length (cv2.stereoRectify without
    # distortion). cv2.fisheye.stereoRectify's own window comes from the image border, which
    # a fisheye may see past 90 deg: focal lengths of 50 px for 300 px lenses, the principal
    # point outside the image.
    fisheye = models == ('equidistant', 'equidistant')
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        left.K,
        np.zeros(5) if fisheye else left.D,
        right.K,
        np.zeros(5) if fisheye else right.D,
        size,
        T_right_left[:3, :3],
        T_right_left[:3, 3].reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=alpha,
    )
    return {'left': (R1, P1), 'right': (R2, P2)}
