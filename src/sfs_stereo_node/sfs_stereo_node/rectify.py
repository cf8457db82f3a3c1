"""Stereo rectification from calibrated CameraInfo (K, D, R, P), ROS convention.

The rectified left frame ("the depth images' frame") is the left optical frame rotated by
the left CameraInfo's R (x_rect = R x_optical), with intrinsics P_left[:3, :3]; the right
P carries Tx = P[0, 3] = -fx * baseline. Maps come from cv2.initUndistortRectifyMap, as
ROS's image_geometry / stereo_image_proc do.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from vgm_common.camera_model import DISTORTION_SIZES, OPENCV_MODELS
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

Maps = tuple[np.ndarray, np.ndarray]  # (map_x, map_y) float32 (H, W) remap tables


class RectifiedPair(NamedTuple):
    """Remap tables of both cameras and the rectified geometry."""

    maps_left: Maps | None  # (map_x, map_y): raw pixel seen at each rectified pixel;
    maps_right: Maps | None  # None: the images are rectified already (used as they are)
    size: tuple[int, int]  # (width, height) of the rectified images [px]
    K: FloatArray  # (3, 3) rectified intrinsics = P_left[:3, :3]
    P_left: FloatArray  # (3, 4)
    R_left: FloatArray  # (3, 3) left optical -> rectified frame
    focal_px: float  # focal length along the baseline [px]
    baseline_m: float  # [m] > 0
    # Principal point of the left minus the right image along the matching direction
    # [px]: a match of raw disparity d (left pixel - right pixel) is at depth
    # Z = focal b / (d - disparity_offset) (image_geometry's StereoCameraModel).
    disparity_offset: float = 0.0
    # Matching runs along image rows of the pair seen through this orientation: the
    # baseline vertical -> transposed; the right camera on the left (or above) ->
    # mirrored, so that a nearer point always has the larger disparity.
    transpose: bool = False
    mirror: bool = False


class PairGeometry(NamedTuple):
    """A rectified pair's matching geometry (:func:`pair_geometry`): the fields of the
    same names in :class:`RectifiedPair`."""

    focal_px: float
    baseline_m: float
    disparity_offset: float
    transpose: bool
    mirror: bool


def _check_rotation(R: npt.ArrayLike, name: str) -> FloatArray:
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise InvalidInput(f'{name}: expected a finite 3x3 rotation', key=name)
    if not R.any():  # an empty CameraInfo R (all zero): no rectification rotation
        return np.eye(3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InvalidInput(f'{name} is not a proper rotation (R R^T != I or det < 0)', key=name)
    return R


def _check_projection(P: npt.ArrayLike, name: str) -> FloatArray:
    P = np.asarray(P, dtype=float)
    if P.shape != (3, 4) or not np.all(np.isfinite(P)):
        raise InvalidInput(f'{name}: expected a finite 3x4 projection', key=name)
    if not (P[0, 0] > 0 and P[1, 1] > 0 and P[2, 2] == 1):
        raise InvalidInput(
            f'{name}: fx, fy must be > 0 and P[2, 2] = 1, got {P[0, 0]}, {P[1, 1]}, {P[2, 2]}',
            key=name,
        )
    return P


def pair_geometry(P_left: npt.ArrayLike, P_right: npt.ArrayLike) -> PairGeometry:
    """``PairGeometry`` of a rectified pair from its two P matrices (ROS convention,
    as cv2.stereoRectify makes them for any baseline direction): equal fx, fy and skew;
    the right P translates along x only (Tx = -fx b: horizontal pair, right camera on
    the right for Tx < 0) or along y only (Ty = -fy b: vertical pair); the principal
    points may differ along the baseline by the disparity offset, not across it.
    Raises InvalidInput naming what does not fit."""
    P_left, P_right = _check_projection(P_left, 'P_left'), _check_projection(P_right, 'P_right')
    if P_left[:, 3].any():
        raise InvalidInput(
            f'P_left must have no translation, got {P_left[:, 3].tolist()}', key='P_left'
        )
    Tx, Ty, Tz = P_right[:, 3]
    if Tz != 0 or (Tx != 0) == (Ty != 0):
        raise InvalidInput(
            f'P_right translation {P_right[:, 3].tolist()}: expected Tx '
            'only (horizontal pair) or Ty only (vertical pair)',
            key='P_right',
        )
    transpose = Tx == 0
    along, across = (1, 0) if transpose else (0, 1)  # principal point rows of P
    same = [(0, 0), (1, 1), (0, 1), (across, 2)]
    if not all(np.isclose(P_left[i, j], P_right[i, j], rtol=1e-6, atol=1e-6) for i, j in same):
        raise InvalidInput(
            'P_left and P_right differ in fx, fy, skew or the principal '
            f'point across the baseline (c{"xy"[across]}): not a rectified '
            'pair',
            key='P_right',
        )
    focal = float(P_right[along, along])
    shift = float(P_right[along, 3])
    mirror = shift > 0
    baseline = abs(shift) / focal
    offset = float(P_left[along, 2] - P_right[along, 2]) * (-1.0 if mirror else 1.0)
    return PairGeometry(focal, baseline, offset, bool(transpose), bool(mirror))


def rectified_geometry(P_left: npt.ArrayLike, P_right: npt.ArrayLike) -> tuple[float, float]:
    """(focal_px, baseline_m) of a rectified pair (``pair_geometry``)."""
    geometry = pair_geometry(P_left, P_right)
    return geometry.focal_px, geometry.baseline_m


def is_rectified_already(
    K: npt.ArrayLike, D: npt.ArrayLike, R: npt.ArrayLike, P: npt.ArrayLike
) -> bool:
    """True when a camera's images need no resampling: D zero, R identity (or empty)
    and K equal to the rectified intrinsics P[:3, :3] (a rectified driver, a dataset
    pair)."""
    R = np.asarray(R, dtype=float)
    return (
        not np.asarray(D, dtype=float).any()
        and (not R.any() or np.allclose(R, np.eye(3), atol=1e-9))
        and np.allclose(
            np.asarray(K, dtype=float), np.asarray(P, dtype=float)[:3, :3], rtol=1e-9, atol=1e-9
        )
    )


def rectification_maps(
    K_left: npt.ArrayLike,
    D_left: npt.ArrayLike,
    R_left: npt.ArrayLike,
    P_left: npt.ArrayLike,
    K_right: npt.ArrayLike,
    D_right: npt.ArrayLike,
    R_right: npt.ArrayLike,
    P_right: npt.ArrayLike,
    size: tuple[int, int],
    models: tuple[str, str] = ('plumb_bob', 'plumb_bob'),
) -> RectifiedPair:
    """Remap tables of a calibrated pair for images of ``size`` (width, height).

    ``models``: the left and right CameraInfo distortion models; plumb_bob and
    rational_polynomial go to cv2.initUndistortRectifyMap, equidistant to
    cv2.fisheye.initUndistortRectifyMap, another is refused naming it.

    Validates every matrix (finite, R proper rotations, P a rectified pair) and raises
    InvalidInput otherwise, so an unrectifiable calibration never produces images. A
    pair whose cameras are both ``is_rectified_already`` gets no tables (maps None):
    its images are used as they are.
    """
    width, height = (int(v) for v in size)
    if width < 8 or height < 8:
        raise InvalidInput(f'image size {size} too small', key='size', value=size)
    R_left, R_right = _check_rotation(R_left, 'R_left'), _check_rotation(R_right, 'R_right')
    geometry = pair_geometry(P_left, P_right)
    cameras: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]] = []  # K, D, R, P
    for K, D, R, P, name in (
        (K_left, D_left, R_left, P_left, 'left'),
        (K_right, D_right, R_right, P_right, 'right'),
    ):
        K, D = np.asarray(K, dtype=float), np.asarray(D, dtype=float).ravel()
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InvalidInput(
                f'K_{name}: expected finite intrinsics with fx, fy > 0', key=f'K_{name}'
            )
        if not np.all(np.isfinite(D)):
            raise InvalidInput(f'D_{name} has non-finite values', key=f'D_{name}')
        model = models[len(cameras)]
        if model not in OPENCV_MODELS or len(D) > DISTORTION_SIZES[model]:
            raise InvalidInput(
                f'{name} camera: cannot rectify distortion model {model!r} with '
                f'{len(D)} coefficients (one of {", ".join(OPENCV_MODELS)} and its D)',
                key='distortion_model',
            )
        cameras.append((K, D, R, np.asarray(P, dtype=float)))
    # An equidistant camera with D = 0 still bends its rays (r = theta, not tan theta).
    if 'equidistant' not in models and all(is_rectified_already(*camera) for camera in cameras):
        maps: list[Maps | None] = [None, None]
    else:
        maps = [
            (
                cv2.fisheye.initUndistortRectifyMap(
                    K, D, R, P[:3, :3], (width, height), cv2.CV_32FC1
                )
                if model == 'equidistant'
                else cv2.initUndistortRectifyMap(K, D, R, P, (width, height), cv2.CV_32FC1)
            )
            for (K, D, R, P), model in zip(cameras, models)
        ]
    P_left = np.asarray(P_left, dtype=float)
    return RectifiedPair(
        maps[0], maps[1], (width, height), P_left[:3, :3].copy(), P_left.copy(), R_left, *geometry
    )


def rectify(
    image: npt.ArrayLike, maps: Maps | None, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """Rectified copy of ``image`` (H, W) by ``maps`` (map_x, map_y); pixels that map
    outside the raw image are 0 (cv2.BORDER_CONSTANT). ``maps`` None: ``image`` itself."""
    if maps is None:
        return np.asarray(image)
    return cv2.remap(
        np.asarray(image),
        maps[0],
        maps[1],
        interpolation,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def rectified_valid_mask(maps: Maps | None, raw_size: tuple[int, int]) -> npt.NDArray[np.bool_]:
    """(H, W) bool: rectified pixels whose raw source lies inside the raw image."""
    width, height = raw_size
    if maps is None:
        return np.ones((height, width), dtype=bool)
    x, y = maps
    return (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)


def raw_depth_to_rectified(depth_raw: npt.ArrayLike, pair: RectifiedPair) -> np.ndarray:
    """Depth [m] along the rectified left optical axis at every rectified pixel, from a
    depth map along the RAW left optical axis (e.g. sensor_sim's depth_left.npy).

    A rectified pixel (u, v) looks along r = K^-1 (u, v, 1) in the rectified frame, i.e.
    along R^T r in the raw optical frame, and sees the raw pixel ``maps_left`` gives; with
    the raw depth z there the point is z / (R^T r)_z * R^T r, whose rectified Z is
    z / (R^T r)_z. Raw depth is sampled by nearest neighbour (NaN stays NaN).
    """
    width, height = pair.size
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    rays = np.linalg.solve(pair.K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
    raw_z = (pair.R_left.T @ rays)[2].reshape(height, width)
    sampled: np.ndarray  # float32 [m] along the raw optical axis
    if pair.maps_left is None:
        sampled = np.asarray(depth_raw, dtype=np.float32)[:height, :width]
    else:
        sampled = cv2.remap(
            np.asarray(depth_raw, dtype=np.float32),
            pair.maps_left[0],
            pair.maps_left[1],
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float('nan'),
        )
    return sampled / raw_z


def light_in_rectified_frame(
    light_optical: Sequence[float] | np.ndarray, R_left: npt.ArrayLike
) -> FloatArray:
    """Unit light direction (surface -> light) rotated from the left optical frame into
    the rectified frame (x right, y down, z forward)."""
    light = np.asarray(light_optical, dtype=float).ravel()
    norm = np.linalg.norm(light)
    if light.shape != (3,) or not np.isfinite(norm) or norm == 0:
        raise InvalidInput(
            f'light_direction must be a finite non-zero 3-vector, got {light_optical}',
            key='light_direction',
        )
    return np.asarray(R_left, dtype=float) @ (light / norm)


def scaled_pair(pair: RectifiedPair, factor: int) -> RectifiedPair:
    """``pair`` downsampled by an integer ``factor``: maps sampled at every rectified
    pixel of the coarse grid (pixel centres, the cv2.resize INTER_AREA convention), K and
    P scaled; the baseline is unchanged."""
    if factor == 1:
        return pair
    width, height = pair.size
    w, h = width // factor, height // factor
    centres = (np.arange(max(w, h)) + 0.5) * factor - 0.5
    cols, rows = centres[:w], centres[:h]

    def sample(map_xy: Maps | None) -> Maps | None:
        if map_xy is None:
            return None
        map_x, map_y = (
            cv2.remap(
                m,
                np.tile(cols.astype(np.float32), (h, 1)),
                np.tile(rows.astype(np.float32)[:, None], (1, w)),
                cv2.INTER_LINEAR,
            )
            for m in map_xy
        )
        return map_x, map_y

    S = np.diag([1.0 / factor, 1.0 / factor, 1.0])
    shift = np.array([[1, 0, 0.5 / factor - 0.5], [0, 1, 0.5 / factor - 0.5], [0, 0, 1]])
    P = shift @ S @ pair.P_left
    return pair._replace(
        maps_left=sample(pair.maps_left),
        maps_right=sample(pair.maps_right),
        size=(w, h),
        K=P[:3, :3].copy(),
        P_left=P,
        focal_px=pair.focal_px / factor,
        disparity_offset=pair.disparity_offset / factor,
    )
