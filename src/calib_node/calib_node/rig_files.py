"""calib_node's files, without ROS: where a calibration is written (calibration.yaml,
the cameras' camera_calibration_parsers files and the PNGs) and the saved rig published
instead of calibrating; the settings that name them are the one source of those
parameters."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from calib_node.plots import write_plots
from calib_node.session import Calibration
from vgm_common.calibration_io import read_calibration, stereo_rectification, write_calibration
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.settings import setting
from vgm_common.topics import OPTICAL_FRAMES


@dataclass(frozen=True)
class FileSettings:
    """Where calib_node's calibration comes from and goes to, and how it pairs images."""

    calibration_file: str = setting(
        '',
        'A calibration.yaml (or its directory) to publish at start instead of calibrating; '
        "the left/right rectification is recomputed from the cameras, aux's R, P are as "
        'stored; a bad file is a one-line start-up error (exit status 2). Empty: calibrate '
        'from the chart.',
        read_only=True,
    )
    output_dir: str = setting(
        '',
        'Where calibration.yaml (the whole rig with poses and quality) and left.yaml, '
        'right.yaml, aux.yaml (camera_calibration_parsers format) are written; empty: not '
        'written.',
    )
    sync_max_wait: float = setting(
        5.0,
        'Incomplete capture sets are dropped after this.',
        unit='s',
        range=(0.01, 60.0),
        read_only=True,
    )


@dataclass(frozen=True)
class Written:
    """What ``write_rig`` wrote: calibration.yaml's path, the PNGs, and why there are no
    PNGs ('' if there are)."""

    calibration_yaml: Path
    plots: list[Path]
    plots_missing: str

    def summary(self, names: tuple[str, ...]) -> str:
        """The log line of what was written for the cameras ``names``."""
        pictures = (
            f' and {len(self.plots)} PNGs (residuals, coverage, uncertainty, '
            'cross-validation, rectified pair)'
            if self.plots
            else ''
        )
        return (
            f'wrote {self.calibration_yaml} and {", ".join(f"{n}.yaml" for n in names)}'
            f'{pictures} beside it (calibration_file:={self.calibration_yaml} publishes it again)'
        )


def write_rig(output_dir: str | Path, calibration: Calibration) -> Written:
    """Write ``calibration`` into ``output_dir``. Raises OSError or VgmError if the YAML
    cannot be written; the plots are an extra that may fail alone (the YAML is what
    matters)."""
    written = write_calibration(
        output_dir,
        calibration.cameras,
        OPTICAL_FRAMES,
        calibration.rectification,
        calibration.quality(),
    ).resolve()  # where the files are is the first thing a user looks for
    try:
        plots = write_plots(
            output_dir,
            {n: (c.width, c.height) for n, c in calibration.cameras.items()},
            calibration.residuals,
            calibration.uncertainty,
            calibration.cross_validation,
            (calibration.cameras, calibration.rectification),
            calibration.stereo_corners,
        )
    except (OSError, ImportError, ValueError) as error:
        return Written(written, [], str(error))
    return Written(written, plots, '')


def read_rig(
    path: str | Path, names: tuple[str, ...]
) -> tuple[dict[str, PinholeCamera], dict[str, tuple[FloatArray, FloatArray]]]:
    """The cameras ``names`` of a saved calibration and their rectification (R, P): left
    and right rectified again from the cameras, as every consumer expects; the others
    as stored. Raises InvalidInput for a bad file or a missing camera."""
    rig = read_calibration(path)
    missing = [name for name in names if name not in rig]
    if missing:
        raise InvalidInput(
            f'calibration_file {path} lacks {", ".join(missing)}', key='calibration_file'
        )
    cameras = {name: rig[name][0] for name in names}
    rectification = {
        **{n: rig[n][1:] for n in names if n not in ('left', 'right')},
        **stereo_rectification(cameras['left'], cameras['right']),
    }
    return cameras, rectification
