"""Rigid transforms as plain numpy arrays.

Conventions: a pose ``T_a_b`` is a 4x4 homogeneous matrix mapping coordinates in frame
``b`` to frame ``a`` (``p_a = T_a_b @ p_b``). Roll-pitch-yaw are fixed-axis angles as in
ROS (REP 103): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``. Quaternions are ``(x, y, z, w)``
as in geometry_msgs.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]  # the float64 arrays these functions return


def _rotation(angle: npt.ArrayLike, axis: Literal['x', 'y', 'z']) -> FloatArray:
    """Rotation(s) by ``angle`` [rad] (scalar or any shape S) about a coordinate axis:
    (3, 3), or (*S, 3, 3) for arrays of angles."""
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    rows = {
        'x': ((one, zero, zero), (zero, c, -s), (zero, s, c)),
        'y': ((c, zero, s), (zero, one, zero), (-s, zero, c)),
        'z': ((c, -s, zero), (s, c, zero), (zero, zero, one)),
    }[axis]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def rot_x(angle: npt.ArrayLike) -> FloatArray:
    """Rotation(s) by ``angle`` [rad] about x: (3, 3), or (*S, 3, 3) for an array of
    angles of shape S."""
    return _rotation(angle, 'x')


def rot_y(angle: npt.ArrayLike) -> FloatArray:
    """Rotation(s) by ``angle`` [rad] about y: (3, 3), or (*S, 3, 3) for an array of
    angles of shape S."""
    return _rotation(angle, 'y')


def rot_z(angle: npt.ArrayLike) -> FloatArray:
    """Rotation(s) by ``angle`` [rad] about z: (3, 3), or (*S, 3, 3) for an array of
    angles of shape S."""
    return _rotation(angle, 'z')


def rpy_to_matrix(roll: npt.ArrayLike, pitch: npt.ArrayLike, yaw: npt.ArrayLike) -> FloatArray:
    """Rotation of fixed-axis roll, pitch, yaw [rad]: (3, 3), or (*S, 3, 3) for arrays of
    angles (a whole population of cameras at once)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def quaternion_to_matrix(q_xyzw: npt.ArrayLike) -> FloatArray:
    """3x3 rotation of a quaternion (x, y, z, w); it is normalised first."""
    x, y, z, w = np.asarray(q_xyzw, dtype=float) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(R: npt.ArrayLike) -> FloatArray:
    """Quaternion (x, y, z, w) with w >= 0 of a 3x3 rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    trace = np.trace(R)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        xyzw = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        xyzw = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        xyzw[i] = s / 4
        xyzw[j] = (R[j, i] + R[i, j]) / s
        xyzw[k] = (R[k, i] + R[i, k]) / s
    q = np.array(xyzw)
    return q if q[3] >= 0 else -q


def look_at_rotation(
    position: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Rotation of a camera optical frame (z forward, x right, y down) at ``position``
    looking at ``target``, with image 'up' as close to ``up`` as possible."""
    z = np.asarray(target, dtype=float) - np.asarray(position, dtype=float)
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=float)
    if np.linalg.norm(np.cross(up, z)) < 1e-6:  # looking along 'up': any image x will do
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def make_transform(R: npt.ArrayLike, t: npt.ArrayLike) -> FloatArray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_transform(T: FloatArray) -> FloatArray:
    """Inverse of a rigid 4x4 transform: ``T_b_a`` from ``T_a_b``."""
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: FloatArray, points: npt.ArrayLike) -> FloatArray:
    """Apply a 4x4 transform to (N, 3) points."""
    points = np.asarray(points, dtype=float)
    return points @ T[:3, :3].T + T[:3, 3]


def is_rotation(R: npt.ArrayLike, tol: float = 1e-6) -> bool:
    """True if R is a finite proper orthonormal 3x3 matrix."""
    R = np.asarray(R, dtype=float)
    return (
        R.shape == (3, 3)
        and bool(np.all(np.isfinite(R)))
        and np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1) < tol
    )
