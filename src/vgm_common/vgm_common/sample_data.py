"""Real images for tests and benches: the sample data Debian's ``opencv-doc`` package
ships (the Middlebury Aloe pair with ground-truth disparity, OpenCV's 9x6 chessboard
stereo calibration photographs), fetched once from the Debian registry and cached
outside the repository.

``opencv_sample_dir()`` returns the directory holding the files; it raises
SampleDataError with the reason when they cannot be fetched (a test that needs them
fails with that reason rather than skipping)."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import numpy.typing as npt

from vgm_common.errors import VgmError

PACKAGE = 'opencv-doc'
DATA_IN_PACKAGE = Path('usr/share/doc/opencv-doc/examples/data')
# Only what the tests and benches use is kept (the package is ~96 MB).
ALOE_FILES = ('aloeL.jpg', 'aloeR.jpg', 'aloeGT.png')
STEREO_CALIBRATION_IDS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14)  # no 10 shipped
STEREO_CALIBRATION_FILES = tuple(
    f'{side}{index:02d}.jpg' for index in STEREO_CALIBRATION_IDS for side in ('left', 'right')
)
CHESSBOARD_INNER_CORNERS = (9, 6)  # of the stereo calibration photographs


class SampleDataError(VgmError):
    """The sample data could not be fetched or is incomplete."""


def cache_dir() -> Path:
    """Where the files are kept: $VGM_DATA_CACHE, else ~/.cache/vgm/opencv-doc."""
    root = os.environ.get('VGM_DATA_CACHE') or Path.home() / '.cache' / 'vgm'
    return Path(root) / PACKAGE


def opencv_sample_dir() -> Path:
    """The directory with the Aloe pair and the stereo calibration photographs,
    downloading them with `apt-get download` + `dpkg-deb -x` on first use."""
    target = cache_dir()
    wanted = ALOE_FILES + STEREO_CALIBRATION_FILES
    if all((target / name).is_file() for name in wanted):
        return target
    for tool in ('apt-get', 'dpkg-deb'):
        if shutil.which(tool) is None:
            raise SampleDataError(
                f'cannot fetch {PACKAGE}: {tool} is not on PATH '
                '(a Debian machine is needed for the real-image data)'
            )
    with tempfile.TemporaryDirectory(prefix='vgm-opencv-doc-') as work_dir:
        work = Path(work_dir)
        _run(['apt-get', 'download', PACKAGE], cwd=work)
        debs = sorted(work.glob(f'{PACKAGE}_*.deb'))
        if not debs:
            raise SampleDataError(f'apt-get download {PACKAGE} produced no .deb in {work}')
        _run(['dpkg-deb', '-x', str(debs[0]), str(work / 'x')], cwd=work)
        source = work / 'x' / DATA_IN_PACKAGE
        missing = [name for name in wanted if not (source / name).is_file()]
        if missing:
            raise SampleDataError(f'{debs[0].name} lacks {", ".join(missing)}')
        staging = target.with_name(target.name + '.partial')
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir(parents=True)
        for name in wanted:
            shutil.copy2(source / name, staging / name)
        shutil.rmtree(target, ignore_errors=True)
        staging.rename(target)  # complete or absent: a killed fetch leaves no half cache
    return target


def _run(argv: list[str], cwd: Path) -> None:
    try:
        result = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise SampleDataError(f'{" ".join(argv)} failed: {error}') from error
    if result.returncode != 0:
        tail = (result.stderr or result.stdout).strip().splitlines()[-3:]
        raise SampleDataError(f'{" ".join(argv)} exited {result.returncode}: ' + ' | '.join(tail))


ALOE_WIDTH_PX = 1282  # aloeGT.png holds the full-size pair's disparities in pixels


def _aloe_images() -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8], npt.NDArray[np.uint8]]:
    """Full-size Aloe: left, right (grey) and the true left disparity image [px, 0 unknown]."""
    import cv2

    directory = opencv_sample_dir()
    images = []
    for name in ALOE_FILES:
        image = cv2.imread(str(directory / name), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise SampleDataError(f'{directory / name} is not a readable image')
        images.append(np.asarray(image, np.uint8))
    if images[0].shape[1] != ALOE_WIDTH_PX or images[2].shape[1] != ALOE_WIDTH_PX:
        raise SampleDataError(f'Aloe is not {ALOE_WIDTH_PX} px wide: another version?')
    return images[0], images[1], images[2]


def aloe_scaled(
    width: int,
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8], npt.NDArray[np.float64]]:
    """Middlebury Aloe, the whole pair scaled to ``width`` x proportional height: (left,
    right) grey uint8 and the true left disparity [px at that size, NaN unknown]."""
    import cv2

    left, right, truth = _aloe_images()
    size = (width, int(round(left.shape[0] * width / ALOE_WIDTH_PX)))
    disparity = cv2.resize(truth.astype(np.float32), size, interpolation=cv2.INTER_NEAREST)
    disparity = disparity.astype(float) * (width / ALOE_WIDTH_PX)
    disparity[disparity == 0] = np.nan
    left_scaled, right_scaled = (
        np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), np.uint8)
        for image in (left, right)
    )
    return left_scaled, right_scaled, disparity


def aloe_pair_640(
    shift: int = 24,
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8], npt.NDArray[np.float32]]:
    """Middlebury Aloe as a 640x480-class already-rectified pair: the middle 4:3 rows
    scaled to 640 px wide, the right image cropped by ``shift`` columns (a ``shift`` px
    principal-point offset between the two): (left, right) grey uint8 (480, 640 - shift)
    and the true left disparity [px, offset-corrected; 0 where unknown]."""
    import cv2

    left, right, truth_image = _aloe_images()
    truth = truth_image.astype(np.float32)
    rows = left.shape[1] * 3 // 4
    top = (left.shape[0] - rows) // 2
    scale = 640 / left.shape[1]
    left_scaled, right_scaled = (
        cv2.resize(image[top : top + rows], (640, 480), interpolation=cv2.INTER_AREA)
        for image in (left, right)
    )
    truth = scale * cv2.resize(
        truth[top : top + rows], (640, 480), interpolation=cv2.INTER_NEAREST
    )
    return (
        np.asarray(left_scaled[:, :-shift], np.uint8),
        np.asarray(right_scaled[:, shift:], np.uint8),
        np.asarray(truth[:, :-shift], np.float32),
    )
