"""Pictures of a calibration for a user to judge at a glance, written beside
calibration.yaml: per camera the residual vectors over the image, the coverage of the views,
the predicted projection uncertainty and the cross-validation (the halves' difference); for
the stereo pair the chart corners both cameras saw, rectified, on the epipolar lines.
matplotlib's object API (no pyplot: the worker thread draws them, and pyplot's global state
is not thread-safe). No rclpy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from calib_node.cross_validation import CrossValidation
from calib_node.uncertainty import Uncertainty
from vgm_common.camera_model import PinholeCamera
from vgm_common.geometry import FloatArray

FIGURE_SIZE_IN = (6.4, 4.8)
DPI = 100  # 640 x 480 px
PLOT_SIZE_PX = (int(FIGURE_SIZE_IN[0] * DPI), int(FIGURE_SIZE_IN[1] * DPI))
PAIR_SIZE_PX = (2 * PLOT_SIZE_PX[0], PLOT_SIZE_PX[1])  # the rectified pair side by side
EPIPOLAR_LINES = 12  # rows drawn across the rectified pair
ARROW_FRACTION = 0.04  # the RMS residual drawn as this fraction of the image width

# {name: [(N, 2) observed corners, (N, 2) residuals (observed - projected)] per view}
Residuals = Mapping[str, list[tuple[FloatArray, FloatArray]]]
# [(left (N, 2), right (N, 2)) corners of a view both saw, row k the same chart corner]
StereoCorners = Sequence[tuple[FloatArray, FloatArray]]


def _figure(size: tuple[int, int], title: str):  # type: ignore[no-untyped-def]
    """A Figure with one axes over the image (origin top left), and its canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=FIGURE_SIZE_IN, dpi=DPI)
    canvas = FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    axes.set_xlim(0, size[0])
    axes.set_ylim(size[1], 0)
    axes.set_aspect('equal')
    axes.set_xlabel('u [px]')
    axes.set_ylabel('v [px]')
    axes.set_title(title, fontsize=9)
    return figure, canvas, axes


def write_plots(
    directory: str | Path,
    image_sizes: Mapping[str, tuple[int, int]],
    residuals: Residuals,
    uncertainty: Uncertainty | None,
    cross_validation: CrossValidation | None = None,
    stereo: tuple[Mapping[str, PinholeCamera], Mapping[str, tuple[FloatArray, FloatArray]]]
    | None = None,
    stereo_corners: StereoCorners = (),
) -> list[Path]:
    """Write ``<camera>_residuals.png``, ``<camera>_coverage.png``, (with an uncertainty)
    ``<camera>_uncertainty.png`` and (with a cross-validation)
    ``<camera>_cross_validation.png`` (PLOT_SIZE_PX each) into ``directory``, and with
    ``stereo`` (the cameras and their rectification {name: (R, P)}) and ``stereo_corners``
    ``rectified_pair.png`` (PAIR_SIZE_PX, :func:`rectified_pair`); returns their paths."""
    from matplotlib import colormaps

    directory = Path(directory)
    written = []
    for name, views in residuals.items():
        size = image_sizes[name]
        corners = np.concatenate([c for c, _ in views])
        errors = np.concatenate([r for _, r in views])
        rms = float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))
        figure, canvas, axes = _figure(
            size,
            f'{name}: reprojection residuals, RMS {rms:.3f} px '
            f'(arrows x{ARROW_FRACTION * size[0] / max(rms, 1e-12):.0f})',
        )
        scale = ARROW_FRACTION * size[0] / max(rms, 1e-12)
        axes.quiver(
            corners[:, 0],
            corners[:, 1],
            scale * errors[:, 0],
            scale * errors[:, 1],
            angles='xy',
            scale_units='xy',
            scale=1.0,
            width=0.002,
            color='tab:red',
        )
        written.append(_save(figure, canvas, directory / f'{name}_residuals.png'))

        figure, canvas, axes = _figure(size, f'{name}: chart corners of {len(views)} views')
        for k, (view_corners, _) in enumerate(views):
            colour = colormaps['viridis'](k / max(len(views) - 1, 1))  # one colour per view
            axes.plot(view_corners[:, 0], view_corners[:, 1], '.', markersize=2, color=colour)
        written.append(_save(figure, canvas, directory / f'{name}_coverage.png'))

        if uncertainty is not None and name in uncertainty.grid_px:
            title = (
                f'{name}: predicted projection std at {uncertainty.range_m[name]:.2f} m, worst '
                f'{uncertainty.worst_px[name]:.2f} px, median {uncertainty.median_px[name]:.2f}'
            )
            path = directory / f'{name}_uncertainty.png'
            written.append(_heat_map(size, uncertainty.grid_px[name], title, corners, path))
        if cross_validation is not None and name in cross_validation.grid_px:
            title = (
                f'{name}: halves ({"%d / %d" % cross_validation.halves} views) apart at '
                f'{cross_validation.range_m[name]:.2f} m, worst '
                f'{cross_validation.worst_px[name]:.2f} px, median '
                f'{cross_validation.median_px[name]:.2f}'
            )
            path = directory / f'{name}_cross_validation.png'
            written.append(_heat_map(size, cross_validation.grid_px[name], title, corners, path))
    if stereo is not None and stereo_corners:
        written.append(rectified_pair(directory / 'rectified_pair.png', *stereo, stereo_corners))
    return written


def rectified_pixels(
    camera: PinholeCamera, R: FloatArray, P: FloatArray, pixels: npt.ArrayLike
) -> FloatArray:
    """(N, 2) pixels of ``camera`` where they land in its rectified image (rectifying
    rotation ``R``, projection ``P``): the undistorted ray turned by R, projected by P's
    3 x 3 (P's last column places the right camera in the left's frame; a ray from the
    camera's own centre does not need it)."""
    xy = camera.undistort_pixels(pixels)
    rays = np.column_stack([xy, np.ones(len(xy))]) @ R.T @ np.asarray(P)[:, :3].T
    return rays[:, :2] / rays[:, 2:]


def rectified_pair(
    path: Path,
    cameras: Mapping[str, PinholeCamera],
    rectification: Mapping[str, tuple[FloatArray, FloatArray]],
    stereo_corners: StereoCorners,
) -> Path:
    """The left and right rectified images side by side with horizontal epipolar lines
    and the chart corners of every view both saw, rectified: a good rectification puts
    each corner on the same row in both (the title gives the row difference, RMS and
    worst, over every corner pair)."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    size = (int(cameras['left'].width), int(cameras['left'].height))  # the rectified window
    rectified = {
        name: [
            rectified_pixels(cameras[name], *rectification[name], view[side])
            for view in stereo_corners
        ]
        for side, name in enumerate(('left', 'right'))
    }
    rows = np.concatenate(
        [lv[:, 1] - rv[:, 1] for lv, rv in zip(rectified['left'], rectified['right'])]
    )
    rows = rows[np.isfinite(rows)]
    figure = Figure(figsize=(2 * FIGURE_SIZE_IN[0], FIGURE_SIZE_IN[1]), dpi=DPI)
    canvas = FigureCanvasAgg(figure)
    figure.suptitle(
        f'rectified pair: {len(stereo_corners)} views, rows apart RMS '
        f'{np.sqrt(np.mean(rows**2)):.3f} px, worst {np.max(np.abs(rows)):.3f} px',
        fontsize=9,
    )
    for column, name in enumerate(('left', 'right')):
        axes = figure.add_subplot(1, 2, column + 1)
        axes.set_xlim(0, size[0])
        axes.set_ylim(size[1], 0)
        axes.set_aspect('equal')
        axes.set_title(f'{name} rectified', fontsize=9)
        axes.set_xlabel('u [px]')
        for v in np.linspace(0, size[1], EPIPOLAR_LINES + 2)[1:-1]:
            axes.axhline(v, color='tab:green', linewidth=0.6)
        for k, uv in enumerate(rectified[name]):
            colour = colormaps['viridis'](k / max(len(stereo_corners) - 1, 1))
            axes.plot(uv[:, 0], uv[:, 1], '.', markersize=2, color=colour)
    return _save(figure, canvas, path)


def _heat_map(
    size: tuple[int, int], grid: FloatArray, title: str, corners: FloatArray, path: Path
) -> Path:
    """A grid of pixel figures [px] over the image, the chart corners seen dotted on it."""
    figure, canvas, axes = _figure(size, title)
    image = axes.imshow(
        grid, extent=(0, size[0], size[1], 0), interpolation='bilinear', cmap='magma', vmin=0.0
    )
    figure.colorbar(image, ax=axes, label='px', shrink=0.8)
    axes.plot(corners[:, 0], corners[:, 1], ',', color='white', alpha=0.5)
    return _save(figure, canvas, path)


def _save(figure, canvas, path: Path) -> Path:  # type: ignore[no-untyped-def]
    canvas.print_png(str(path))
    return path
