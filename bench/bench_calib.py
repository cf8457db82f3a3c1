#!/usr/bin/env python3
"""calib_node's algorithms against the thesis's chapter 4 (ALGORITHMS.md §3).

1. Table 4.3: the 512 control points and the true cameras / bounds of Tables 4.1 / 4.2,
   noise-free: GA, GA + network (the thesis), ours (LM in the seed model from the GA, and
   from the closed-form DLT), OpenCV (calibrateCamera + stereoCalibrate). Errors of the
   identifiable quantities (fx = f Nx, fy = f Ny, kappa = k f^2, u0, v0, R, T), reprojection
   RMS, run time; beside the thesis's printed values.
2. Figures 4.3-4.7: the same at Gaussian pixel noise sigma = 0 .. 3 px (mean absolute error
   over seeded trials; fewer trials for the slow GA stages, see --ga-trials).
3. The node's setting: the default scenario's three plumb_bob cameras and 10 chart poses,
   exact corners plus sigma = 0 / 0.5 px noise, methods lm / opencv / lxpm_ga: relative
   errors of fx, fy, baseline; time.
4. Generated rigs (``calib_rigs.py``): rendered charts through random rigs,
   stage and handheld calibration against OpenCV on the same images (``--rigs N``).
5. ``--uncertainty N [--draws D --supersample S]`` (alone): the predicted projection
   uncertainty against the true projection error on N generated rigs, each rendered D
   times with S x S rays a pixel (4 by default).
6. ``--mrcal [--mrcal-rigs N]`` (alone): OpenCV's 13 stereo sample pairs and N generated
   stereo rigs calibrated on the same corners by calib_node, mrcal (a separate process:
   ``--mrcal-python``, ``--mrcal-path``; set-up in ``calib_mrcal.py``) and OpenCV; mrcal.md.
7. ``--gauge N [--draws D --sigma S]`` (alone): the projection uncertainty held in the left
   camera's frame and held to the charts, each against the true error in its gauge, on N
   generated stereo rigs; gauge.md.

    source ros2_ws/install/setup.bash && .venv/bin/python bench/bench_calib.py
    (options: --trials 20 --ga-trials 3 --sigmas 0 0.5 1 1.5 2 2.5 3 --rigs 10)
Writes bench/results/calib/calib.md, calib.json and PNG plots.
"""

import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # see calib_node/__init__.py
import argparse  # noqa: E402
import json
import time
from pathlib import Path

import numpy as np
from vgm_evaluation.bench_report import save_figure, write_results

from calib_node.calibrate import calibrate_rig
from calib_node.chart_detection import chart_points
from calib_node.lxpm_ga import lxpm_ga, stereo_objective
from calib_node.seed_calibration import division_init, dlt_camera, opencv_reference, refine_seed_lm
from calib_node.seed_camera import (
    LEFT_BOUNDS,
    LEFT_TRUTH,
    RIGHT_BOUNDS,
    RIGHT_TRUTH,
    identifiable,
    project_seed,
    seed_stereo_observations,
)
from calib_node.thesis import network_refine
from sensor_sim.scenario import load_scenario, resolve_scenario_path

RESULTS = Path(__file__).resolve().parent / 'results' / 'calib'
POINTS, CLEAN_PIXELS = seed_stereo_observations()  # noise-free
TRUTH = (LEFT_TRUTH, RIGHT_TRUTH)
IMAGE_SIZES = ((320, 240), (512, 384))  # the ch4_calibration scenario's cameras
QUANTITIES = ('fx', 'fy', 'kappa', 'u0', 'v0', 'R', 'T')
# Table 4.3 [T] as identifiable products (ALGORITHMS.md §3.7): GA, GA-ANN per camera.
THESIS = {
    'left': {
        'GA': {
            'fx': 1825.8,
            'fy': 1798.9,
            'kappa': 11.526,
            'u0': 21.0,
            'v0': 19.0,
            'T': (64.7812, 34.7845, 1249.9474),
            'angles': (0.0003, 0.0052, 0.0005),
        },
        'GA+network': {
            'fx': 1798.9,
            'fy': 1798.9,
            'kappa': 11.526,
            'u0': 20.0,
            'v0': 19.0,
            'T': (62.1313, 35.0, 1220.0),
            'angles': (0.0003, 0.0009, 0.0005),
        },
    },
    'right': {
        'GA': {
            'fx': 3423.9,
            'fy': 3232.3,
            'kappa': 63.462,
            'u0': 240.0,
            'v0': 197.0,
            'T': (-36.8733, 37.2688, 1211.6814),
            'angles': (-1.9023, 0.2252, 0.1452),
        },
        'GA+network': {
            'fx': 3423.9,
            'fy': 3304.2,
            'kappa': 63.462,
            'u0': 244.0,
            'v0': 195.0,
            'T': (-36.9, 37.56, 1211.0),
            'angles': (-1.9029, 0.2, 0.15),
        },
    },
}

# Table 4.3 [T] as printed, PARAM_NAMES order (u0, v0, Nx, Ny, f, k, alpha, beta, gamma, T).
THESIS_PARAMS = {
    ('left', 'GA'): [
        21,
        19,
        204,
        201,
        8.9499,
        0.1439,
        0.0003,
        0.0052,
        0.0005,
        64.7812,
        34.7845,
        1249.9474,
    ],
    ('left', 'GA+network'): [
        20,
        19,
        201,
        201,
        8.9499,
        0.1439,
        0.0003,
        0.0009,
        0.0005,
        62.1313,
        35.0,
        1220,
    ],
    ('right', 'GA'): [
        240,
        197,
        143,
        135,
        23.9432,
        0.1107,
        -1.9023,
        0.2252,
        0.1452,
        -36.8733,
        37.2688,
        1211.6814,
    ],
    ('right', 'GA+network'): [
        244,
        195,
        143,
        138,
        23.9432,
        0.1107,
        -1.9029,
        0.2,
        0.15,
        -36.9,
        37.56,
        1211,
    ],
}


def rotation_error(R, R_true):
    return float(np.arccos(np.clip((np.trace(R @ R_true.T) - 1) / 2, -1, 1)))


def errors_of(ident, truth):
    """Absolute errors of the identifiable quantities of one camera."""
    want = identifiable(truth)
    out = {
        name: abs(float(getattr(ident, name)) - float(getattr(want, name)))
        for name in ('fx', 'fy', 'kappa', 'u0', 'v0')
    }
    out['R'] = rotation_error(np.asarray(ident.R), want.R)
    out['T'] = float(np.linalg.norm(np.asarray(ident.T) - want.T))
    return out


def rms(params, pixels):
    return float(
        np.sqrt(np.mean(np.sum((project_seed(params[None], POINTS)[0] - pixels) ** 2, axis=1)))
    )


def seed_params_from_dlt(pixels):
    """DLT camera as seed parameters with f = 1 and k = 0 (ours, closed-form start)."""
    from scipy.spatial.transform import Rotation

    K, R, t = dlt_camera(POINTS, pixels)
    return np.r_[
        K[0, 2], K[1, 2], K[0, 0], K[1, 1], 1.0, 0.0, Rotation.from_matrix(R).as_euler('ZYX'), t
    ]


def opencv_identifiable(K, R, T):
    class Ident:  # the seed's Identifiable fields; OpenCV's polynomial has no kappa
        pass

    ident = Ident()
    ident.fx, ident.fy, ident.u0, ident.v0 = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ident.kappa, ident.R, ident.T = np.nan, R, T
    return ident


def trial(sigma, seed, run_ga=True, extras=False):
    """One synthetic trial: {method: {'left'/'right': errors, 'rms': [l, r], 'time': s}}.

    ``extras``: also the DLT + LM start (the old "ours") and the unstructured network.
    """
    rng = np.random.default_rng(seed)
    pixels = CLEAN_PIXELS + sigma * rng.standard_normal(CLEAN_PIXELS.shape)
    out = {}

    def record(method, params, seconds, **more):
        out[method] = {'time': seconds, 'rms': [rms(p, uv) for p, uv in zip(params, pixels)]}
        out[method].update(more)
        for name, p, truth in zip(('left', 'right'), params, TRUTH):
            out[method][name] = errors_of(identifiable(p), truth)

    # The reference optimum: LM started at the truth. A method whose final cost is above
    # it has stopped in a wrong minimum.
    *_, best = refine_seed_lm(*TRUTH, POINTS, *pixels)
    best_rms = (best.rms_left, best.rms_right)

    def wrong_minima(rms_pair):
        return int(sum(r > b * (1 + 1e-6) + 1e-9 for r, b in zip(rms_pair, best_rms)))

    if run_ga:
        bounds = np.concatenate([LEFT_BOUNDS, RIGHT_BOUNDS])
        started = time.perf_counter()
        result = lxpm_ga(
            stereo_objective(POINTS, *pixels),
            bounds[:, 0],
            bounds[:, 1],
            np.random.default_rng(seed),
        )
        ga_time = time.perf_counter() - started
        ga = (result.best[:12], result.best[12:])
        record('GA', ga, ga_time)
        started = time.perf_counter()
        nets = [network_refine(p, POINTS, uv) for p, uv in zip(ga, pixels)]
        record(
            'GA+network',
            [n[0] for n in nets],
            ga_time + time.perf_counter() - started,
            accepted=[bool(n[1].accepted) for n in nets],
            network_rms=[float(n[1].rms_after) for n in nets],
        )
        if extras:
            started = time.perf_counter()
            free = [
                network_refine(p, POINTS, uv, weights='free', accept='always')[0]
                for p, uv in zip(ga, pixels)
            ]
            record(
                'GA+network (free weights, always)', free, ga_time + time.perf_counter() - started
            )
        started = time.perf_counter()
        left, right, info = refine_seed_lm(*ga, POINTS, *pixels)
        record(
            'GA+LM',
            (left, right),
            ga_time + time.perf_counter() - started,
            wrong=wrong_minima((info.rms_left, info.rms_right)),
        )
    started = time.perf_counter()
    starts = [division_init(POINTS, uv)[0] for uv in pixels]
    left, right, info = refine_seed_lm(*starts, POINTS, *pixels)
    record(
        'ours: division init+LM',
        (left, right),
        time.perf_counter() - started,
        wrong=wrong_minima((info.rms_left, info.rms_right)),
    )
    if extras:
        started = time.perf_counter()
        left, right, info = refine_seed_lm(
            *(seed_params_from_dlt(uv) for uv in pixels), POINTS, *pixels
        )
        record(
            'old: DLT+LM',
            (left, right),
            time.perf_counter() - started,
            wrong=wrong_minima((info.rms_left, info.rms_right)),
        )
    started = time.perf_counter()
    ref = opencv_reference(POINTS, *pixels, *IMAGE_SIZES)
    seconds = time.perf_counter() - started
    out['OpenCV'] = {'time': seconds, 'rms': [ref.rms_left, ref.rms_right]}
    for name, K, R, T, truth in (
        ('left', ref.K_left, ref.R_left, ref.T_left, LEFT_TRUTH),
        ('right', ref.K_right, ref.R_right, ref.T_right, RIGHT_TRUTH),
    ):
        out['OpenCV'][name] = errors_of(opencv_identifiable(K, R, T), truth)
    return out


def fmt(value):
    if value is None or not np.isfinite(value):
        return 'n/a'
    if value == 0:
        return '0'
    return f'{value:.3g}' if 1e-3 <= abs(value) < 1e5 else f'{value:.2e}'


def thesis_errors(camera, stage):
    printed = THESIS[camera][stage]
    truth = identifiable(TRUTH[camera == 'right'])
    from vgm_common.geometry import rpy_to_matrix

    alpha, beta, gamma = printed['angles']
    return {
        'fx': abs(printed['fx'] - truth.fx),
        'fy': abs(printed['fy'] - truth.fy),
        'kappa': abs(printed['kappa'] - truth.kappa),
        'u0': abs(printed['u0'] - truth.u0),
        'v0': abs(printed['v0'] - truth.v0),
        'R': rotation_error(rpy_to_matrix(gamma, beta, alpha), truth.R),
        'T': float(np.linalg.norm(np.array(printed['T']) - truth.T)),
    }


def table_43(result):
    lines = [
        '| camera | method | '
        + ' | '.join(f'{q} err' for q in QUANTITIES)
        + ' | RMS [px] | time [s] |',
        '|' + '---|' * (len(QUANTITIES) + 4),
    ]
    for camera in ('left', 'right'):
        for stage in ('GA', 'GA+network'):
            e = thesis_errors(camera, stage)
            clean = project_seed(TRUTH[camera == 'right'][None], POINTS)[0]
            thesis_rms = rms(np.array(THESIS_PARAMS[camera, stage], dtype=float), clean)
            lines.append(
                f'| {camera} | thesis {stage} (Table 4.3) | '
                + ' | '.join(fmt(e[q]) for q in QUANTITIES)
                + f' | {fmt(thesis_rms)} | n/a |'
            )
        for method, data in result.items():
            e = data[camera]
            lines.append(
                f'| {camera} | {method} | '
                + ' | '.join(fmt(e[q]) for q in QUANTITIES)
                + f' | {fmt(data["rms"][camera == "right"])} | {data["time"]:.2f} |'
            )
    return lines


def sweep(sigmas, trials, ga_trials):
    results = {}
    for sigma in sigmas:
        runs = [trial(sigma, 1000 + s, run_ga=s < ga_trials) for s in range(trials)]
        summary = {}
        for method in runs[0]:
            method_runs = [r[method] for r in runs if method in r]
            summary[method] = {'trials': len(method_runs)}
            if 'wrong' in method_runs[0]:
                summary[method]['wrong_minima'] = int(sum(r['wrong'] for r in method_runs))
            if 'accepted' in method_runs[0]:
                summary[method]['network_accepted'] = int(
                    sum(sum(r['accepted']) for r in method_runs)
                )
            summary[method]['time'] = float(np.mean([r['time'] for r in method_runs]))
            for camera in ('left', 'right'):
                summary[method][camera] = {
                    q: [
                        float(np.mean([r[camera][q] for r in method_runs])),
                        float(np.std([r[camera][q] for r in method_runs])),
                    ]
                    for q in QUANTITIES
                }
        results[sigma] = summary
        print(
            f'sigma {sigma}: '
            + ', '.join(f'{m} fx err L {s["left"]["fx"][0]:.3g}' for m, s in summary.items()),
            flush=True,
        )
    return results


def plot_sweep(results, directory):
    try:
        import matplotlib

        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        print('matplotlib not available: no plots')
        return []
    figures = {
        'fig4_3_focal_kappa': ('fx', 'kappa'),
        'fig4_4_fy': ('fx', 'fy'),
        'fig4_5_principal_point': ('u0', 'v0'),
        'fig4_6_translation': ('T',),
        'fig4_7_rotation': ('R',),
    }
    labels = {
        'fx': 'f Nx [px]',
        'fy': 'f Ny [px]',
        'kappa': 'k f^2',
        'u0': 'u0 [px]',
        'v0': 'v0 [px]',
        'T': '|T error| [unit]',
        'R': 'rotation error [rad]',
    }
    sigmas = sorted(results)
    written = []
    for name, quantities in figures.items():
        fig, axes = plt.subplots(
            1, 2 * len(quantities), figsize=(6 * len(quantities), 3.6), squeeze=False
        )
        column = 0
        for q in quantities:
            for camera in ('left', 'right'):
                ax = axes[0, column]
                column += 1
                for method in results[sigmas[0]]:
                    # log axis: exact (0) errors drawn at 1e-14
                    means = [max(results[s][method][camera][q][0], 1e-14) for s in sigmas]
                    ax.plot(sigmas, means, marker='o', label=method)
                ax.set_yscale('log')
                ax.set_xlabel('pixel noise sigma [px]')
                ax.set_title(f'{camera}: {labels[q]}')
                ax.grid(True, alpha=0.3)
        axes[0, 0].legend(fontsize=7)
        fig.tight_layout()
        written.append(save_figure(fig, directory / f'{name}.png', dpi=90).name)
    return written


def scenario_rig(sigma, seed):
    """The default scenario's cameras and chart poses, exact corners + noise."""
    scenario = load_scenario(resolve_scenario_path('default'))
    calibration = scenario.calibration
    chart = chart_points(calibration.rows, calibration.cols, calibration.spacing)
    rng = np.random.default_rng(seed)
    observations = {}
    for name, camera in scenario.cameras.items():
        points, pixels = [], []
        for T in calibration.T_base_chart:
            base = chart @ T[:3, :3].T + T[:3, 3]
            uv, depth = camera.project(base)
            if np.all(depth > 0) and np.all((uv >= 0) & (uv < [camera.width, camera.height])):
                points.append(base)
                pixels.append(uv + sigma * rng.standard_normal(uv.shape))
        observations[name] = (
            np.concatenate(points),
            np.concatenate(pixels),
            (camera.width, camera.height),
        )
    return scenario.cameras, observations


def scenario_table(trials):
    lines = [
        '| method | sigma [px] | fx rel err (max over cameras) | fy rel err | '
        'baseline rel err | max RMS [px] | fx rel std predicted (max) | time [s] |',
        '|---|---|---|---|---|---|---|---|',
    ]
    rows = []
    for method in ('lm', 'opencv', 'lxpm_ga'):
        for sigma in (0.0, 0.5):
            n = 1 if (sigma == 0 or method == 'lxpm_ga') else trials
            stats = []
            for seed in range(n):
                truth, observations = scenario_rig(sigma, seed)
                result = calibrate_rig(observations, method, seed)
                fx = max(abs(f.K[0, 0] / truth[c].K[0, 0] - 1) for c, f in result.fits.items())
                fy = max(abs(f.K[1, 1] / truth[c].K[1, 1] - 1) for c, f in result.fits.items())
                baseline = np.linalg.norm(
                    result.fits['left'].T_base_camera[:3, 3]
                    - result.fits['right'].T_base_camera[:3, 3]
                )
                true_baseline = np.linalg.norm(
                    truth['left'].centre_base - truth['right'].centre_base
                )
                # the LM / OpenCV covariance: the statistical floor of fx at this noise
                predicted = max(
                    (f.std.get('fx', np.nan) / f.K[0, 0] for f in result.fits.values()),
                    default=np.nan,
                )
                stats.append(
                    (
                        fx,
                        fy,
                        abs(baseline / true_baseline - 1),
                        max(f.rms_px for f in result.fits.values()),
                        predicted,
                        result.seconds,
                    )
                )
            mean = np.mean(stats, axis=0)
            rows.append(
                {
                    'method': method,
                    'sigma': sigma,
                    'trials': n,
                    'fx_rel': mean[0],
                    'fy_rel': mean[1],
                    'baseline_rel': mean[2],
                    'rms': mean[3],
                    'fx_rel_std_predicted': mean[4],
                    'time': mean[5],
                }
            )
            lines.append(
                f'| {method} | {sigma} ({n} trials) | {fmt(mean[0])} | '
                f'{fmt(mean[1])} | {fmt(mean[2])} | {fmt(mean[3])} | '
                f'{fmt(mean[4])} | {mean[5]:.2f} |'
            )
            print(lines[-1], flush=True)
    return lines, rows


def uncertainty_check(rigs, draws, supersample):
    """Predicted projection uncertainty vs the true projection error on generated rigs:
    uncertainty.md and uncertainty.json."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from calib_rigs import uncertainty_table

    started = time.perf_counter()
    lines, rows = uncertainty_table(rigs, draws, supersample)
    lines = [
        '# calib_node: predicted uncertainty against the truth',
        '',
        f'Command: `source ros2_ws/install/setup.bash && .venv/bin/python '
        f'bench/bench_calib.py --uncertainty {rigs} --draws {draws} '
        f'--supersample {supersample}` '
        f'({time.perf_counter() - started:.0f} s).',
        '',
        *lines,
    ]
    write_results(RESULTS, 'uncertainty', lines, rows)


def gauge_check(rigs, draws, sigma):
    """The projection uncertainty held in the left camera's frame and held to the charts,
    each against the true error in its own gauge: handheld bundle adjustment of generated
    stereo rigs (exact corners plus Gaussian noise ``sigma`` [px], ``draws`` each);
    gauge.md."""
    from vgm_evaluation.rig_generator import (
        camera_in_frame,
        draw_rig,
        true_corners,
        true_projection_error,
        true_projection_error_chart_fixed,
    )

    from calib_node.bundle import bundle_adjust
    from calib_node.chart_detection import chart_points

    started = time.perf_counter()
    names = ('left', 'right')
    lines = [
        '| rig | views | camera | left frame: predicted / true, median | worst | '
        'held to the charts: predicted / true, median | worst |',
        '|---|---|---|---|---|---|---|',
    ]
    rows = []
    for seed in range(rigs):
        rig = draw_rig(seed, names)
        chart = chart_points(rig.rows, rig.cols, rig.spacing)
        sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
        T_base_left = rig.cameras['left'].T_base_camera
        truth = {n: np.linalg.inv(c.T_base_camera) @ T_base_left for n, c in rig.cameras.items()}
        T_left_chart = [np.linalg.inv(T_base_left) @ T for T in rig.T_base_chart]
        grids = {n: {k: [] for k in ('left', 'true left', 'charts', 'true charts')} for n in names}
        for draw in range(draws):
            rng = np.random.default_rng(1000 * seed + draw)
            views = [
                {n: uv + rng.normal(0.0, sigma, uv.shape) for n, uv in view.items()}
                for view in true_corners(rig)
            ]
            # Deterministic: the same solution twice, its uncertainty in the two gauges.
            held = bundle_adjust(chart, views, sizes, fit_tangential=False)
            floating = bundle_adjust(
                chart, views, sizes, fit_tangential=False, hold_to_charts=False
            )
            for name, fit in held.fits.items():
                true = camera_in_frame(
                    rig.cameras[name].K, rig.cameras[name].D, truth[name], sizes[name]
                )
                calibrated = fit.camera(sizes[name])
                range_m = held.uncertainty.range_m[name]
                grid = grids[name]
                grid['left'].append(floating.uncertainty.grid_px[name])
                grid['charts'].append(held.uncertainty.grid_px[name])
                grid['true left'].append(true_projection_error(true, calibrated, range_m))
                grid['true charts'].append(
                    true_projection_error_chart_fixed(
                        true, T_left_chart, calibrated, held.T_ref_chart, range_m
                    )
                )
        for name, grid in grids.items():
            rms = {k: np.sqrt(np.mean(np.square(v), axis=0)) for k, v in grid.items()}
            rows.append(
                {
                    'rig': seed,
                    'views': len(rig.T_base_chart),
                    'camera': name,
                    **{
                        f'{gauge} {figure.__name__} [px]': float(figure(value))
                        for gauge, value in rms.items()
                        for figure in (np.median, np.max)
                    },
                }
            )

            def pair(a, b, figure, rms=rms):
                return f'{figure(rms[a]):.3f} / {figure(rms[b]):.3f}'

            lines.append(
                f'| {seed} | {len(rig.T_base_chart)} | {name} | '
                f'{pair("left", "true left", np.median)} | {pair("left", "true left", np.max)} | '
                f'{pair("charts", "true charts", np.median)} | '
                f'{pair("charts", "true charts", np.max)} |'
            )
    lines = [
        '# calib_node: the projection uncertainty in two gauges, each against its truth',
        '',
        f'Command: `source ros2_ws/install/setup.bash && .venv/bin/python '
        f'bench/bench_calib.py --gauge {rigs} --draws {draws} --sigma {sigma:g}` '
        f'({time.perf_counter() - started:.0f} s).',
        '',
        f'Generated stereo rigs (`draw_rig(seed, (left, right))`), exact corners plus '
        f'Gaussian noise {sigma:g} px, {draws} draws each, handheld bundle adjustment (no '
        'p1, p2: the truth has none). Per camera the RMS over the draws, per grid pixel, of '
        'the predicted projection std and of the true projection error at the working '
        'range, then the median and the worst over the 16 x 12 grid [px]. Left frame: the '
        "point held fixed in the left camera's frame; held to the charts: mrcal's "
        "'mean-pcam', what calib_node reports.",
        '',
        *lines,
    ]
    write_results(RESULTS, 'gauge', lines, rows)


def mrcal_check(python, path, rigs):
    """Ours beside mrcal and OpenCV on the sample pairs and ``rigs`` generated stereo rigs
    (``calib_mrcal.py``)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from calib_mrcal import Mrcal, rig_table, sample_table

    started = time.perf_counter()
    mrcal = Mrcal(python, path)
    sample_lines, summary = sample_table(mrcal)
    rig_lines, rig_rows = rig_table(rigs, mrcal) if rigs else ([], [])
    lines = [
        '# calib_node beside mrcal on the same corners',
        '',
        f'Command: `source ros2_ws/install/setup.bash && .venv/bin/python '
        f'bench/bench_calib.py --mrcal --mrcal-rigs {rigs} --mrcal-python {python} '
        f'--mrcal-path {path}` ({time.perf_counter() - started:.0f} s).',
        '',
        "## OpenCV's sample photographs",
        '',
        *sample_lines,
        '',
        '## Generated rigs',
        '',
        *rig_lines,
    ]
    write_results(RESULTS, 'mrcal', lines, {**summary, 'rigs': rig_rows})


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--trials', type=int, default=20, help='trials per sigma (LM, OpenCV)')
    parser.add_argument(
        '--ga-trials', type=int, default=3, help='of which with the GA stages (about 3-5 s each)'
    )
    parser.add_argument(
        '--sigmas', type=float, nargs='+', default=[0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0]
    )
    parser.add_argument('--rigs', type=int, default=10, help='generated rigs, 0 to skip')
    parser.add_argument(
        '--plot-only', action='store_true', help='redraw the plots from the last calib.json'
    )
    parser.add_argument(
        '--uncertainty',
        type=int,
        default=0,
        help='only the uncertainty check on this many generated rigs (uncertainty.md)',
    )
    parser.add_argument('--draws', type=int, default=6, help='renderings per rig (--uncertainty)')
    parser.add_argument(
        '--gauge',
        type=int,
        default=0,
        help='only the uncertainty in two gauges on N generated rigs (gauge.md; --draws)',
    )
    parser.add_argument('--sigma', type=float, default=0.3, help='corner noise [px] (--gauge)')
    parser.add_argument(
        '--supersample', type=int, default=4, help='rays a pixel, squared (--uncertainty)'
    )
    parser.add_argument(
        '--mrcal',
        action='store_true',
        help='only ours beside mrcal on the sample pairs (mrcal.md)',
    )
    parser.add_argument(
        '--mrcal-python', default='python3.12', help="mrcal's interpreter (--mrcal)"
    )
    parser.add_argument(
        '--mrcal-rigs', type=int, default=3, help='generated stereo rigs (--mrcal)'
    )
    parser.add_argument(
        '--mrcal-path', default='/tmp/mrcal', help='where mrcal is installed (pip --target)'
    )
    args = parser.parse_args()
    if args.gauge:
        gauge_check(args.gauge, args.draws, args.sigma)
        return
    if args.mrcal:
        mrcal_check(args.mrcal_python, args.mrcal_path, args.mrcal_rigs)
        return
    if args.uncertainty:
        uncertainty_check(args.uncertainty, args.draws, args.supersample)
        return
    if args.plot_only:
        sweep_results = json.loads((RESULTS / 'calib.json').read_text())['sweep']
        print(plot_sweep({float(k): v for k, v in sweep_results.items()}, RESULTS))
        return
    started = time.perf_counter()

    noise_free = trial(0.0, 0, extras=True)
    t_stereo = noise_free['OpenCV']['time']
    lines = [
        '# calib_node bench: thesis chapter 4',
        '',
        f'Command: `source ros2_ws/install/setup.bash && .venv/bin/python '
        f'bench/bench_calib.py --trials {args.trials} --ga-trials {args.ga_trials}`. '
        'Times are wall-clock on a 2-core machine shared with other jobs: noisy.',
        '',
        '## Table 4.3: 512 points, Tables 4.1/4.2 cameras, noise-free',
        '',
        'Absolute errors of the identifiable quantities (A4.1): fx = f Nx, fy = f Ny '
        '[px], kappa = k f^2, u0, v0 [px], R (rotation angle of R_est R_true^T) [rad], '
        'T (norm) [unit]. Thesis rows: Table 4.3 turned into the same products. GA: '
        'population 240, 200 generations, pc 0.9, pm 0.005, pm_index 0.25, printed '
        'Laplace rule drawn per gene, tournament 3, elitism 1, clipping, seed 0. '
        'Network: structured weights, accepted only if the full-model RMS drops. '
        'OpenCV kappa: n/a (polynomial model). Thesis RMS: its printed parameters '
        'projected on the noise-free points.',
        '',
    ]
    lines += table_43(noise_free)
    times = {m: d['time'] for m, d in noise_free.items()}
    lines += [
        '',
        'Whole stereo calibration times [s] (ratio to OpenCV 2 x calibrateCamera + '
        'stereoCalibrate on the same points):',
        '',
        '| method | time [s] | ratio |',
        '|---|---|---|',
    ] + [f'| {m} | {t:.2f} | {t / t_stereo:.1f} |' for m, t in times.items()]
    lines += [
        '',
        f'Network acceptance (noise-free run): '
        f'{noise_free["GA+network"]["accepted"]} (left, right); network-camera RMS '
        f'{[round(r, 2) for r in noise_free["GA+network"]["network_rms"]]} px.',
        '',
    ]

    results = sweep(args.sigmas, args.trials, args.ga_trials)
    plots = plot_sweep(results, RESULTS)
    lines += [
        '## Figures 4.3-4.7: noise sweep',
        '',
        f'Mean absolute error over {args.trials} seeded trials per sigma for ours and '
        f'OpenCV, {args.ga_trials} for the GA stages. "wrong": cameras (of 2 x trials) '
        'whose final RMS is above that of LM started at the truth (a wrong local '
        'minimum). Plots: ' + ', '.join(plots) + '.',
        '',
        '| sigma | method | trials | wrong | L fx | L fy | L kappa | L u0 | L v0 | L R | '
        'L T | R fx | R fy | R kappa | R u0 | R v0 | R R | R T | time [s] |',
        '|' + '---|' * 19,
    ]
    for sigma, summary in results.items():
        for method, data in summary.items():
            lines.append(
                f'| {sigma} | {method} | {data["trials"]} | '
                f'{data.get("wrong_minima", "")} | '
                + ' | '.join(fmt(data[c][q][0]) for c in ('left', 'right') for q in QUANTITIES)
                + f' | {data["time"]:.2f} |'
            )
    if 0.5 in results:
        ours = results[0.5]['ours: division init+LM']
        lines += [
            '',
            'sigma = 0.5 px, ours, mean relative errors: '
            + ', '.join(
                f'{c} fx {ours[c]["fx"][0] / identifiable(t).fx:.2%}, fy '
                f'{ours[c]["fy"][0] / identifiable(t).fy:.2%}'
                for c, t in zip(('left', 'right'), TRUTH)
            )
            + '.',
        ]

    scenario_lines, scenario_rows = scenario_table(args.trials)
    lines += [
        '',
        "## The node's setting: default scenario (3 plumb_bob cameras, 10 chart poses)",
        '',
        'Exact chart corners projected by the true cameras plus Gaussian '
        'noise; all three cameras calibrated; errors relative.',
        '',
    ] + scenario_lines
    if args.rigs:
        import sys

        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from calib_rigs import rigs_table

        rig_lines, _ = rigs_table(args.rigs)
        lines += ['', f'## Generated rigs: {args.rigs} rigs, rendered charts', '']
        lines += rig_lines
    lines += ['', f'Bench run time: {time.perf_counter() - started:.0f} s.']
    write_results(
        RESULTS,
        'calib',
        lines,
        {
            'table_4_3': noise_free,
            'sweep': {str(k): v for k, v in results.items()},
            'scenario': scenario_rows,
        },
    )


if __name__ == '__main__':
    main()
