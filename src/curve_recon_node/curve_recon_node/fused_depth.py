"""The newest usable fused depth image and its intrinsics, for the waypoints' approach
axes (the surface normals there), without ROS: curve_recon_node converts /depth/fused and
/depth/camera_info and hands the arrays here.

sfs_stereo_node publishes a frame's depth before its camera_info, and DDS does not order
the two topics: the first depth image waits for intrinsics; one it supersedes never had
any and is refused.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from curve_recon_node.waypoints import (
    DEPTH_RANGE_M,
    check_depth_intrinsics,
    normals_from_depth,
    usable_depth,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.topics import DEPTH_INFO_TOPIC


class DepthFrame(NamedTuple):
    """A depth image [m] and its stamp."""

    depth_m: FloatArray  # (H, W); unusable values NaN once accepted
    stamp_ns: int


class FusedDepth:
    """The newest accepted depth image (``latest``) and the intrinsics it goes with."""

    def __init__(self) -> None:
        self.latest: DepthFrame | None = None
        self._latest_K: FloatArray | None = None  # the intrinsics ``latest`` came with
        self._intrinsics: tuple[FloatArray, int, int] | None = None  # (K, width, height)
        self._waiting: DepthFrame | None = None  # depth that came before any intrinsics

    def set_intrinsics(self, K_rect: npt.ArrayLike, width: int, height: int) -> DepthFrame | None:
        """Take the rectified K (3, 3) of depth images ``width`` x ``height``; returns the
        depth image that waited for intrinsics, if one did (give it to ``add`` if its
        stamp is theirs). Raises InvalidInput for an implausible K: the depth images that
        go with it are unusable until valid intrinsics come."""
        K = np.asarray(K_rect, float)
        try:
            check_depth_intrinsics(K, width, height)
        except InvalidInput:
            self._intrinsics = None
            raise
        self._intrinsics = (K, width, height)
        waiting, self._waiting = self._waiting, None
        return waiting

    def add(self, depth_m: npt.ArrayLike, stamp_ns: int) -> dict[str, int] | None:
        """Accept a depth image [m] as ``latest``; returns the counts of values ignored
        for being unusable (see ``usable_depth``), or None when it waits for intrinsics.
        Raises InvalidInput when it cannot be used (nothing changes then)."""
        depth = np.asarray(depth_m, float)
        if self._intrinsics is None:
            superseded, self._waiting = self._waiting, DepthFrame(depth, stamp_ns)
            if superseded is None:
                return None
            raise InvalidInput(
                f'no valid {DEPTH_INFO_TOPIC} yet: the depth image cannot be used',
                key='camera_info',
            )
        K, width, height = self._intrinsics
        if depth.shape != (height, width):
            raise InvalidInput(
                f'depth is {depth.shape[1]}x{depth.shape[0]} but its '
                f'camera_info says {width}x{height}',
                key='size',
            )
        usable, removed = usable_depth(depth)
        if not np.isfinite(usable).any():
            raise InvalidInput(
                'no usable depth: every value is NaN, not positive or outside '
                f'[{DEPTH_RANGE_M[0]:g}, {DEPTH_RANGE_M[1]:g}] m ({removed})',
                key='depth',
                value=removed,
            )
        self.latest, self._latest_K = DepthFrame(usable, stamp_ns), K
        return removed

    def approach_directions(
        self,
        waypoints_base: npt.ArrayLike,
        T_base_left: npt.ArrayLike,
        R_left_rect: npt.ArrayLike,
        window_px: int,
    ) -> FloatArray | None:
        """Unit directions (N, 3) into the surface at ``waypoints_base`` (base frame),
        NaN rows where the depth has no normal, or None if it has none at any: from the
        latest depth, seen by the left camera at ``T_base_left`` whose rectification is
        ``R_left_rect`` (x_rect = R x_left). Raises InvalidInput (see
        ``normals_from_depth``)."""
        if self.latest is None or self._latest_K is None:
            return None
        T_base_left = np.asarray(T_base_left, float)
        T_base_rect = np.eye(4)
        T_base_rect[:3, :3] = T_base_left[:3, :3] @ np.asarray(R_left_rect, float).T
        T_base_rect[:3, 3] = T_base_left[:3, 3]
        normals = normals_from_depth(
            waypoints_base, self.latest.depth_m, self._latest_K, T_base_rect, window_px
        )
        if not np.any(np.all(np.isfinite(normals), axis=1)):
            return None
        return -normals
