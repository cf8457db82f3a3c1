"""image_publisher without ROS: the settings that are the one source of its parameters,
the image sets of a folder (the n-th ``<camera>*`` file of each camera, or of its
``<camera>/`` sub-folder, in name order) read as mono8, and the order they are shown in."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vgm_common.errors import VgmError
from vgm_common.settings import setting
from vgm_common.topics import CAMERA_NAMES

IMAGE_SUFFIXES = ('.png', '.jpg', '.jpeg', '.bmp', '.pgm', '.ppm', '.tif', '.tiff')


class ImageSetError(VgmError):
    """The folder does not hold usable image sets; the message says why."""


def _camera_names(names: tuple[str, ...] | list[str]) -> str | None:
    if names and all(n in CAMERA_NAMES for n in names):
        return None
    return f'must name cameras among {", ".join(CAMERA_NAMES)}'


@dataclass(frozen=True)
class ImageFolderSettings:
    """Which images image_publisher shows, and how: the one source of its parameters."""

    folder: str = setting('', 'Folder of the images: <camera>* files or <camera>/ sub-folders.')
    cameras: tuple[str, ...] = setting(
        ('left', 'right'),
        'Cameras whose images the folder holds (left, right, aux).',
        check=_camera_names,
        read_only=True,
    )
    calibration_file: str = setting(
        '',
        "A calibration.yaml (calib_node's output_dir): its cameras' CameraInfo (left/right "
        "rectified) and poses are published latched; '' publishes images only.",
        read_only=True,
    )
    rate: float = setting(
        1.0, 'Image sets per second.', unit='Hz', range=(0.01, 100.0), read_only=True
    )
    loop: bool = setting(False, 'Start again after the last set.', read_only=True)
    exit_when_done: bool = setting(
        False, 'Exit once every set was published once (unless loop).', read_only=True
    )
    wait_for_subscribers: float = setting(
        5.0,
        'Publishing starts once every image topic has a subscriber, or after this: a '
        'reliable publisher drops what it sends before discovery.',
        unit='s',
        range=(0.0, 3600.0),
        read_only=True,
    )


def image_sets(folder: str | Path, cameras: list[str]) -> list[dict[str, Path]]:
    """[{camera: file}] in name order: the n-th ``<camera>*`` file (or file of the
    ``<camera>/`` sub-folder) of each camera. Raises ImageSetError if the folder is
    missing, a camera has no image, or the cameras' counts differ."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ImageSetError(f'folder {str(folder)!r} is not a directory')
    files = {}
    for name in cameras:
        sub = folder / name
        candidates = sub.iterdir() if sub.is_dir() else folder.glob(f'{name}*')
        files[name] = sorted(
            p for p in candidates if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        )
    counts = {name: len(found) for name, found in files.items()}
    if not all(counts.values()) or len(set(counts.values())) != 1:
        listed = ', '.join(f'{name} {n}' for name, n in counts.items())
        raise ImageSetError(
            f'{folder}: every camera needs the same number of images, named <camera>* or '
            f'in <camera>/ ({", ".join(IMAGE_SUFFIXES)}); found {listed}'
        )
    return [dict(zip(files, paths)) for paths in zip(*files.values())]


def read_grey(path: Path) -> np.ndarray:
    """The image at ``path`` as mono8 (H, W) uint8; ImageSetError if it cannot be read."""
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ImageSetError(f'cannot read image {path}')
    return image


class SetCycle:
    """Which of ``count`` image sets comes next: each once in order, or with ``loop``
    again and again."""

    def __init__(self, count: int, loop: bool) -> None:
        self._count = count
        self._loop = loop
        self._next = 0

    def next(self) -> int | None:
        """The index of the set to show now; None once each was shown (without loop)."""
        if self._next == self._count:
            if not self._loop:
                return None
            self._next = 0
        index = self._next
        self._next += 1
        return index

    @property
    def done(self) -> bool:
        """True once each set was shown, without loop (the last one now)."""
        return not self._loop and self._next == self._count
