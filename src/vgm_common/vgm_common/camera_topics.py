"""``CalibratedCameras``: what a node needs to know of the calibrated rig, assembled
from the latched CameraInfo and pose topics calib_node publishes (their names and frames
are in ``vgm_common.topics``); ``ImageCaptures``: the cameras' image streams paired by
stamp."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from vgm_common.camera_model import PinholeCamera
from vgm_common.conversions import (
    camera_info_rectification,
    camera_info_to_camera,
    pose_to_matrix,
    stamp_to_ns,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.sync import ExactTimeSync
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


class ImageCaptures:
    """The image topics of the cameras ``names`` paired by identical stamp (what
    message_filters' TimeSynchronizer does on them); each complete capture goes to
    ``on_capture(stamp_ns, {name: Image})``, on the thread of its last image.

    - ``subscribed``: the cameras subscribed to (default ``names``), so that ``use`` can
      change the paired ones at run time without new subscriptions.
    - ``streams``: name -> (message type, topic) for a stream that is not a camera's
      image (a stamped message paired with one, e.g. the DisparityImage of a rectified
      image); a name not in it is the camera's Image on its ``IMAGE_TOPICS`` topic.
    - ``accept(name, msg)``: checks every image before it is paired (falsy: not paired).
    - ``on_unpaired(total)``: called when images were dropped without their partners.
    - The sync is behind a lock: images of several callback groups and ``use`` from a
      parameter callback may come on several executor threads.
    """

    def __init__(
        self,
        node: Node,
        names: Iterable[str],
        on_capture: Callable[[int, dict[str, Any]], None],
        max_wait: float,
        *,
        subscribed: Iterable[str] | None = None,
        streams: Mapping[str, tuple[type, str]] | None = None,
        callback_group: CallbackGroup | None = None,
        accept: Callable[[str, Any], bool | None] | None = None,
        on_unpaired: Callable[[int], None] | None = None,
    ) -> None:
        self._on_capture = on_capture
        self._max_wait = max_wait
        self._accept = accept
        self._on_unpaired = on_unpaired
        self._lock = threading.Lock()
        self._sync = self._new_sync(names)
        streams = streams or {}
        for name in names if subscribed is None else subscribed:
            message_type, topic = streams.get(name) or (Image, IMAGE_TOPICS[name])
            node.create_subscription(
                message_type,
                topic,
                partial(self._on_image, name),
                DEFAULT_QOS,
                callback_group=callback_group,
            )

    def _new_sync(self, names: Iterable[str]) -> ExactTimeSync:
        self._unpaired_said = 0
        self._last_match = (time.monotonic(), 0)  # (time [s], dropped) at the last capture
        return ExactTimeSync(names, self._matched, queue_size=10, max_wait=self._max_wait)

    def use(self, names: Iterable[str]) -> None:
        """Pair ``names`` from now on; captures pending for the old set are dropped (they
        lack a view, or have one too many)."""
        with self._lock:
            self._sync = self._new_sync(names)

    @property
    def names(self) -> tuple[str, ...]:
        """The cameras paired now."""
        return self._sync.keys

    def _on_image(self, name: str, msg: Any) -> None:  # an Image, or a streams' type
        if self._accept is not None and not self._accept(name, msg):
            return
        with self._lock:
            if name not in self._sync.keys:
                return
            self._sync.add(name, stamp_to_ns(msg.header.stamp), msg, time.monotonic())
            dropped = self._sync.dropped
            newly_unpaired = dropped > self._unpaired_said
            self._unpaired_said = dropped
        if newly_unpaired and self._on_unpaired is not None:
            self._on_unpaired(dropped)

    def _matched(self, stamp_ns: int, messages: dict[str, Any]) -> None:
        self._last_match = (time.monotonic(), self._sync.dropped)
        self._on_capture(stamp_ns, messages)

    def counts(self) -> dict[str, int]:
        """Captures completed, images dropped without their partners, stamps pending."""
        return {
            'matched': self._sync.matched,
            'dropped': self._sync.dropped,
            'pending': self._sync.pending,
        }

    def unsynchronized(self) -> int:
        """Images dropped since the last complete capture, if that was longer than twice
        ``max_wait`` ago (the cameras' stamps do not agree), else 0."""
        since, dropped_then = self._last_match
        dropped = self._sync.dropped - dropped_then
        return dropped if time.monotonic() - since > 2 * self._max_wait else 0

    def silent(self, after: float) -> list[str]:
        """The cameras without an image for ``after`` [s] while another sent one (see
        ``ExactTimeSync.silent``)."""
        with self._lock:
            return self._sync.silent(time.monotonic(), after)


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
