"""calib_node against mrcal (and OpenCV) on the same chessboard corners (calib_node's
detector): OpenCV's 13 stereo sample pairs (Debian's opencv-doc) and generated stereo rigs
(``vgm_evaluation.rig_generator``, rendered, with the truth), calibrated by

- ours: ``bundle.bundle_adjust_selected`` (the handheld core, plumb_bob k1 k2 p1 p2 by BIC),
- mrcal: ``mrcal-calibrate-cameras`` on a corners file of those corners (LENSMODEL_OPENCV4 =
  k1 k2 p1 p2, the board taken as flat: ``--skip-calobject-warp-solve``; mrcal's defaults
  otherwise: its light regularisation and outlier rejection),
- OpenCV: calibrateCamera + stereoCalibrate (``calib_rigs.opencv_rig``).

Per camera fx, fy, cx, cy, RMS, baseline, and the projection uncertainty at the working
range (the median depth of the corners in our fit) over the same 16 x 12 pixel grid:
ours (``uncertainty.rig_uncertainty``, the point held to the charts) beside mrcal's own
(``mrcal.projection_uncertainty``, 'mean-pcam', run by ``mrcal_peer.py``), both as
sqrt(trace) of the 2 x 2 covariance. On generated rigs also the errors against the truth
and the true projection error at the working range in the left camera's frame
(``rig_generator.true_projection_error``) and held to the charts
(``rig_generator.true_projection_error_chart_fixed``, each tool's own chart poses). And the
cross-validation of ours (``cross_validation``) beside mrcal's (``mrcal.projection_diff``
of its calibrations of the same two halves).

mrcal is no dependency of the project: the bench runs it as a separate process, with the
interpreter and path given (``--mrcal-python``, ``--mrcal-path``). Set-up used (PyPI's
wheels need Python >= 3.12; pyfltk, a GUI dependency, does not build here and is not
needed):

    PY=python3.12
    $PY -m pip install --target /tmp/mrcal --no-deps mrcal==2.5.2.post1 numpysane gnuplotlib
    $PY -m pip install --target /tmp/mrcal numpy scipy opencv-python-headless pyyaml shapely \
        packaging
"""

import json
import os
import subprocess
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from calib_rigs import detect_views, opencv_rig
from vgm_evaluation.rig_generator import (
    camera_in_frame,
    draw_rig,
    render_rig,
    true_projection_error,
    true_projection_error_chart_fixed,
)

from calib_node.bundle import bundle_adjust_selected
from calib_node.chart_detection import chart_points, detect_chessboard
from calib_node.cross_validation import compare_halves, split_chart_views
from calib_node.uncertainty import (
    GRID,
    image_grid,
)
from vgm_common.sample_data import STEREO_CALIBRATION_IDS, opencv_sample_dir

NAMES = ('left', 'right')
PEER = Path(__file__).resolve().parent / 'mrcal_peer.py'
# mrcal as it runs by default (outliers rejected) and on every corner, as ours and OpenCV.
MRCAL_RUNS = {'mrcal': (), 'mrcal, all corners': ('--skip-outlier-rejection',)}
TOOLS = ('ours', *MRCAL_RUNS, 'opencv')


class Board(NamedTuple):
    rows: int  # inner corners along the chart y axis
    cols: int
    spacing: float  # [m]


class Mrcal(NamedTuple):
    python: str  # mrcal's interpreter
    path: str  # its pip --target directory (bin/ holds mrcal-calibrate-cameras)


SAMPLE_BOARD = Board(6, 9, 0.025)  # OpenCV's stereo sample photographs


def sample_views():
    """([{name: corners (54, 2)}] per pair, {name: (width, height)})."""
    directory = Path(opencv_sample_dir())
    views, sizes = [], {}
    for index in STEREO_CALIBRATION_IDS:
        view = {}
        for name in NAMES:
            grey = cv2.imread(str(directory / f'{name}{index:02d}.jpg'), cv2.IMREAD_GRAYSCALE)
            sizes[name] = grey.shape[::-1]
            view[name] = detect_chessboard(grey, SAMPLE_BOARD.rows, SAMPLE_BOARD.cols).corners
        views.append(view)
    return views, sizes


def write_corners(path, views):
    """mrcal's corners file (vnlog ``filename x y level``): our corners in the chart's
    row-major order (index r * cols + c: mrcal's object-width-n = cols); a camera that
    missed the chart in a view is the row ``filename - - -``."""
    lines = ['# filename x y level']
    for index, view in enumerate(views):
        for name in NAMES:
            image = f'{name}{index:03d}.png'
            if name not in view:
                lines.append(f'{image} - - -')
                continue
            lines += [f'{image} {u:.6f} {v:.6f} 0' for u, v in view[name]]
    Path(path).write_text('\n'.join(lines) + '\n')


def _calibrate_mrcal(views, size, board, mrcal, focal, options, work):
    """mrcal-calibrate-cameras on ``views`` into the directory ``work`` (camera-<i>.cameramodel);
    its wall time [s]."""
    corners = Path(work) / 'corners.vnl'
    write_corners(corners, views)
    started = time.perf_counter()
    arguments = [
        *('--corners-cache', str(corners), '--imagersize', *map(str, size)),
        *('--lensmodel', 'LENSMODEL_OPENCV4', '--focal', str(focal)),
        *('--object-spacing', str(board.spacing), '--object-width-n', str(board.cols)),
        *('--object-height-n', str(board.rows), '--skip-calobject-warp-solve'),
        *options,
        *('--outdir', str(work)),
        *[f'{name}*.png' for name in NAMES],
    ]
    command = [mrcal.python, str(Path(mrcal.path) / 'bin' / 'mrcal-calibrate-cameras')]
    subprocess.run(
        command + arguments,
        env=dict(os.environ, PYTHONPATH=mrcal.path),
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return time.perf_counter() - started


def _peer(mrcal, request):
    """mrcal_peer.py's JSON answer to ``request``."""
    answer = subprocess.run(
        [mrcal.python, str(PEER), json.dumps(request)],
        env=dict(os.environ, PYTHONPATH=mrcal.path),
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return json.loads(answer.stdout)


def run_mrcal(views, size, board, pixels, ranges, mrcal, focal, options=()):
    """mrcal-calibrate-cameras + mrcal_peer.py in a temporary directory: the peer's JSON
    per camera and the calibration's wall time [s]."""
    with tempfile.TemporaryDirectory(prefix='calib-mrcal-') as work:
        seconds = _calibrate_mrcal(views, size, board, mrcal, focal, options, work)
        request = {
            'models': [str(Path(work) / f'camera-{i}.cameramodel') for i in range(len(NAMES))],
            'pixels': [p.tolist() for p in pixels],
            'ranges': ranges,
        }
        return _peer(mrcal, request), seconds


def cross_validation(views, sizes, board, mrcal, ranges, focal):
    """Ours and mrcal's cross-validation on the same two halves of the views
    (``cross_validation.split_chart_views``): {tool: {name: (worst, median) [px]}} and the
    halves' sizes. Ours: the halves' bundle adjustments, one rigid transform fitted for the
    rig (calib_node's figure); mrcal: mrcal-calibrate-cameras on each half, then
    ``mrcal.projection_diff`` per camera (its transform fitted per camera)."""
    chart = chart_points(*board)
    views = [v for v in views if v]
    halves = split_chart_views(views, NAMES, board.rows, board.cols, sizes)
    ours = [
        bundle_adjust_selected(chart, [views[i] for i in h], sizes, None, NAMES) for h in halves
    ]
    cameras = [{n: f.camera(sizes[n]) for n, f in r.fits.items()} for r in ours]
    uncertainty = (ours[0].uncertainty, ours[1].uncertainty)
    counts = (len(halves[0]), len(halves[1]))
    ranges_m = dict(zip(NAMES, ranges))
    cross = compare_halves(cameras[0], cameras[1], ranges_m, counts, True, uncertainty)
    result = {'ours': {n: (cross.worst_px[n], cross.median_px[n]) for n in NAMES}}
    for tool, options in MRCAL_RUNS.items():
        with tempfile.TemporaryDirectory(prefix='calib-mrcal-') as work:
            for k, half in enumerate(halves):
                (Path(work) / f'half{k}').mkdir()
                half_views = [views[i] for i in half]
                _calibrate_mrcal(
                    half_views,
                    sizes['left'],
                    board,
                    mrcal,
                    focal,
                    options,
                    Path(work) / f'half{k}',
                )
            models = [
                [str(Path(work) / f'half{k}' / f'camera-{i}.cameramodel') for k in (0, 1)]
                for i in range(len(NAMES))
            ]
            answer = _peer(mrcal, {'halves': models, 'ranges': list(ranges)})
        result[tool] = {n: (a['worst_px'], a['median_px']) for n, a in zip(NAMES, answer)}
    return result, counts


def cross_validation_lines(result, counts):
    """Markdown rows of :func:`cross_validation`."""
    return [
        f'| {name} | {tool} | {counts[0]} / {counts[1]} | {result[tool][name][0]:.2f} / '
        f'{result[tool][name][1]:.2f} |'
        for name in NAMES
        for tool in ('ours', *MRCAL_RUNS)
    ]


def calibrate_three(views, sizes, board, mrcal):
    """Ours, mrcal (both runs) and OpenCV on the same corners: ({tool: {name: solution}},
    {tool: seconds}, working ranges, our baseline std [m]); a solution is a dict of K, D
    (5,), T_camera_ref (4, 4; left = reference), rms, std grid (ours and mrcal), outliers."""
    chart = chart_points(*board)
    views = [v for v in views if v]  # a view no camera saw the chart in tells nothing
    started = time.perf_counter()
    ours = bundle_adjust_selected(chart, views, sizes, None, NAMES)
    seconds = {'ours': time.perf_counter() - started}
    pixels = [image_grid(sizes[n], GRID) for n in NAMES]
    ranges = [ours.uncertainty.range_m[n] for n in NAMES]
    solutions = {
        'ours': {
            n: {
                'K': f.K,
                'D': np.asarray(f.D, dtype=float),
                'T_camera_ref': np.linalg.inv(f.T_base_camera),
                'rms': f.rms_px,
                'std': ours.uncertainty.grid_px[n].ravel(),
                'T_ref_chart': ours.T_ref_chart,
            }
            for n, f in ours.fits.items()
        }
    }
    focal = float(np.mean([ours.fits[n].K[0, 0] for n in NAMES]))
    for tool, options in MRCAL_RUNS.items():
        peer, seconds[tool] = run_mrcal(
            views, sizes['left'], board, pixels, ranges, mrcal, focal, options
        )
        solutions[tool] = {}
        for name, theirs in zip(NAMES, peer):
            fx, fy, cx, cy, k1, k2, p1, p2 = theirs['intrinsics']
            T_ref_camera = np.eye(4)
            Rt = np.asarray(theirs['T_ref_camera'])
            T_ref_camera[:3, :3], T_ref_camera[:3, 3] = Rt[:3], Rt[3]
            solutions[tool][name] = {
                'K': np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
                'D': np.array([k1, k2, p1, p2, 0.0]),
                'T_camera_ref': np.linalg.inv(T_ref_camera),
                'rms': theirs['rms_px'],
                'std': np.asarray(theirs['std_px']),
                'outliers': theirs['outliers'],
                'T_ref_chart': [np.asarray(T) for T in theirs['T_ref_frame']],
            }
    started = time.perf_counter()
    opencv = opencv_rig(chart, views, sizes, list(NAMES))
    seconds['opencv'] = time.perf_counter() - started
    solutions['opencv'] = {
        n: {'K': c.K, 'D': c.D, 'T_camera_ref': np.linalg.inv(c.T_base_camera)}
        for n, c in opencv.items()
    }
    return solutions, seconds, ranges, ours.uncertainty.baseline_std_m, focal


def baseline(solution):
    """Distance between the left and right optical centres [m]."""
    centres = [np.linalg.inv(solution[n]['T_camera_ref'])[:3, 3] for n in NAMES]
    return float(np.linalg.norm(centres[1] - centres[0]))


def _std(solution):
    if 'std' not in solution:
        return ''
    return f'{solution["std"].max():.2f} / {np.median(solution["std"]):.2f}'


def _rms(solution):
    if 'rms' not in solution:
        return ''
    outliers = f' ({solution["outliers"]} outliers)' if 'outliers' in solution else ''
    return f'{solution["rms"]:.3f}{outliers}'


def sample_table(mrcal):
    """Markdown lines and a JSON-able summary: OpenCV's 13 sample pairs."""
    views, sizes = sample_views()
    solutions, seconds, ranges, baseline_std, focal = calibrate_three(
        views, sizes, SAMPLE_BOARD, mrcal
    )
    lines = [
        "OpenCV's 13 stereo sample pairs (640 x 480, 9 x 6 corners, 0.025 m), calib_node's "
        f'corners of all 13 pairs; working range {ranges[0]:.3f} / {ranges[1]:.3f} m (left / '
        'right: the median corner depth). Projection std: sqrt(trace) of the 2 x 2 covariance '
        f'of a point at the working range, over a {GRID[0]} x {GRID[1]} grid spanning the '
        'image; ours: residual variance RSS / (n - p), the chart poses part of the covariance, '
        "the point held fixed to the charts (as mrcal's); mrcal: its 'mean-pcam' method (the "
        'point fixed relative to the observed boards), observed-pixel noise from its residuals. '
        'mrcal: LENSMODEL_OPENCV4, flat board, its light regularisation; outlier rejection '
        'as by default, and off ("all corners").',
        '',
        '| camera | tool | fx [px] | fy [px] | cx [px] | cy [px] | RMS [px] | '
        'projection std worst / median [px] |',
        '|---|---|---|---|---|---|---|---|',
    ]
    for name in NAMES:
        for tool in TOOLS:
            s = solutions[tool][name]
            K = s['K']
            lines.append(
                f'| {name} | {tool} | {K[0, 0]:.2f} | {K[1, 1]:.2f} | {K[0, 2]:.2f} | '
                f'{K[1, 2]:.2f} | {_rms(s)} | {_std(s)} |'
            )
    baselines = {t: baseline(solutions[t]) for t in TOOLS}
    lines += [
        '',
        '| | ' + ' | '.join(TOOLS) + ' |',
        '|---|' + '---|' * len(TOOLS),
        '| baseline [m] | ' + ' | '.join(f'{baselines[t]:.5f}' for t in TOOLS) + ' |',
        '| time [s] | '
        + ' | '.join(
            f'{seconds[t]:.2f}' + (' (process)' if t in MRCAL_RUNS else '') for t in TOOLS
        )
        + ' |',
        '',
    ]
    ours = solutions['ours']
    for tool in TOOLS[1:]:
        theirs = solutions[tool]
        lines.append(
            f'Ours relative to {tool}: '
            + ', '.join(
                f'{n} fx {ours[n]["K"][0, 0] / theirs[n]["K"][0, 0] - 1:+.3%}, '
                f'fy {ours[n]["K"][1, 1] / theirs[n]["K"][1, 1] - 1:+.3%}'
                for n in NAMES
            )
            + f', baseline {baselines["ours"] / baselines[tool] - 1:+.3%}.'
        )
    lines.append(f'Our baseline std: {baseline_std * 1e3:.3f} mm.')
    cross, counts = cross_validation(views, sizes, SAMPLE_BOARD, mrcal, ranges, focal)
    lines += [
        '',
        'Cross-validation: the views split into two halves that cover the image alike, each '
        'calibrated apart, the two solutions compared at the working range (worst / median '
        'over the grid [px]); ours aligns the halves by one rigid transform for the rig, '
        "mrcal's projection_diff by one per camera.",
        '',
        '| camera | tool | views | cross-validation worst / median [px] |',
        '|---|---|---|---|',
        *cross_validation_lines(cross, counts),
    ]
    summary = {
        'intrinsics': {
            t: {n: solutions[t][n]['K'][[0, 1, 0, 1], [0, 1, 2, 2]].tolist() for n in NAMES}
            for t in TOOLS
        },
        'baselines': baselines,
        'ranges': ranges,
    }
    return lines, summary


def rig_table(count, mrcal):
    """Markdown lines and rows: ``count`` generated stereo rigs (seeds 0..count-1, one
    rendering each) against the truth."""
    lines = [
        f'{count} generated stereo rigs (seeds 0..{count - 1}; `rig_generator.draw_rig(seed, '
        "('left', 'right'))`, rendered once), the same corners for every tool. Errors of fx, "
        'fy, cx, cy against the truth [px]; true projection error: where the calibrated '
        'camera projects the points the true camera sees on the grid at the working range, '
        "both in their own left camera's frame (worst / median over the grid [px]); held "
        'to the charts: the same, each point carried by the true chart poses into the '
        "charts and back out by the tool's own, averaged over the charts (the gauge of ours "
        "and mrcal's uncertainty; OpenCV's rig gives no chart poses); predicted: the tool's "
        'own projection std (worst / median). Cross-validation: as on the sample pairs, '
        "beside the full calibration's true error held to the charts.",
        '',
        '| rig | camera | tool | fx err | fy err | cx err | cy err | true projection error | '
        'held to the charts | predicted | baseline err [um] |',
        '|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    cross_lines = [
        '',
        '| rig | camera | tool | views | cross-validation worst / median [px] |',
        '|---|---|---|---|---|',
    ]
    rows = []
    for seed in range(count):
        rig = draw_rig(seed, NAMES)
        sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
        views = detect_views(rig, render_rig(rig, seed))
        board = Board(rig.rows, rig.cols, rig.spacing)
        solutions, _, ranges, _, focal = calibrate_three(views, sizes, board, mrcal)
        cross, counts = cross_validation(views, sizes, board, mrcal, ranges, focal)
        cross_lines += [f'| {seed} ' + line for line in cross_validation_lines(cross, counts)]
        T_base_left = rig.cameras['left'].T_base_camera
        T_left_chart = [
            np.linalg.inv(T_base_left) @ T for T, v in zip(rig.T_base_chart, views) if v
        ]
        truth = {
            n: {'K': c.K, 'T_camera_ref': np.linalg.inv(c.T_base_camera) @ T_base_left}
            for n, c in rig.cameras.items()
        }
        true_baseline = baseline(truth)
        for name, range_m in zip(NAMES, ranges):
            true = rig.cameras[name]
            for tool in TOOLS:
                s = solutions[tool][name]
                errors = np.abs(s['K'] - true.K)[[0, 1, 0, 1], [0, 1, 2, 2]]
                true_in_frame = camera_in_frame(
                    true.K, true.D, truth[name]['T_camera_ref'], sizes[name]
                )
                calibrated = camera_in_frame(s['K'], s['D'], s['T_camera_ref'], sizes[name])
                projection = true_projection_error(true_in_frame, calibrated, range_m)
                held = ''
                if 'T_ref_chart' in s:
                    fixed = true_projection_error_chart_fixed(
                        true_in_frame, T_left_chart, calibrated, s['T_ref_chart'], range_m
                    )
                    held = f'{fixed.max():.2f} / {np.median(fixed):.2f}'
                baseline_error = abs(baseline(solutions[tool]) - true_baseline) * 1e6
                lines.append(
                    f'| {seed} | {name} | {tool} | '
                    + ' | '.join(f'{e:.3f}' for e in errors)
                    + f' | {projection.max():.2f} / {np.median(projection):.2f} | {held} | '
                    f'{_std(s)} | {baseline_error:.1f} |'
                )
                rows.append(
                    {
                        'rig': seed,
                        'camera': name,
                        'tool': tool,
                        'errors': errors.tolist(),
                        'true_projection_px': [
                            float(projection.max()),
                            float(np.median(projection)),
                        ],
                        'baseline_error_um': baseline_error,
                    }
                )
    return lines + cross_lines, rows
