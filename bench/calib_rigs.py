"""Generated rigs: calib_node's stage and handheld calibrations against
OpenCV's calibrateCamera + stereoCalibrate, on the same rendered images, scored against
the truth. Imported by bench_calib.py (``--rigs``) and the tests."""

import time

import cv2
import numpy as np
from vgm_evaluation.rig_generator import (
    camera_in_frame,
    draw_rig,
    render_rig,
    score_rig,
    true_corners,
    true_projection_error,
    true_projection_error_chart_fixed,
    with_edge_views,
)

from calib_node.bundle import bundle_adjust_selected
from calib_node.calibrate import calibrate_rig, stage_uncertainty
from calib_node.chart_detection import CharucoChart, chart_points, detect_chessboard
from vgm_common.camera_model import DISTORTION_SIZES, PinholeCamera
from vgm_common.geometry import make_transform

MODES = ('stage', 'handheld')
FIGURES = ('fx', 'fy', 'cx', 'cy', 'distortion', 'baseline', 'position', 'rotation', 'rect_rows')


def detect_views(rig, images, detector='ours'):
    """[{name: (N, 2)}] corners per view; ``'opencv'``: findChessboardCorners + cornerSubPix
    11 x 11 (OpenCV's tutorial), matched to the chart order by the nearest true corner set
    orientation (ours orders by colour; OpenCV's own order is only used as found)."""
    views = []
    for view in images:
        found = {}
        for name, image in view.items():
            if detector == 'ours':
                detection = detect_chessboard(image, rig.rows, rig.cols)
                if detection.corners is not None:
                    found[name] = detection.corners
                continue
            ok, corners = cv2.findChessboardCorners(
                image,
                (rig.cols, rig.rows),
                flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE,
            )
            if ok:
                corners = cv2.cornerSubPix(
                    image,
                    corners,
                    (11, 11),
                    (-1, -1),
                    (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 1e-3),
                )
                found[name] = corners.reshape(-1, 2).astype(float)
        views.append(found)
    return views


def orient_like(views, reference_views, rows, cols):
    """Reorder OpenCV's own corners into our chart order (the nearest of the four board
    symmetries to our detection of the same view), so both calibrate the same frame."""
    out = []
    for view, ref in zip(views, reference_views):
        fixed = {}
        for name, corners in view.items():
            if name not in ref:
                continue
            grid = corners.reshape(rows, cols, 2)
            options = [grid, grid[::-1, ::-1], grid[:, ::-1], grid[::-1]]
            best = min(options, key=lambda g: np.sum((g.reshape(-1, 2) - ref[name]) ** 2))
            fixed[name] = best.reshape(-1, 2)
        out.append(fixed)
    return out


def opencv_rig(chart, views, image_sizes, names, flags=cv2.CALIB_FIX_K3, model='plumb_bob'):
    """calibrateCamera per camera, then stereoCalibrate (intrinsic guess, joint) of left
    with each other camera on their common views (a ChArUco view: the corners both saw;
    NaN rows are corners not seen). Parameter set as ours: k1, k2, p1, p2 (``flags``
    and the ``model`` of the result: another set). Poses relative to left (left at the
    identity)."""
    objects = np.asarray(chart, dtype=np.float32).reshape(-1, 1, 3)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    intr = {}
    for name in names:
        seen = [v[name] for v in views if name in v]
        found = [np.isfinite(s[:, 0]) for s in seen]
        _, K, D, _, _ = cv2.calibrateCamera(
            [objects[f] for f in found],
            [s[f].astype(np.float32).reshape(-1, 1, 2) for s, f in zip(seen, found)],
            image_sizes[name],
            None,
            None,
            flags=flags,
            criteria=criteria,
        )
        intr[name] = (K, D.ravel()[: DISTORTION_SIZES[model]])
    cameras = {'left': PinholeCamera(*image_sizes['left'], *intr['left'], np.eye(4), model)}
    K_left, D_left = intr['left']
    for name in names[1:]:
        common = [v for v in views if 'left' in v and name in v]
        both = [np.isfinite(v['left'][:, 0]) & np.isfinite(v[name][:, 0]) for v in common]
        common = [(v, b) for v, b in zip(common, both) if b.sum() >= 6]
        rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
            [objects[b] for _, b in common],
            [v['left'][b].astype(np.float32).reshape(-1, 1, 2) for v, b in common],
            [v[name][b].astype(np.float32).reshape(-1, 1, 2) for v, b in common],
            intr['left'][0].copy(),
            intr['left'][1].copy(),
            intr[name][0].copy(),
            intr[name][1].copy(),
            image_sizes['left'],
            flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags,
            criteria=criteria,
        )
        T_name_left = np.eye(4)
        T_name_left[:3, :3], T_name_left[:3, 3] = R, T.ravel()
        size = DISTORTION_SIZES[model]
        cameras[name] = PinholeCamera(
            *image_sizes[name], K2, D2.ravel()[:size], np.linalg.inv(T_name_left), model
        )
        if name == 'right':
            K_left, D_left = K1, D1.ravel()[:size]
    cameras['left'] = PinholeCamera(*image_sizes['left'], K_left, D_left, np.eye(4), model)
    return cameras


def opencv_lens_rig(chart, views, image_sizes, names, model):
    """:func:`opencv_rig` for wide lenses on the same corners: rational_polynomial by
    cv2.calibrateCamera + cv2.stereoCalibrate with CALIB_RATIONAL_MODEL (k1..k6, p1, p2);
    equidistant by cv2.fisheye.calibrate + cv2.fisheye.stereoCalibrate (k1..k4, skew
    fixed, intrinsics recomputed jointly from the single-camera ones; views whose
    extrinsic initialisation fails in cv2.fisheye left out). Poses relative to left (left
    at the identity)."""
    if model == 'rational_polynomial':
        return opencv_rig(chart, views, image_sizes, names, cv2.CALIB_RATIONAL_MODEL, model)
    objects = np.asarray(chart, dtype=np.float64).reshape(1, -1, 3)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW

    def calibrate(seen, size):
        # np.eye(3), zeros: not read without CALIB_USE_INTRINSIC_GUESS (None fails in 5.0)
        return cv2.fisheye.calibrate(
            [objects] * len(seen),
            seen,
            size,
            np.eye(3),
            np.zeros((4, 1)),
            flags=flags,
            criteria=criteria,
        )

    # cv2.fisheye's extrinsic initialisation fails on some views (assertion norm_u1 > 0 in
    # InitExtrinsics); such views are left out, as OpenCV users do.
    kept = []
    for view in views:
        usable = {}
        for name, corners in view.items():
            seen = corners.reshape(1, -1, 2).astype(np.float64)
            try:
                calibrate([seen], image_sizes[name])
            except cv2.error:
                continue
            usable[name] = seen
        kept.append(usable)
    intr, T_camera_chart = {}, {}
    for name in names:
        indices = [i for i, v in enumerate(kept) if name in v]
        _, K, D, rvecs, tvecs = calibrate([kept[i][name] for i in indices], image_sizes[name])
        intr[name] = (K, D.ravel())
        T_camera_chart[name] = {
            i: make_transform(cv2.Rodrigues(r)[0], np.ravel(t))
            for i, r, t in zip(indices, rvecs, tvecs)
        }
    cameras = {'left': PinholeCamera(*image_sizes['left'], *intr['left'], np.eye(4), model)}
    K_left, D_left = intr['left']
    for name in names[1:]:
        common = [i for i, v in enumerate(kept) if 'left' in v and name in v]
        try:
            _, K1, D1, K2, D2, R, T, *_ = cv2.fisheye.stereoCalibrate(
                [objects] * len(common),
                [kept[i]['left'] for i in common],
                [kept[i][name] for i in common],
                intr['left'][0].copy(),
                intr['left'][1].copy().reshape(4, 1),
                intr[name][0].copy(),
                intr[name][1].copy().reshape(4, 1),
                image_sizes['left'],
                flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
                criteria=criteria,
            )
            T_name_left = make_transform(R, np.ravel(T))
            if name == 'right':
                K_left, D_left = K1, D1.ravel()
        except cv2.error:
            # Its pose check between views fails (assertion abs_max < threshold) on
            # most of these rigs: the views' relative poses from cv2.fisheye.calibrate
            # averaged instead (rotation: the mean matrix projected onto SO(3)).
            K2, D2 = intr[name][0], intr[name][1]
            relative = [
                T_camera_chart[name][i] @ np.linalg.inv(T_camera_chart['left'][i]) for i in common
            ]
            U, _, Vt = np.linalg.svd(np.mean([T[:3, :3] for T in relative], axis=0))
            R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
            T_name_left = make_transform(R, np.mean([T[:3, 3] for T in relative], axis=0))
        cameras[name] = PinholeCamera(
            *image_sizes[name], K2, np.ravel(D2), np.linalg.inv(T_name_left), model
        )
    cameras['left'] = PinholeCamera(*image_sizes['left'], K_left, D_left, np.eye(4), model)
    return cameras


def stage_observations(rig, views):
    """{name: (base_link points, pixels, (width, height))} as the stage mode sees them."""
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    observations = {}
    for name, camera in rig.cameras.items():
        points, pixels = [], []
        for T, view in zip(rig.T_base_chart, views):
            if name in view:
                points.append(chart @ T[:3, :3].T + T[:3, 3])
                pixels.append(view[name])
        observations[name] = (
            np.concatenate(points),
            np.concatenate(pixels),
            (camera.width, camera.height),
        )
    return observations


def stage_rig(rig, views):
    """calib_node's stage mode: every corner in base_link through the target pose."""
    observations = stage_observations(rig, views)
    result = calibrate_rig(observations, 'lm')
    return {n: f.camera(observations[n][2]) for n, f in result.fits.items()}


def handheld_rig(rig, views):
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
    result = bundle_adjust_selected(chart, views, sizes, names=list(rig.cameras))
    return {n: f.camera(sizes[n]) for n, f in result.fits.items()}


def run_rig(seed, cameras=('left', 'right', 'aux'), views=None, noise=None, exact=False):
    """One generated rig: scores of stage / handheld / OpenCV (our corners) / OpenCV (own
    detection), and times. ``exact``: the true corner pixels instead of images."""
    rig = draw_rig(seed, cameras, views, noise)
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
    names = list(rig.cameras)
    if exact:
        from vgm_evaluation.rig_generator import true_corners

        ours_views = true_corners(rig)
        own_views = None
    else:
        images = render_rig(rig, seed)
        ours_views = detect_views(rig, images, 'ours')
        own_views = orient_like(
            detect_views(rig, images, 'opencv'), ours_views, rig.rows, rig.cols
        )
    out = {'params': rig.params}
    timings = {}
    started = time.perf_counter()
    out['stage'] = score_rig(rig.cameras, stage_rig(rig, ours_views))
    timings['stage'] = time.perf_counter() - started
    started = time.perf_counter()
    out['handheld'] = score_rig(rig.cameras, handheld_rig(rig, ours_views))
    timings['handheld'] = time.perf_counter() - started
    started = time.perf_counter()
    out['opencv'] = score_rig(rig.cameras, opencv_rig(chart, ours_views, sizes, names))
    timings['opencv'] = time.perf_counter() - started
    if own_views is not None and all(sum(n in v for v in own_views) >= 3 for n in names):
        try:
            out['opencv_own'] = score_rig(rig.cameras, opencv_rig(chart, own_views, sizes, names))
        except cv2.error:
            pass
    out['time'] = timings
    return out


def lens_run(seed, model):
    """One generated rig of wide ``model`` lenses (``draw_rig(seed, lens_model=model)``),
    rendered: ours (stage and handheld, lens model by BIC) and OpenCV's calibration of
    that model (:func:`opencv_lens_rig`) on our corners, scored against the truth, the
    models ours chose and the seconds each took."""
    rig = draw_rig(seed, lens_model=model)
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
    views = detect_views(rig, render_rig(rig, seed), 'ours')
    out = {'params': rig.params, 'model': model, 'time': {}, 'chosen': {}}
    out['found'] = [sum(n in v for v in views) for n in rig.cameras]
    for mode, calibrate in (
        ('stage', stage_rig),
        ('handheld', handheld_rig),
        ('opencv', lambda r, v: opencv_lens_rig(chart, v, sizes, list(r.cameras), model)),
    ):
        started = time.perf_counter()
        try:
            cameras = calibrate(rig, views)
        except cv2.error as error:  # cv2.fisheye's InitExtrinsics assertion on some rigs
            print(f'{model} rig {seed}: {mode} failed: {error}', flush=True)
            out[mode] = None
            continue
        out['time'][mode] = time.perf_counter() - started
        out[mode] = score_rig(rig.cameras, cameras)
        out['chosen'][mode] = {n: c.distortion_model for n, c in cameras.items()}
    return out


def lens_table(count, models=('rational_polynomial', 'equidistant')):
    """Markdown lines and per-rig results of ``count`` rigs (seeds 0..count-1) per lens
    model of ``models``."""
    lines = [
        'Wide lenses (`draw_rig(seed, lens_model=...)`: rational_polynomial f 0.4-0.55 width, '
        'barrel, decentred; equidistant f 0.28-0.38 width), rendered and detected by us; '
        'worst camera per figure; ratio = ours (stage or handheld, distortion_model auto) / '
        'OpenCV (cv2.calibrateCamera + cv2.stereoCalibrate with CALIB_RATIONAL_MODEL, or '
        'cv2.fisheye.calibrate + cv2.fisheye.stereoCalibrate) on the same corners. '
        '`distortion` compares each lens over the image with the true K, so a fit whose '
        'focal length and distortion trade (the rational model) shows it there.',
        '',
    ]
    results = []
    for model in models:
        rows = []
        for seed in range(count):
            rows.append(lens_run(seed, model))
            print(f'{model} rig {seed}: {rows[-1]["chosen"]} {rows[-1]["time"]}', flush=True)
        results += rows
        failed = [seed for seed, r in enumerate(rows) if r['opencv'] is None]
        rows = [r for r in rows if r['opencv'] is not None]
        lines += [
            f'### {model}',
            '',
            '| figure | stage / OpenCV median | max | handheld / OpenCV median | max | '
            'stage median | handheld median | OpenCV median |',
            '|---|---|---|---|---|---|---|---|',
        ]
        if failed:
            lines[-3:-3] = [f'OpenCV failed on rigs {failed} (left out below).', '']
        for figure in FIGURES:
            ratios = {
                mode: [r[mode][figure] / max(r['opencv'][figure], 1e-300) for r in rows]
                for mode in ('stage', 'handheld')
            }
            medians = [np.median([r[m][figure] for r in rows]) for m in ('stage', 'handheld')]
            lines.append(
                f'| {figure} | {np.median(ratios["stage"]):.2f} | {np.max(ratios["stage"]):.2f} '
                f'| {np.median(ratios["handheld"]):.2f} | {np.max(ratios["handheld"]):.2f} | '
                f'{medians[0]:.2e} | {medians[1]:.2e} | '
                f'{np.median([r["opencv"][figure] for r in rows]):.2e} |'
            )
        lines.append('')
        for mode in ('stage', 'handheld'):
            chosen = [m for r in rows for m in r['chosen'][mode].values()]
            seconds = np.median([r['time'][mode] for r in rows])
            lines.append(
                f'Models ours chose, {mode} ({len(chosen)} cameras): '
                + ', '.join(f'{m} {chosen.count(m)}' for m in sorted(set(chosen)))
                + f'; median {seconds:.1f} s a rig (OpenCV '
                + f'{np.median([r["time"]["opencv"] for r in rows]):.1f} s).'
            )
        lines.append('')
    return lines, results


def rigs_table(count):
    """Markdown lines and per-rig results of ``count`` generated rigs (seeds 0..count-1)."""
    results = []
    for seed in range(count):
        results.append(run_rig(seed))
        print(f'rig {seed}: {results[-1]["params"]}', flush=True)
    lines = [
        'Worst camera per figure; ratio = ours / OpenCV (cv2.calibrateCamera + '
        'cv2.stereoCalibrate with CALIB_USE_INTRINSIC_GUESS on the same corners, k1 k2 p1 '
        'p2; ours selects p1 p2 by BIC and drops them on these lenses); "own": OpenCV '
        'on its own detection (findChessboardCorners + cornerSubPix 11 x 11). Positions '
        'and rotations relative to the left camera. Goals: stage median <= 0.7, max <= 1.2; '
        'handheld median <= 1.0, max <= 1.5.',
        '',
        '| figure | stage / OpenCV median | max | handheld / OpenCV median | max | '
        'stage / OpenCV own median | max |',
        '|---|---|---|---|---|---|---|',
    ]
    for figure in FIGURES:
        ratios = {
            m: [r[m][figure] / max(r['opencv'][figure], 1e-300) for r in results]
            for m in ('stage', 'handheld')
        }
        own = [
            r['stage'][figure] / max(r['opencv_own'][figure], 1e-300)
            for r in results
            if 'opencv_own' in r
        ]
        lines.append(
            f'| {figure} | {np.median(ratios["stage"]):.2f} | '
            f'{np.max(ratios["stage"]):.2f} | {np.median(ratios["handheld"]):.2f} | '
            f'{np.max(ratios["handheld"]):.2f} | '
            + (f'{np.median(own):.2f} | {np.max(own):.2f} |' if own else 'n/a | n/a |')
        )
    lines += [
        '',
        '| rig | width | views | noise | baseline [m] | vergence [deg] | aux oblique '
        '[deg] | k1 L / R | stage worst ratio | handheld worst ratio | stage fx err | '
        'OpenCV fx err |',
        '|---|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for seed, r in enumerate(results):
        p = r['params']
        worst = {
            m: max(FIGURES, key=lambda f: r[m][f] / max(r['opencv'][f], 1e-300))
            for m in ('stage', 'handheld')
        }
        lines.append(
            f'| {seed} | {p["width"]} | {p["views"]} | {p["noise"]:.1f} | '
            f'{p["baseline_m"]:.3f} | {p["vergence_deg"]:.1f} | {p["aux_oblique_deg"]:.0f} | '
            f'{p["k1_left"]:.2f} / {p["k1_right"]:.2f} | '
            + ' | '.join(
                f'{worst[m]} {r[m][worst[m]] / max(r["opencv"][worst[m]], 1e-300):.2f}'
                for m in ('stage', 'handheld')
            )
            + f' | {r["stage"]["fx"]:.2e} | {r["opencv"]["fx"]:.2e} |'
        )
    times = {
        m: np.median([r['time'][m] for r in results]) for m in ('stage', 'handheld', 'opencv')
    }
    lines += [
        '',
        'Median calibration time of the three cameras [s] (loaded 2-core machine): '
        + ', '.join(f'{m} {t:.2f}' for m, t in times.items())
        + f'; handheld / OpenCV {times["handheld"] / times["opencv"]:.1f}, stage / '
        f'OpenCV {times["stage"] / times["opencv"]:.1f}.',
    ]
    return lines, results


def _uncertainty_runs(rig, views):
    """{mode: (Uncertainty, {name: (K, D, T_camera_ref, model)}, {name: true T_camera_ref},
    charts)} of one calibration per mode, as calib_node makes them (p1, p2 by BIC);
    charts: None on the stage (the point fixed in base_link), handheld (true, estimated)
    chart poses in the left camera's frame (the point held to the charts, as the
    uncertainty)."""
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
    observations = stage_observations(rig, views)
    stage = calibrate_rig(observations, 'lm', view_size=len(chart)).fits
    handheld = bundle_adjust_selected(chart, views, sizes, names=list(rig.cameras))
    T_base_left = rig.cameras['left'].T_base_camera
    return {
        'stage': (
            stage_uncertainty(stage, observations),
            {n: (f.K, f.D, np.linalg.inv(f.T_base_camera), f.model) for n, f in stage.items()},
            {n: np.linalg.inv(c.T_base_camera) for n, c in rig.cameras.items()},
            None,
        ),
        'handheld': (
            handheld.uncertainty,
            {
                n: (f.K, f.D, np.linalg.inv(f.T_base_camera), f.model)
                for n, f in handheld.fits.items()
            },
            {n: np.linalg.inv(c.T_base_camera) @ T_base_left for n, c in rig.cameras.items()},
            (
                [np.linalg.inv(T_base_left) @ T for T in rig.T_base_chart],
                handheld.T_ref_chart,
            ),
        ),
    }


def uncertainty_table(count, draws, supersample=4):
    """Markdown lines and rows: the predicted projection uncertainty against the true
    projection error on ``count`` generated rigs (seeds 0..count-1), each rendered
    ``draws`` times with fresh image noise (the prediction is the RMS over such repeats),
    ``supersample``^2 rays a pixel."""
    rows = []
    for seed in range(count):
        rig = draw_rig(seed)
        sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
        b_true = np.linalg.norm(rig.cameras['left'].centre_base - rig.cameras['right'].centre_base)
        collected = {m: {'pred': {}, 'err': {}, 'worst': {}, 'b': []} for m in MODES}
        for draw in range(draws):
            views = detect_views(rig, render_rig(rig, seed + 1000 * draw, supersample))
            for mode, (u, cameras, truth, charts) in _uncertainty_runs(rig, views).items():
                c = collected[mode]
                for name, true in rig.cameras.items():
                    K, D, T_camera_ref, model = cameras[name]
                    calibrated = camera_in_frame(K, D, T_camera_ref, sizes[name], model)
                    true_in_frame = camera_in_frame(true.K, true.D, truth[name], sizes[name])
                    range_m = u.range_m[name]
                    error = (
                        true_projection_error(true_in_frame, calibrated, range_m)
                        if charts is None
                        else true_projection_error_chart_fixed(
                            true_in_frame, charts[0], calibrated, charts[1], range_m
                        )
                    )
                    c['pred'].setdefault(name, []).append(u.grid_px[name])
                    c['err'].setdefault(name, []).append(error)
                    c['worst'].setdefault(name, []).append(u.worst_px[name])
                centres = [np.linalg.inv(cameras[n][2])[:3, 3] for n in ('left', 'right')]
                c['b'].append((np.linalg.norm(centres[0] - centres[1]) - b_true, u.baseline_std_m))
        for mode, c in collected.items():
            for name in rig.cameras:
                pred, err = np.array(c['pred'][name]), np.array(c['err'][name])
                single = np.sqrt(np.mean(pred**2, axis=(1, 2)) / np.mean(err**2, axis=(1, 2)))
                rows.append(
                    {
                        'rig': seed,
                        'mode': mode,
                        'camera': name,
                        'predicted_px': float(np.sqrt(np.mean(pred**2))),
                        'true_px': float(np.sqrt(np.mean(err**2))),
                        'worst_predicted_px': float(np.mean(c['worst'][name])),
                        'worst_true_px': float(np.max(np.sqrt(np.mean(err**2, axis=0)))),
                        'single_draw': (float(single.min()), float(single.max())),
                    }
                )
            b = np.array(c['b'])
            rows[-1]['baseline'] = (float(np.mean(b[:, 1])), float(np.sqrt(np.mean(b[:, 0] ** 2))))
        print(f'rig {seed}: {rig.params}', flush=True)
    lines = [
        f'Each rig rendered {draws} times (image noise seeds); per mode and camera the '
        'predicted projection standard deviation at the working range (RMS over the 16 x 12 '
        'image grid and the draws) against the true projection error (true camera vs '
        'calibrated, the same points, RMS over grid and draws); "worst": the largest '
        'grid point of each; "one draw": the range of the ratio from single calibrations. '
        'Goal: ratio within 0.5-2 on every rig.',
        '',
        '| rig | mode | camera | predicted [px] | true [px] | ratio | worst predicted | '
        'worst true | ratio | one draw | baseline std predicted / true [um] |',
        '|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for r in rows:
        baseline = (
            f'{1e6 * r["baseline"][0]:.1f} / {1e6 * r["baseline"][1]:.1f}'
            if 'baseline' in r
            else ''
        )
        lines.append(
            f'| {r["rig"]} | {r["mode"]} | {r["camera"]} | {r["predicted_px"]:.3f} | '
            f'{r["true_px"]:.3f} | {r["predicted_px"] / r["true_px"]:.2f} | '
            f'{r["worst_predicted_px"]:.3f} | {r["worst_true_px"]:.3f} | '
            f'{r["worst_predicted_px"] / r["worst_true_px"]:.2f} | '
            f'{r["single_draw"][0]:.2f}-{r["single_draw"][1]:.2f} | {baseline} |'
        )
    ratios = [r['predicted_px'] / r['true_px'] for r in rows]
    worst = [r['worst_predicted_px'] / r['worst_true_px'] for r in rows]
    lines += [
        '',
        f'RMS ratio over {len(rows)} cameras: min {min(ratios):.2f}, median '
        f'{np.median(ratios):.2f}, max {max(ratios):.2f}; worst-point ratio: min '
        f'{min(worst):.2f}, median {np.median(worst):.2f}, max {max(worst):.2f}.',
    ]
    return lines, rows


def corner_bias_table(seeds, draws, supersample=4):
    """Where the stage uncertainty misses come from: per camera of the generated rigs
    ``seeds``, rendered ``draws`` times, the detected corners' error against the true
    projection split into the part every rendering repeats (the mean over the draws: the
    detector's bias on this rendering) and the rest (the image noise); then the stage
    calibration (plumb_bob k1 k2, as the truth) predicted against true projection error at
    the working range on the detected corners, and on the true corners plus only the
    repeated part; ``supersample``^2 rays a pixel (the renderer's own staircase on the
    edges repeats too). Markdown lines and rows."""
    rows = []
    for seed in seeds:
        rig = draw_rig(seed)
        chart = chart_points(rig.rows, rig.cols, rig.spacing)
        truth = true_corners(rig)
        renders = [
            detect_views(rig, render_rig(rig, seed + 1000 * d, supersample)) for d in range(draws)
        ]
        repeated = [
            {
                n: t[n] + np.mean([r[k][n] - t[n] for r in renders], axis=0)
                for n in rig.cameras
                if all(n in r[k] for r in renders)
            }
            for k, t in enumerate(truth)
        ]

        def stage(views, rig=rig, chart=chart):
            observations = stage_observations(rig, views)
            fits = calibrate_rig(
                observations,
                'lm',
                view_size=len(chart),
                fit_tangential=False,
                distortion_model='plumb_bob',
            ).fits
            u = stage_uncertainty(fits, observations)
            out = {}
            for n, f in fits.items():
                c = rig.cameras[n]
                error = true_projection_error(c, f.camera((c.width, c.height)), u.range_m[n])
                out[n] = (np.mean(u.grid_px[n] ** 2), np.mean(error**2))
            return out

        detected = [stage(views) for views in renders]
        bias_only = stage(repeated)
        for n in rig.cameras:
            seen = [k for k, view in enumerate(repeated) if n in view]
            errors = np.array([[r[k][n] - truth[k][n] for k in seen] for r in renders])
            common = errors.mean(axis=0)
            pred = np.sqrt(np.mean([d[n][0] for d in detected]))
            true = np.sqrt(np.mean([d[n][1] for d in detected]))
            rows.append(
                {
                    'rig': seed,
                    'camera': n,
                    'corner_error_px': float(np.sqrt(np.mean(np.sum(errors**2, axis=-1)))),
                    'repeated_px': float(np.sqrt(np.mean(np.sum(common**2, axis=-1)))),
                    'random_px': float(np.sqrt(np.mean(np.sum((errors - common) ** 2, -1)))),
                    'predicted_px': float(pred),
                    'true_px': float(true),
                    'bias_only_predicted_px': float(np.sqrt(bias_only[n][0])),
                    'bias_only_true_px': float(np.sqrt(bias_only[n][1])),
                }
            )
        print(f'rig {seed} done', flush=True)
    lines = [
        f'Stage calibration (plumb_bob k1 k2), {draws} renderings per rig. Corner errors '
        'RMS [px] against the true projection: all, the part every rendering repeats, the '
        'rest. Projection at the working range, RMS over the grid [px]: predicted / true on '
        'the detected corners (RMS over the draws), and on the true corners plus the '
        'repeated part alone.',
        '',
        '| rig | camera | corner error | repeated | random | predicted / true | ratio | '
        'repeated part alone: predicted / true |',
        '|---|---|---|---|---|---|---|---|',
    ]
    for r in rows:
        lines.append(
            f'| {r["rig"]} | {r["camera"]} | {r["corner_error_px"]:.4f} | '
            f'{r["repeated_px"]:.4f} | {r["random_px"]:.4f} | {r["predicted_px"]:.4f} / '
            f'{r["true_px"]:.4f} | {r["predicted_px"] / r["true_px"]:.2f} | '
            f'{r["bias_only_predicted_px"]:.4f} / {r["bias_only_true_px"]:.4f} |'
        )
    return lines, rows


def charuco_run(seed, edge_views=4):
    """One generated rig shown as a chessboard and as a ChArUco board at the same poses
    (its views plus ``edge_views`` cut by an image edge: with_edge_views), handheld:
    scores of ours (bundle_adjust_selected) and OpenCV (calibrateCamera +
    stereoCalibrate) on the same corners, and the corners each pattern gave."""
    rig = with_edge_views(draw_rig(seed), edge_views)
    sizes = {n: (c.width, c.height) for n, c in rig.cameras.items()}
    names = list(rig.cameras)
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    out = {'params': rig.params}
    for pattern in ('chessboard', 'charuco'):
        shown = rig._replace(pattern=pattern)
        images = render_rig(shown, seed)
        if pattern == 'chessboard':
            views = detect_views(shown, images, 'ours')
        else:
            detector = CharucoChart(rig.rows, rig.cols, rig.spacing)
            views = [
                {
                    n: d.corners
                    for n, image in view.items()
                    if (d := detector.detect(image)).corners is not None
                }
                for view in images
            ]
        views = [v for v in views if v]  # a view is one in which some camera found it
        corners = sum(int(np.isfinite(c[:, 0]).sum()) for v in views for c in v.values())
        out[pattern] = {
            'views': len(views),
            'corners': corners,
            'ours': score_rig(rig.cameras, handheld_rig(shown, views)),
            'opencv': score_rig(rig.cameras, opencv_rig(chart, views, sizes, names)),
        }
    return out


def charuco_table(count, edge_views=4):
    """Markdown lines and per-rig results of :func:`charuco_run` on seeds 0..count-1."""
    results = [charuco_run(seed, edge_views) for seed in range(count)]
    lines = [
        f"Handheld, generated rigs (seeds 0-{count - 1}), each rig's views plus "
        f"{edge_views} boards cut by the left image's edge; the same poses shown as a "
        'chessboard and as a ChArUco board (DICT_5X5_100, markers 0.75). Worst camera '
        'per figure (relative errors for fx, baseline; px for cx).',
        '',
        '| seed | pattern | views | corners | fx ours | fx OpenCV | cx ours [px] | '
        'cx OpenCV [px] | baseline ours | baseline OpenCV |',
        '|---|---|---|---|---|---|---|---|---|---|',
    ]
    for seed, result in enumerate(results):
        for pattern in ('chessboard', 'charuco'):
            r = result[pattern]
            lines.append(
                f'| {seed} | {pattern} | {r["views"]} | {r["corners"]} | '
                f'{r["ours"]["fx"]:.2e} | {r["opencv"]["fx"]:.2e} | '
                f'{r["ours"]["cx"]:.3f} | {r["opencv"]["cx"]:.3f} | '
                f'{r["ours"]["baseline"]:.2e} | {r["opencv"]["baseline"]:.2e} |'
            )
    return lines, results


def main():
    """``python bench/calib_rigs.py [rigs]``: bench/results/calib/rigs.md and rigs.json;
    ``python bench/calib_rigs.py charuco [rigs]``: charuco.md and charuco.json;
    ``python bench/calib_rigs.py lenses [rigs]``: lenses.md and lenses.json (rigs per
    lens model); ``python bench/calib_rigs.py bias [rigs [draws [supersample]]]``: bias.md
    and bias.json (:func:`corner_bias_table`; supersample 4 by default)."""
    import sys
    from pathlib import Path

    from vgm_evaluation.bench_report import write_results

    kinds = ('charuco', 'lenses', 'bias')
    kind = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1] in kinds else ''
    arguments = sys.argv[2:] if kind else sys.argv[1:]
    count = (
        int(arguments[0]) if arguments else {'charuco': 3, 'lenses': 5, 'bias': 5, '': 10}[kind]
    )
    if kind == 'bias':  # rigs 0..count-1, draws
        draws = int(arguments[1]) if len(arguments) > 1 else 3
        supersample = int(arguments[2]) if len(arguments) > 2 else 4
        lines, results = corner_bias_table(range(count), draws, supersample)
        count = f'{count} {draws} {supersample}'
    else:
        table = {'charuco': charuco_table, 'lenses': lens_table, '': rigs_table}[kind]
        lines, results = table(count)
    title = {
        'charuco': 'ChArUco and chessboard on generated rigs',
        'lenses': 'Rational and fisheye lenses',
        'bias': "The corner detector's repeated error and the stage uncertainty",
        '': 'calib_node on generated rigs',
    }[kind]
    command = f'bench/calib_rigs.py {kind + " " if kind else ""}{count}'
    header = [
        f'# {title} on generated rigs',
        '',
        f'Command: `source ros2_ws/install/setup.bash && .venv/bin/python {command}`.',
        '',
    ]
    out = Path(__file__).resolve().parent / 'results' / 'calib'
    write_results(out, kind or 'rigs', header + lines, results)


if __name__ == '__main__':
    main()
