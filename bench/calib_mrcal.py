"""calib_node against mrcal (and OpenCV) on the same chessboard corners: OpenCV's 13
stereo sample pairs (Debian's opencv-doc), corners found by calib_node's detector, all 13
pairs calibrated by

- ours: ``bundle.bundle_adjust_selected`` (the handheld core, plumb_bob k1 k2 p1 p2 by BIC),
- mrcal: ``mrcal-calibrate-cameras`` on a corners file of those corners (LENSMODEL_OPENCV4 =
  k1 k2 p1 p2, the board taken as flat: ``--skip-calobject-warp-solve``; mrcal's defaults
  otherwise: its light regularisation and outlier rejection),
- OpenCV: calibrateCamera + stereoCalibrate (``calib_rigs.opencv_rig``).

Per camera fx, fy, cx, cy, RMS, baseline, and the projection uncertainty at the working
range (the median depth of the corners in our fit) over the same 16 x 12 pixel grid:
ours (``uncertainty.rig_uncertainty``) beside mrcal's own (``mrcal.projection_uncertainty``,
run by ``mrcal_peer.py``), both as sqrt(trace) of the 2 x 2 covariance.

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

import cv2
import numpy as np
from calib_rigs import opencv_rig

from calib_node.bundle import bundle_adjust_selected
from calib_node.chart_detection import chart_points, detect_chessboard
from calib_node.uncertainty import GRID, image_grid
from vgm_common.sample_data import STEREO_CALIBRATION_IDS, opencv_sample_dir

ROWS, COLS, SPACING = 6, 9, 0.025  # the sample photographs' chart
NAMES = ('left', 'right')
PEER = Path(__file__).resolve().parent / 'mrcal_peer.py'
# mrcal as it runs by default (outliers rejected) and on every corner, as ours and OpenCV.
MRCAL_RUNS = {'mrcal': (), 'mrcal, all corners': ('--skip-outlier-rejection',)}
TOOLS = ('ours', *MRCAL_RUNS, 'opencv')


def sample_views():
    """([{name: (54, 2) corners}] per pair, {name: (width, height)}, image directory)."""
    directory = Path(opencv_sample_dir())
    views, sizes = [], {}
    for index in STEREO_CALIBRATION_IDS:
        view = {}
        for name in NAMES:
            grey = cv2.imread(str(directory / f'{name}{index:02d}.jpg'), cv2.IMREAD_GRAYSCALE)
            sizes[name] = grey.shape[::-1]
            view[name] = detect_chessboard(grey, ROWS, COLS).corners
        views.append(view)
    return views, sizes, directory


def write_corners(path, views):
    """mrcal's corners file (vnlog ``filename x y level``), our corners in the chart's
    row-major order (index r * COLS + c: mrcal's object-width-n = COLS)."""
    lines = ['# filename x y level']
    for index, view in zip(STEREO_CALIBRATION_IDS, views):
        for name in NAMES:
            lines += [f'{name}{index:02d}.jpg {u:.6f} {v:.6f} 0' for u, v in view[name]]
    Path(path).write_text('\n'.join(lines) + '\n')


def run_mrcal(views, directory, pixels, ranges, python, path, focal, options=()):
    """mrcal-calibrate-cameras + mrcal_peer.py in a temporary directory: the peer's JSON
    per camera and the calibration's wall time [s]."""
    environment = dict(os.environ, PYTHONPATH=path)
    with tempfile.TemporaryDirectory(prefix='calib-mrcal-') as work:
        corners = Path(work) / 'corners.vnl'
        write_corners(corners, views)
        started = time.perf_counter()
        subprocess.run(
            [
                python,
                str(Path(path) / 'bin' / 'mrcal-calibrate-cameras'),
                '--corners-cache',
                str(corners),
                '--image-directory',
                str(directory),
                '--lensmodel',
                'LENSMODEL_OPENCV4',
                '--focal',
                str(focal),
                '--object-spacing',
                str(SPACING),
                '--object-width-n',
                str(COLS),
                '--object-height-n',
                str(ROWS),
                '--skip-calobject-warp-solve',
                *options,
                '--outdir',
                work,
                *[f'{name}*.jpg' for name in NAMES],
            ],
            env=environment,
            check=True,
            capture_output=True,
            text=True,
            timeout=600,
        )
        seconds = time.perf_counter() - started
        request = {
            'models': [str(Path(work) / f'camera-{i}.cameramodel') for i in range(len(NAMES))],
            'pixels': [p.tolist() for p in pixels],
            'ranges': ranges,
        }
        answer = subprocess.run(
            [python, str(PEER), json.dumps(request)],
            env=environment,
            check=True,
            capture_output=True,
            text=True,
            timeout=600,
        )
    return json.loads(answer.stdout), seconds


def _distance(T_a, T_b):
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def mrcal_table(python, path):
    """Markdown lines and a JSON-able summary of the three calibrations."""
    views, sizes, directory = sample_views()
    chart = chart_points(ROWS, COLS, SPACING)
    started = time.perf_counter()
    ours = bundle_adjust_selected(chart, views, sizes, None, NAMES)
    ours_seconds = time.perf_counter() - started
    started = time.perf_counter()
    opencv = opencv_rig(chart, views, sizes, list(NAMES))
    opencv_seconds = time.perf_counter() - started
    pixels = [image_grid(sizes[n], GRID) for n in NAMES]
    ranges = [ours.uncertainty.range_m[n] for n in NAMES]
    focal = float(np.mean([ours.fits[n].K[0, 0] for n in NAMES]))
    peers = {
        tool: run_mrcal(views, directory, pixels, ranges, python, path, focal, options)
        for tool, options in MRCAL_RUNS.items()
    }

    rows: dict[str, dict[str, dict[str, float]]] = {tool: {} for tool in TOOLS}
    for c, name in enumerate(NAMES):
        fit = ours.fits[name]
        rows['ours'][name] = {
            'fx': fit.K[0, 0],
            'fy': fit.K[1, 1],
            'cx': fit.K[0, 2],
            'cy': fit.K[1, 2],
            'rms': fit.rms_px,
            'std_worst': ours.uncertainty.worst_px[name],
            'std_median': ours.uncertainty.median_px[name],
        }
        for tool, (peer, _) in peers.items():
            theirs = peer[c]
            fx, fy, cx, cy = theirs['intrinsics'][:4]
            rows[tool][name] = {
                'fx': fx,
                'fy': fy,
                'cx': cx,
                'cy': cy,
                'rms': theirs['rms_px'],
                'std_worst': max(theirs['std_px']),
                'std_median': float(np.median(theirs['std_px'])),
                'outliers': theirs['outliers'],
            }
        camera = opencv[name]
        rows['opencv'][name] = {
            'fx': camera.K[0, 0],
            'fy': camera.K[1, 1],
            'cx': camera.K[0, 2],
            'cy': camera.K[1, 2],
        }
    baselines = {
        'ours': _distance(ours.fits['left'].T_base_camera, ours.fits['right'].T_base_camera),
        **{
            tool: float(np.linalg.norm(np.asarray(peer[1]['T_ref_camera'])[3]))
            for tool, (peer, _) in peers.items()
        },
        'opencv': _distance(opencv['left'].T_base_camera, opencv['right'].T_base_camera),
    }
    lines = [
        f"OpenCV's 13 stereo sample pairs (640 x 480, 9 x 6 corners, 0.025 m), calib_node's "
        f'corners of all 13 pairs; working range {ranges[0]:.3f} / {ranges[1]:.3f} m (left / '
        'right: the median corner depth). Projection std: sqrt(trace) of the 2 x 2 covariance '
        f'of a point at the working range, over a {GRID[0]} x {GRID[1]} grid spanning the '
        'image; ours: residual variance RSS / (n - p), the chart poses part of the covariance; '
        "mrcal: its 'mean-pcam' method, observed-pixel noise from its residuals. mrcal: "
        'LENSMODEL_OPENCV4, flat board, its regularisation and outlier rejection.',
        '',
        '| camera | tool | fx [px] | fy [px] | cx [px] | cy [px] | RMS [px] | '
        'projection std worst / median [px] |',
        '|---|---|---|---|---|---|---|---|',
    ]
    for name in NAMES:
        for tool in TOOLS:
            row = rows[tool][name]
            rms = f'{row["rms"]:.3f}' if 'rms' in row else ''
            if 'outliers' in row:
                rms += f' ({row["outliers"]} outliers)'
            std = f'{row["std_worst"]:.2f} / {row["std_median"]:.2f}' if 'std_worst' in row else ''
            lines.append(
                f'| {name} | {tool} | {row["fx"]:.2f} | {row["fy"]:.2f} | {row["cx"]:.2f} | '
                f'{row["cy"]:.2f} | {rms} | {std} |'
            )
    lines += [
        '',
        '| | ' + ' | '.join(TOOLS) + ' |',
        '|---|' + '---|' * len(TOOLS),
        '| baseline [m] | ' + ' | '.join(f'{baselines[t]:.5f}' for t in TOOLS) + ' |',
        f'| time [s] | {ours_seconds:.2f} | '
        + ' | '.join(f'{peers[t][1]:.2f} (process)' for t in MRCAL_RUNS)
        + f' | {opencv_seconds:.2f} |',
        '',
        *[
            f'Ours relative to {tool}: '
            + ', '.join(
                f'{n} fx {rows["ours"][n]["fx"] / rows[tool][n]["fx"] - 1:+.3%}, '
                f'fy {rows["ours"][n]["fy"] / rows[tool][n]["fy"] - 1:+.3%}'
                for n in NAMES
            )
            + f', baseline {baselines["ours"] / baselines[tool] - 1:+.3%}.'
            for tool in (*MRCAL_RUNS, 'opencv')
        ],
        f'Our baseline std: {ours.uncertainty.baseline_std_m * 1e3:.3f} mm.',
    ]
    return lines, {'cameras': rows, 'baselines': baselines, 'ranges': ranges}
