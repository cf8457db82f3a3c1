"""``CalibratedCameras``: what a node needs to know of the calibrated rig, assembled
from the latched CameraInfo and pose topics calib_node publishes (their names and frames
are in ``vgm_common.topics``); ``subscribe_images``: the cameras' image streams."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from vgm_common.camera_model import PinholeCamera
from vgm_common.conversions import camera_info_rectification, camera_info_to_camera, pose_to_matrix
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import (
    BASE_FRAME,
    CAMERA_INFO_TOPICS,
    CAMERA_NAMES,
    IMAGE_TOPICS,
    POSE_TOPICS,
)

if TYPE_CHECKING:
    from rclpy.callback_groups import CallbackGroup
    from rclpy.node import Node

    from vgm_common.diagnostics import Diagnostics


def subscribe_images(
    node: Node,
    names: Iterable[str],
    on_image: Callable[[str, Image], None],
    callback_group: CallbackGroup | None = None,
) -> None:
    """Subscribes ``node`` to the image topic of each camera in ``names``, calling
    ``on_image(name, msg)``; one ``callback_group`` for all, so that a node's image sync
    (not thread-safe) is fed from one thread at a time."""
    for name in names:
        node.create_subscription(
            Image,
            IMAGE_TOPICS[name],
            partial(on_image, name),
            DEFAULT_QOS,
            callback_group=callback_group,
        )


@dataclass(frozen=True)
class CalibratedCamera:
    """One camera as calibrated: the raw camera (K, D, pose in base_link) and the
    rectification (R 3x3, P 3x4) of its CameraInfo."""

    camera: PinholeCamera
    R: np.ndarray
    P: np.ndarray


class CalibratedCameras:
    """Subscribes the latched camera_info and pose of ``names`` and keeps the newest
    valid pair of each. Invalid messages are reported to ``diagnostics`` and ignored (the
    previous calibration stays). ``version`` increases whenever a camera changes, so
    users can rebuild cached maps; ``on_change(name)`` is called then, if given."""

    def __init__(
        self,
        node: Node,
        names: Iterable[str] = CAMERA_NAMES,
        diagnostics: Diagnostics | None = None,
        on_change: Callable[[str], None] | None = None,
    ) -> None:
        self.names = tuple(names)
        self._diagnostics = diagnostics
        self._on_change = on_change
        self._infos: dict[str, CameraInfo] = {}
        self._poses: dict[str, FloatArray] = {}  # T_base_camera
        self._cameras: dict[str, CalibratedCamera] = {}
        self.version = 0
        for name in self.names:
            node.create_subscription(
                CameraInfo, CAMERA_INFO_TOPICS[name], partial(self._on_info, name), LATCHED_QOS
            )
            node.create_subscription(
                PoseStamped, POSE_TOPICS[name], partial(self._on_pose, name), LATCHED_QOS
            )

    @property
    def ready(self) -> bool:
        """True once every camera of ``names`` has a valid camera_info and pose."""
        return all(name in self._cameras for name in self.names)

    def missing(self) -> list[str]:
        """Names of the cameras not yet calibrated (for diagnostics)."""
        return [name for name in self.names if name not in self._cameras]

    def __getitem__(self, name: str) -> CalibratedCamera:
        return self._cameras[name]

    def get(self, name: str) -> CalibratedCamera | None:
        """The ``CalibratedCamera`` of ``name``, or None while it is not calibrated."""
        return self._cameras.get(name)

    def _on_info(self, name: str, msg: CameraInfo) -> None:
        try:
            camera_info_to_camera(msg)  # validates
            camera_info_rectification(msg)
        except (InvalidInput, ValueError) as error:
            self._reject(CAMERA_INFO_TOPICS[name], error)
            return
        self._infos[name] = msg
        self._update(name)

    def _on_pose(self, name: str, msg: PoseStamped) -> None:
        try:
            if msg.header.frame_id != BASE_FRAME:
                raise InvalidInput(
                    f'camera pose must be in {BASE_FRAME}, got {msg.header.frame_id!r}',
                    key='frame_id',
                )
            T = pose_to_matrix(msg.pose)
        except InvalidInput as error:
            self._reject(POSE_TOPICS[name], error)
            return
        self._poses[name] = T
        self._update(name)

    def _update(self, name: str) -> None:
        if name not in self._infos or name not in self._poses:
            return
        info = self._infos[name]
        self._cameras[name] = CalibratedCamera(
            camera_info_to_camera(info, self._poses[name]), *camera_info_rectification(info)
        )
        self.version += 1
        if self._on_change is not None:
            self._on_change(name)

    def _reject(self, what: str, error: Exception) -> None:
        if self._diagnostics is not None:
            self._diagnostics.reject(what, error)
