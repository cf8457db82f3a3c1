"""Message <-> numpy conversion, written once for every node (no cv_bridge here).

Every ``*_to_numpy`` / ``*_from_msg`` function validates its message and raises
``InvalidInput`` naming the problem; every ``*_to_msg`` function copies the caller's
data (messages never alias numpy arrays the caller may change).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

import numpy as np
import numpy.typing as npt
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import Header
from stereo_msgs.msg import DisparityImage

from vgm_common.camera_model import (
    COEFFICIENT_NAMES,
    DISTORTION_SIZES,
    OPENCV_MODELS,
    PinholeCamera,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import (
    FloatArray,
    is_rotation,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
)

# encoding -> (numpy dtype, channels), REP 118 and sensor_msgs/image_encodings.
IMAGE_ENCODINGS: dict[str, tuple[type[np.generic], int]] = {
    'mono8': (np.uint8, 1),
    'mono16': (np.uint16, 1),
    'rgb8': (np.uint8, 3),
    'bgr8': (np.uint8, 3),
    'rgba8': (np.uint8, 4),
    'bgra8': (np.uint8, 4),
    '8UC1': (np.uint8, 1),
    '8UC3': (np.uint8, 3),
    '16UC1': (np.uint16, 1),
    '32FC1': (np.float32, 1),
    '64FC1': (np.float64, 1),
}


def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> integer time [ns]."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def ns_to_stamp(ns: int) -> Time:
    """Integer time [ns] -> builtin_interfaces/Time."""
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def make_header(stamp_ns: int, frame_id: str) -> Header:
    """std_msgs/Header stamped ``stamp_ns`` [ns] in frame ``frame_id``."""
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


# --- sensor_msgs/Image -------------------------------------------------------------


def check_image(msg: Image) -> tuple[np.dtype, int, int]:
    """Raise InvalidInput unless ``msg`` is a well-formed Image (known encoding, non-empty,
    step and data length consistent); returns (dtype, channels, row bytes). Cheap: the
    pixels are not touched, so a node can check every image as it arrives."""
    if msg.encoding not in IMAGE_ENCODINGS:
        raise InvalidInput(
            f'unsupported image encoding {msg.encoding!r}', key='encoding', value=msg.encoding
        )
    scalar_type, channels = IMAGE_ENCODINGS[msg.encoding]
    dtype = np.dtype(scalar_type).newbyteorder('>' if msg.is_bigendian else '<')
    row_bytes = msg.width * channels * dtype.itemsize
    if msg.width == 0 or msg.height == 0:
        raise InvalidInput('empty image (width or height is 0)', key='size')
    if msg.step < row_bytes:
        raise InvalidInput(
            f'image step {msg.step} is smaller than width * pixel size {row_bytes}',
            key='step',
            value=msg.step,
        )
    if len(msg.data) != msg.step * msg.height:
        raise InvalidInput(
            f'image data has {len(msg.data)} bytes, expected step * height '
            f'= {msg.step * msg.height}',
            key='data',
            value=len(msg.data),
        )
    return dtype, channels, row_bytes


def image_to_numpy(msg: Image) -> np.ndarray:
    """Image -> array of shape (H, W) or (H, W, C), a copy, in the message's dtype."""
    dtype, channels, row_bytes = check_image(msg)
    rows = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(msg.height, msg.step)
    pixels = rows[:, :row_bytes].copy().view(dtype).astype(dtype.newbyteorder('='))
    return (
        pixels.reshape(msg.height, msg.width, channels)
        if channels > 1
        else pixels.reshape(msg.height, msg.width)
    )


_GREY_WEIGHTS = {
    'rgb8': (0.299, 0.587, 0.114),
    'rgba8': (0.299, 0.587, 0.114),
    'bgr8': (0.114, 0.587, 0.299),
    'bgra8': (0.114, 0.587, 0.299),
}


GREY_ENCODINGS = ('mono8', 'mono16', '8UC1', '16UC1', *_GREY_WEIGHTS)


def check_grey_image(msg: Image) -> None:
    """``check_image``, and an encoding ``image_to_grey`` converts; raises InvalidInput."""
    check_image(msg)
    if msg.encoding not in GREY_ENCODINGS:
        raise InvalidInput(
            f'image encoding {msg.encoding!r} is not grey or 8-bit colour '
            f'({", ".join(GREY_ENCODINGS)})',
            key='encoding',
            value=msg.encoding,
        )


def image_to_grey(msg: Image) -> npt.NDArray[np.float32]:
    """Image (mono8/16, 8UC1/16UC1, rgb8, bgr8, rgba8, bgra8) -> (H, W) float32 grey
    levels on the 0..255 scale (16-bit images scaled down, colour by ITU-R BT.601)."""
    check_grey_image(msg)
    array = image_to_numpy(msg)
    if msg.encoding in ('mono8', '8UC1'):
        return array.astype(np.float32)
    if msg.encoding in ('mono16', '16UC1'):
        return array.astype(np.float32) * np.float32(255.0 / 65535.0)
    return array[:, :, :3].astype(np.float32) @ np.array(
        _GREY_WEIGHTS[msg.encoding], dtype=np.float32
    )


def numpy_to_image(array: npt.ArrayLike, encoding: str, stamp_ns: int, frame_id: str) -> Image:
    """(H, W) or (H, W, C) array -> Image (little-endian, no row padding)."""
    if encoding not in IMAGE_ENCODINGS:
        raise InvalidInput(f'unsupported image encoding {encoding!r}', key='encoding')
    dtype, channels = IMAGE_ENCODINGS[encoding]
    array = np.ascontiguousarray(array, dtype=dtype)
    if array.ndim != (2 if channels == 1 else 3) or (channels > 1 and array.shape[2] != channels):
        raise InvalidInput(f'array of shape {array.shape} does not fit encoding {encoding}')
    msg = Image(
        header=make_header(stamp_ns, frame_id),
        height=array.shape[0],
        width=array.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=array.shape[1] * channels * array.itemsize,
    )
    msg.data = array.tobytes()
    return msg


def numpy_to_disparity_image(
    disparity: npt.ArrayLike,
    stamp_ns: int,
    frame_id: str,
    focal_px: float,
    baseline_m: float,
    disparity_range: tuple[float, float],
    delta_d: float,
    valid_window: tuple[int, int, int, int] | None = None,
) -> DisparityImage:
    """(H, W) disparity [px], NaN where unknown -> stereo_msgs/DisparityImage as
    stereo_image_proc fills it: ``f`` [px], ``t`` (the baseline [m]; the ROS 2 field is
    lower-case, and a ``T=`` keyword is silently ignored), the searched ``disparity_range``
    (min, max), the matcher's step ``delta_d``, the fully valid window (x, y, w, h; None:
    the whole image). Unknown pixels are -1 (below any ``min_disparity`` >= 0, which
    marks them; one below a negative one)."""
    array = np.asarray(disparity, dtype=np.float32)
    low, high = disparity_range
    msg = DisparityImage(
        header=make_header(stamp_ns, frame_id),
        f=float(focal_px),
        t=float(baseline_m),
        min_disparity=float(low),
        max_disparity=float(high),
        delta_d=float(delta_d),
    )
    msg.image = numpy_to_image(
        np.where(np.isfinite(array), array, np.float32(min(-1.0, low - 1.0))),
        '32FC1',
        stamp_ns,
        frame_id,
    )
    x, y, width, height = valid_window or (0, 0, array.shape[1], array.shape[0])
    msg.valid_window.x_offset, msg.valid_window.y_offset = int(x), int(y)
    msg.valid_window.width, msg.valid_window.height = int(width), int(height)
    return msg


# --- sensor_msgs/CameraInfo ----------------------------------------------------------


def camera_info_to_camera(
    msg: CameraInfo, T_base_camera: FloatArray | None = None
) -> PinholeCamera:
    """CameraInfo -> PinholeCamera (raw, unrectified intrinsics K, D of its model).

    K must be upper-triangular with positive focal lengths and K[2, 2] = 1. The model
    names the coefficients (``camera_model.COEFFICIENT_NAMES``): plumb_bob takes exactly five
    (k1, k2, t1, t2, k3), rational_polynomial eight, equidistant four; no model ('')
    means no distortion (plumb_bob zeros), with D empty or all zero. Another model is an
    InvalidInput naming it."""
    K = np.array(msg.k, dtype=float).reshape(3, 3)
    if (
        not np.all(np.isfinite(K))
        or K[0, 0] <= 0
        or K[1, 1] <= 0
        or K[2, 2] != 1
        or np.any(K[[1, 2, 2], [0, 0, 1]] != 0)
    ):
        raise InvalidInput(
            f'camera_info K is not a valid intrinsic matrix (upper-triangular, '
            f'fx, fy > 0, K[2][2] = 1): {K.tolist()}',
            key='k',
        )
    model = msg.distortion_model or 'plumb_bob'
    if msg.distortion_model not in ('', *OPENCV_MODELS):
        raise InvalidInput(
            f'unsupported distortion model {msg.distortion_model!r} (expected one of '
            f'{", ".join(OPENCV_MODELS)} or none)',
            key='distortion_model',
        )
    D = np.zeros(DISTORTION_SIZES[model])
    if msg.distortion_model:
        if len(msg.d) != len(D):
            raise InvalidInput(
                f'camera_info D has {len(msg.d)} coefficients: {model} '
                f'takes {len(D)} ({COEFFICIENT_NAMES[model]})',
                key='d',
            )
        D[:] = msg.d
    elif any(msg.d):
        raise InvalidInput(
            'camera_info D has coefficients but no distortion_model', key='distortion_model'
        )
    if not np.all(np.isfinite(D)):
        raise InvalidInput('camera_info D contains non-finite values', key='d')
    if msg.width == 0 or msg.height == 0:
        raise InvalidInput('camera_info has zero image size', key='size')
    T = np.eye(4) if T_base_camera is None else T_base_camera
    return PinholeCamera(int(msg.width), int(msg.height), K, D, T, model)


def camera_info_rectification(msg: CameraInfo) -> tuple[FloatArray, FloatArray]:
    """(R 3x3, P 3x4) of a CameraInfo, validated: R a rotation (an all-zero R, "not
    set", is taken as the identity), P finite with positive focal lengths and last row
    (0, 0, 1, 0)."""
    R = np.array(msg.r, dtype=float).reshape(3, 3)
    P = np.array(msg.p, dtype=float).reshape(3, 4)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(P))):
        raise InvalidInput('camera_info R or P has non-finite values', key='r')
    if not R.any():
        R = np.eye(3)
    elif not is_rotation(R, tol=1e-6):
        raise InvalidInput(f'camera_info R is not a rotation: {R.tolist()}', key='r')
    if P[0, 0] <= 0 or P[1, 1] <= 0 or np.any(P[2] != (0, 0, 1, 0)):
        raise InvalidInput(
            f'camera_info P is not a projection matrix (fx, fy > 0, last row '
            f'0 0 1 0): {P.tolist()}',
            key='p',
        )
    return R, P


def camera_to_camera_info(
    camera: PinholeCamera,
    stamp_ns: int,
    frame_id: str,
    R: npt.ArrayLike | None = None,
    P: npt.ArrayLike | None = None,
) -> CameraInfo:
    """PinholeCamera -> CameraInfo. R (3x3) and P (3x4) default to the unrectified
    identity and [K | 0]."""
    R = np.eye(3) if R is None else np.asarray(R, dtype=float)
    P = np.hstack([camera.K, np.zeros((3, 1))]) if P is None else np.asarray(P, dtype=float)
    if camera.distortion_model not in OPENCV_MODELS:
        raise InvalidInput(
            f'CameraInfo has no distortion model {camera.distortion_model!r} (expected one '
            f'of {", ".join(OPENCV_MODELS)})',
            key='distortion_model',
        )
    D = np.zeros(DISTORTION_SIZES[camera.distortion_model])
    D[: len(camera.D)] = camera.D  # a shorter plumb_bob D padded with zeros
    return CameraInfo(
        header=make_header(stamp_ns, frame_id),
        height=camera.height,
        width=camera.width,
        distortion_model=camera.distortion_model,
        d=D.tolist(),
        k=camera.K.flatten().tolist(),
        r=R.flatten().tolist(),
        p=P.flatten().tolist(),
    )


# --- geometry_msgs/Pose, nav_msgs/Path -------------------------------------------------


def pose_to_matrix(pose: Pose) -> FloatArray:
    """geometry_msgs/Pose -> 4x4; rejects non-finite values and non-unit quaternions."""
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
    t = np.array([pose.position.x, pose.position.y, pose.position.z])
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise InvalidInput('pose has non-finite values', key='pose')
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise InvalidInput(
            f'pose orientation is not a unit quaternion (norm {np.linalg.norm(q):.4g})',
            key='orientation',
        )
    return make_transform(quaternion_to_matrix(q), t)


def matrix_to_pose(T: FloatArray) -> Pose:
    """4x4 -> geometry_msgs/Pose; raises InvalidInput unless the rotation is orthonormal."""
    if not is_rotation(T[:3, :3]):
        raise InvalidInput('transform rotation is not orthonormal', key='rotation')
    x, y, z, w = matrix_to_quaternion(T[:3, :3])
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation.x, pose.orientation.y = float(x), float(y)
    pose.orientation.z, pose.orientation.w = float(z), float(w)
    return pose


def matrix_to_pose_stamped(T: FloatArray, stamp_ns: int, frame_id: str) -> PoseStamped:
    """4x4 pose in ``frame_id`` -> geometry_msgs/PoseStamped stamped ``stamp_ns`` [ns];
    raises InvalidInput unless the rotation is orthonormal."""
    return PoseStamped(header=make_header(stamp_ns, frame_id), pose=matrix_to_pose(T))


def path_to_matrices(msg: Path) -> FloatArray:
    """nav_msgs/Path -> (N, 4, 4) poses in the path's frame; rejects empty paths."""
    if not msg.poses:
        raise InvalidInput('path is empty', key='poses')
    return np.stack([pose_to_matrix(p.pose) for p in msg.poses])


def matrices_to_path(T_frame_poses: Iterable[FloatArray], stamp_ns: int, frame_id: str) -> Path:
    """4x4 poses in ``frame_id`` -> nav_msgs/Path, every pose with the path's header
    (``stamp_ns`` [ns]); raises InvalidInput unless each rotation is orthonormal."""
    header = make_header(stamp_ns, frame_id)
    return Path(
        header=header,
        poses=[PoseStamped(header=header, pose=matrix_to_pose(T)) for T in T_frame_poses],
    )


# --- sensor_msgs/PointCloud2 (x, y, z float32) ---------------------------------------

_XYZ_FIELDS = [
    PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
    for i, n in enumerate('xyz')
]


def points_to_pointcloud2(points: npt.ArrayLike, stamp_ns: int, frame_id: str) -> PointCloud2:
    """(N, 3) points [m] -> unorganised PointCloud2 with float32 x, y, z."""
    points = np.ascontiguousarray(points, dtype='<f4').reshape(-1, 3)
    msg = PointCloud2(
        header=make_header(stamp_ns, frame_id),
        height=1,
        width=len(points),
        fields=list(_XYZ_FIELDS),
        is_bigendian=False,
        point_step=12,
        row_step=12 * len(points),
        is_dense=bool(np.all(np.isfinite(points))),
    )
    msg.data = points.tobytes()
    return msg


_XYZI_FIELDS = [
    *_XYZ_FIELDS,
    PointField(name='intensity', offset=12, datatype=PointField.FLOAT32, count=1),
]


def depth_to_pointcloud2(
    depth_m: npt.ArrayLike,
    K: npt.ArrayLike,
    grey: npt.ArrayLike,
    stamp_ns: int,
    frame_id: str,
) -> PointCloud2:
    """(H, W) depth [m, Z along the optical axis, NaN unknown] of the pinhole camera
    ``K`` (3, 3) -> organised PointCloud2 (height H, width W, as depth_image_proc's
    point_cloud_xyzi makes it): float32 x, y, z [m] in ``frame_id`` and intensity
    (``grey``, (H, W) grey levels); NaN x, y, z where the depth is unknown, so RViz and
    Foxglove show the cloud as it is and a pixel's point is at its pixel's index."""
    depth_m = np.asarray(depth_m, dtype=np.float32)
    grey = np.asarray(grey, dtype=np.float32)
    if depth_m.ndim != 2 or grey.shape != depth_m.shape:
        raise InvalidInput(
            f'depth {depth_m.shape} and grey {grey.shape} must be the same (H, W)', key='shape'
        )
    K = np.asarray(K, dtype=float)
    H, W = depth_m.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    points = np.empty((H, W, 4), dtype='<f4')
    points[..., 0] = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) * depth_m / K[0, 0]
    points[..., 1] = (v - K[1, 2]) * depth_m / K[1, 1]
    points[..., 2] = depth_m
    points[..., 3] = grey
    msg = PointCloud2(
        header=make_header(stamp_ns, frame_id),
        height=H,
        width=W,
        fields=list(_XYZI_FIELDS),
        is_bigendian=False,
        point_step=16,
        row_step=16 * W,
        is_dense=bool(np.all(np.isfinite(depth_m))),
    )
    msg.data = points.tobytes()
    return msg


def pointcloud2_to_points(msg: PointCloud2) -> npt.NDArray[np.float32]:
    """PointCloud2 with float32 x, y, z fields (any layout) -> (N, 3) float32 array."""
    offsets = {f.name: f for f in msg.fields}
    for name in 'xyz':
        field = offsets.get(name)
        if field is None or field.datatype != PointField.FLOAT32:
            raise InvalidInput(f'point cloud lacks a float32 {name!r} field', key='fields')
    count = msg.width * msg.height
    if len(msg.data) < count * msg.point_step:
        raise InvalidInput(
            'point cloud data is shorter than width * height * point_step', key='data'
        )
    dtype = np.dtype(
        {
            'names': list('xyz'),
            'formats': ['>f4' if msg.is_bigendian else '<f4'] * 3,
            'offsets': [offsets[n].offset for n in 'xyz'],
            'itemsize': msg.point_step,
        }
    )
    records = np.frombuffer(bytes(msg.data), dtype=dtype, count=count)
    return np.column_stack([records[n] for n in 'xyz']).astype(np.float32)


# --- sensor_msgs/CompressedImage (image_transport's compressed plugin) --------------


def grey_to_compressed_jpeg(
    array: npt.ArrayLike, quality: int, stamp_ns: int, frame_id: str
) -> CompressedImage:
    """(H, W) uint8 grey image -> CompressedImage, JPEG at ``quality`` (1..100), with the
    format string of image_transport's compressed plugin ('mono8; jpeg compressed mono8')."""
    import cv2  # only the nodes that compress need it

    array = np.ascontiguousarray(array)
    if array.ndim != 2 or array.dtype != np.uint8:
        raise InvalidInput(f'expected an (H, W) uint8 image, got {array.dtype} {array.shape}')
    ok, data = cv2.imencode('.jpg', array, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise InvalidInput('JPEG encoding failed')
    return CompressedImage(
        header=make_header(stamp_ns, frame_id),
        format='mono8; jpeg compressed mono8',
        data=data.tobytes(),
    )


def compressed_to_grey(msg: CompressedImage) -> npt.NDArray[np.uint8]:
    """CompressedImage (JPEG or PNG, any channels) -> (H, W) uint8 grey image."""
    import cv2

    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if image is None:
        raise InvalidInput(
            f'compressed image ({msg.format!r}, {data.size} bytes) does not decode as JPEG or PNG',
            key='data',
        )
    return cast(npt.NDArray[np.uint8], image)  # IMREAD_GRAYSCALE decodes to 8 bits
