"""Handheld-chart calibration of a rig: a Zhang start per camera
(``cv2.calibrateCamera`` on its planar views), then one bundle adjustment over every
camera's intrinsics and distortion, the rig's extrinsics and every chart pose. No rclpy.

Frames: the reference frame ``ref`` is ``base_link`` when at least one view's chart pose
is known (``/calibration/target_pose``; those poses are held fixed), else the first
camera's optical frame (``left``; its pose is the identity, held fixed) and the caller
places it in base_link (the node's ``rig_pose``).

Parameters of the adjustment, per camera: fx, fy, cx, cy and the distortion of its model
(plumb_bob k1, k2, p1, p2, k3 with p1, p2 and k3 optional; rational_polynomial k1, k2,
p1, p2, k3..k6; equidistant k1..k4) and T_camera_ref (Rodrigues vector, translation); per
view with an unknown chart pose: T_ref_chart. Residuals: every detected corner's
reprojection error [px], unweighted (the corners' errors are alike, ~0.05-0.1 px). The
Jacobian is analytic: ``cv2.projectPoints``' (``cv2.fisheye``'s) derivatives chained
through ``cv2.composeRT``'s.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import NamedTuple, cast

import cv2
import numpy as np
import numpy.typing as npt

from calib_node.calibrate import (
    CalibrationError,
    CameraFit,
    calibrate_camera_lm,
    select_rig_models,
    solve_lm,
    tangential_pays,
)
from calib_node.uncertainty import (
    ChartPoses,
    RigCamera,
    Uncertainty,
    canonical_rotations,
    parameter_covariance,
    rig_uncertainty,
    working_range,
)
from vgm_common.camera_model import DISTORTION_SIZES, PinholeCamera, project_points
from vgm_common.geometry import FloatArray, invert_transform, make_transform

Views = Sequence[Mapping[str, npt.ArrayLike]]  # [{name: (N, 2) pixels}] per view
Intrinsics = dict[str, tuple[np.ndarray, list[float]]]  # {name: (K (3, 3), D of its model)}
BoolArray = npt.NDArray[np.bool_]


def bundle_adjust_selected(
    chart: npt.ArrayLike,
    views: Views,
    image_sizes: Mapping[str, tuple[int, int]],
    T_ref_chart_known: Sequence[FloatArray | None] | None = None,
    names: Sequence[str] | None = None,
    fit_tangential: bool = True,
    fit_k3: bool = False,
    select_model: bool = True,
    distortion_model: str = 'auto',
) -> BundleResult:
    """:func:`bundle_adjust` of the rig with the lens model and p1, p2 chosen by BIC.

    ``distortion_model`` (``calibrate.MODEL_CHOICES``): the model every camera is fitted
    with, or ``auto`` (with ``select_model`` every one of ``FIT_MODELS``, without it
    plumb_bob). First the plumb_bob rig; with ``select_model`` also without p1, p2: the
    simpler rig is kept unless p1, p2 pay (``calibrate.tangential_pays``, BIC over the
    rig). With ``auto`` then the equidistant rig (from the plumb_bob one), and each camera
    fitted rational_polynomial on the chart poses the equidistant rig found (it follows
    narrow and fisheye lenses alike, measured: its residuals within 0.1 % of the better
    model's); each camera's model is chosen as on the stage (``select_rig_models``: the
    lowest BIC, left and right one model), and a rig that is not all plumb_bob or all
    equidistant is adjusted once more from the chosen fits.

    Why rational_polynomial not as a whole rig: on lenses it does not fit better its
    bundle crawls along the valley where k1..k3 and k4..k6 cancel (measured: 99-174
    evaluations, 10-18 s, on three-camera rigs of 16 views; the equidistant rig 5-9).
    """
    names = list(names or image_sizes)

    def adjust(
        tangential: bool,
        models: Mapping[str, str] | None = None,
        start: BundleResult | None = None,
    ) -> BundleResult:
        return bundle_adjust(
            chart,
            views,
            image_sizes,
            T_ref_chart_known,
            names,
            tangential,
            fit_k3,
            models=models,
            start=start,
        )

    plumb_bob = adjust(fit_tangential)
    if fit_tangential and select_model:
        plain = adjust(False)
        n = 2 * sum(f.points for f in plumb_bob.fits.values())
        rss = (plumb_bob.rms_px**2 * n / 2, plain.rms_px**2 * n / 2)
        if not tangential_pays(*rss, n, len(plumb_bob.fits)):
            plumb_bob = plain
    tangential = _fits_tangential(plumb_bob.fits.values())
    if distortion_model != 'auto':
        if distortion_model == 'plumb_bob':
            return plumb_bob
        return adjust(tangential, {n: distortion_model for n in names}, plumb_bob)
    if not select_model:
        return plumb_bob
    equidistant = adjust(False, {n: 'equidistant' for n in names}, plumb_bob)
    rational = {
        n: calibrate_camera_lm(
            points,
            pixels,
            image_sizes[n],
            _camera_start(equidistant.fits[n], plumb_bob.fits[n].D),
            _fits_tangential([plumb_bob.fits[n]]),
            fit_k3,
            model='rational_polynomial',
        )
        for n, (points, pixels) in _chart_observations(
            chart, views, equidistant.T_ref_chart, names
        ).items()
    }
    chosen = select_rig_models(
        {
            n: {
                'plumb_bob': plumb_bob.fits[n],
                'equidistant': equidistant.fits[n],
                'rational_polynomial': rational[n],
            }
            for n in names
        }
    )
    for rig in (plumb_bob, equidistant):
        if all(fit is rig.fits[n] for n, fit in chosen.items()):
            return rig
    return adjust(
        _fits_tangential(chosen.values()),
        {n: fit.model for n, fit in chosen.items()},
        equidistant._replace(fits=chosen),
    )


def _fits_tangential(fits: Iterable[CameraFit]) -> bool:
    """Whether any of the fits estimated p1, p2 (a fit without them has them 0)."""
    return any(f.model != 'equidistant' and bool(np.any(f.D[2:4])) for f in fits)


def _camera_start(
    fit: CameraFit, D: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """(K, D, R, t) to start ``calibrate_camera_lm``: the fit's K and reference->camera
    pose, the given plumb_bob ``D``."""
    T_camera_ref = invert_transform(fit.T_base_camera)
    return fit.K, np.asarray(D, dtype=float), T_camera_ref[:3, :3], T_camera_ref[:3, 3]


def _chart_observations(
    chart: npt.ArrayLike, views: Views, T_ref_chart: Sequence[FloatArray], names: Sequence[str]
) -> dict[str, tuple[FloatArray, FloatArray]]:
    """{name: (corners in the reference frame (N, 3), their pixels (N, 2))} of every view
    the camera saw, the charts placed by ``T_ref_chart`` (a ChArUco corner not seen left
    out)."""
    chart = np.asarray(chart, dtype=float)
    observations = {}
    for name in names:
        points, pixels = [], []
        for view, T in zip(views, T_ref_chart):
            if name in view:
                uv = np.asarray(view[name], dtype=float)
                seen = np.isfinite(uv[:, 0])
                points.append((chart @ T[:3, :3].T + T[:3, 3])[seen])
                pixels.append(uv[seen])
        observations[name] = (np.concatenate(points), np.concatenate(pixels))
    return observations


class BundleResult(NamedTuple):
    """A bundle adjustment's rig: every camera's fit in the reference frame, every view's
    chart pose and the reprojection RMS [px]."""

    fits: dict[str, CameraFit]  # T_base_camera = T_ref_camera
    T_ref_chart: list[FloatArray]  # (4, 4) chart pose of every view in the reference frame
    reference: str  # 'base_link' or the name of the reference camera
    rms_px: float  # over every corner of every camera
    iterations: int
    uncertainty: Uncertainty  # of the projections at the working range and the baseline


def _rt(T: FloatArray) -> tuple[np.ndarray, FloatArray]:
    return cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0].ravel(), T[:3, 3].copy()


def _T(rvec: npt.ArrayLike, tvec: npt.ArrayLike) -> FloatArray:
    return make_transform(cv2.Rodrigues(np.asarray(rvec, dtype=float))[0], tvec)


def _mean_transform(transforms: Sequence[FloatArray]) -> FloatArray:
    """Chordal mean of rotations (SVD projection of the sum) and mean translation."""
    U, _, Vt = np.linalg.svd(np.sum([T[:3, :3] for T in transforms], axis=0))
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    return make_transform(R, np.mean([T[:3, 3] for T in transforms], axis=0))


def zhang_start(
    chart: npt.ArrayLike,
    views: Views,
    image_sizes: Mapping[str, tuple[int, int]],
    fit_tangential: bool = True,
    fit_k3: bool = False,
) -> tuple[Intrinsics, list[dict[str, FloatArray]]]:
    """Per camera ``cv2.calibrateCamera`` (Zhang) on the views that saw the chart.

    Returns:
        ({name: (K, D (5,))}, [{name: T_camera_chart (4, 4)}] per view).

    Raises:
        CalibrationError: a camera saw the chart in fewer than 3 views, or OpenCV failed.
    """
    flags = (0 if fit_tangential else cv2.CALIB_ZERO_TANGENT_DIST) | (
        0 if fit_k3 else cv2.CALIB_FIX_K3
    )
    objects = np.asarray(chart, dtype=np.float32).reshape(-1, 1, 3)
    intrinsics: Intrinsics = {}
    poses: list[dict[str, FloatArray]] = [dict() for _ in views]
    for name, size in image_sizes.items():
        seen = [i for i, view in enumerate(views) if name in view]
        if len(seen) < 3:
            raise CalibrationError(
                f'{name}: the chart was found in {len(seen)} views, '
                'need at least 3 without target poses'
            )
        pixels = [np.asarray(views[i][name], dtype=np.float32).reshape(-1, 1, 2) for i in seen]
        found = [np.isfinite(uv[:, 0, 0]) for uv in pixels]  # NaN: a ChArUco corner not seen
        try:
            _, K, D, rvecs, tvecs = cv2.calibrateCamera(
                [objects[f] for f in found],
                [uv[f] for uv, f in zip(pixels, found)],
                tuple(int(s) for s in size),
                None,
                None,
                flags=flags,
            )
        except cv2.error as error:
            raise CalibrationError(f'{name}: Zhang start failed: {error}') from None
        # float64 out, and np.float64 is a float (the stub's MatLike allows integers too)
        intrinsics[name] = (K, cast(list[float], (list(np.ravel(D)) + [0.0] * 5)[:5]))
        for i, rvec, tvec in zip(seen, rvecs, tvecs):
            poses[i][name] = _T(rvec.ravel(), tvec.ravel())
    return intrinsics, poses


def bundle_adjust(
    chart: npt.ArrayLike,
    views: Views,
    image_sizes: Mapping[str, tuple[int, int]],
    T_ref_chart_known: Sequence[FloatArray | None] | None = None,
    names: Sequence[str] | None = None,
    fit_tangential: bool = True,
    fit_k3: bool = False,
    max_nfev: int = 200,
    hold_to_charts: bool = True,
    *,
    models: Mapping[str, str] | None = None,
    start: BundleResult | None = None,
) -> BundleResult:
    """Calibrate the rig from chessboard views jointly.

    Args:
        chart: (N, 3) chart-frame corners [m].
        views: [{name: (N, 2) pixels}] per view (a camera missing from a view did not see
            the chart).
        image_sizes: {name: (width, height)}.
        T_ref_chart_known: per view a (4, 4) chart pose in base_link or None (unknown);
            None: all unknown.
        names: camera order; the first is the reference camera when no pose is known.
        fit_tangential: estimate p1, p2 (plumb_bob, rational_polynomial); fit_k3: estimate
            plumb_bob's k3 (rational_polynomial always estimates k3..k6).
        hold_to_charts: the uncertainty's points held fixed to the charts when no chart
            pose is known (``uncertainty.projection_std_chart_fixed``); False: in the
            reference camera's frame (for comparison: it floats with its intrinsics).
        models: {name: distortion model (``calibrate.FIT_MODELS``)}; None: plumb_bob.
        start: a rig of the same views (e.g. the plumb_bob one) to start from instead of
            Zhang's per-camera solutions: its intrinsics (its distortion carried over to
            a rational_polynomial camera, zero for an equidistant one), camera and chart
            poses.

    Returns:
        :class:`BundleResult`.

    Raises:
        CalibrationError: too few views, a camera that never shares a view with the
            reference, or a failed fit.
    """
    chart = np.ascontiguousarray(chart, dtype=float)
    names = list(names or image_sizes)
    model_of = {n: (models or {}).get(n, 'plumb_bob') for n in names}
    known = list(T_ref_chart_known or [None] * len(views))
    has_known = any(T is not None for T in known)
    reference = 'base_link' if has_known else names[0]
    if start is None:
        intrinsics, T_camera_chart = zhang_start(
            chart, views, {n: image_sizes[n] for n in names}, fit_tangential, fit_k3
        )
        # Start of T_camera_ref and T_ref_chart from the Zhang poses.
        if has_known:
            T_camera_ref = _start_camera_poses_from_known_charts(
                names, views, known, T_camera_chart
            )
        else:
            T_camera_ref = _start_camera_poses_from_reference(names, views, T_camera_chart)
        T_ref_chart = _start_chart_poses(views, known, T_camera_ref, T_camera_chart)
    else:
        intrinsics = {n: (start.fits[n].K, list(start.fits[n].D)) for n in names}
        T_camera_ref = {n: invert_transform(start.fits[n].T_base_camera) for n in names}
        T_ref_chart = list(start.T_ref_chart)
    intrinsics = {
        n: (K, _start_distortion(D, start.fits[n].model if start else 'plumb_bob', model_of[n]))
        for n, (K, D) in intrinsics.items()
    }
    layout = _Layout(tuple(model_of[n] for n in names), len(views))
    x0 = _parameter_vector(names, intrinsics, T_camera_ref, T_ref_chart)
    free = _free_parameters(len(x0), layout, known, has_known, fit_tangential, fit_k3)
    pairs = [
        (c, i) for i in range(layout.views) for c, name in enumerate(names) if name in views[i]
    ]
    observed = np.concatenate(
        [np.asarray(views[i][names[c]], dtype=float).ravel() for c, i in pairs]
    )
    seen = np.isfinite(observed)  # NaN: a ChArUco corner not seen (residual 0, no Jacobian)
    evaluate = _reprojection(chart, x0, free, pairs, observed, layout)
    result = solve_lm(evaluate, x0[free], max_nfev)
    x = x0.copy()
    x[free] = result.x
    if not np.all(np.isfinite(x)):
        raise CalibrationError('bundle adjustment diverged')
    residual_pairs = result.fun.reshape(len(pairs), -1, 2)
    seen_pairs = seen.reshape(len(pairs), -1, 2)[..., 0]
    fits = _camera_fits(x, free, names, pairs, residual_pairs, layout, seen_pairs)
    charts = [_T(x[layout.chart(i)][:3], x[layout.chart(i)][3:]) for i in range(layout.views)]
    rms = float(np.sqrt(np.mean(np.sum(residual_pairs[seen_pairs] ** 2, axis=1))))
    rotations = [layout.camera(c).start for c in range(len(names))]
    rotations += [layout.chart(i).start for i in range(layout.views)]
    x = canonical_rotations(x, rotations)
    uncertainty = _uncertainty(
        chart,
        x,
        free,
        evaluate(x[free]),
        names,
        image_sizes,
        pairs,
        charts,
        layout,
        hold_to_charts,
        seen,
    )
    return BundleResult(fits, charts, reference, rms, int(result.nfev), uncertainty)


def _start_distortion(D: Sequence[float], model: str, to_model: str) -> list[float]:
    """A start of ``to_model``'s distortion from a fit's D of ``model``: the same
    coefficients where the models share them (plumb_bob is rational_polynomial with
    k4 = k5 = k6 = 0), else zero (as ``calibrate_camera_lm`` starts an equidistant fit)."""
    size = DISTORTION_SIZES[to_model]
    if (model == 'equidistant') != (to_model == 'equidistant'):
        return [0.0] * size
    return (list(D) + [0.0] * size)[:size]


# --- stages of bundle_adjust ---------------------------------------------------------


class _Layout(NamedTuple):
    """Where each block sits in the parameter vector: intrinsics (fx, fy, cx, cy and the
    distortion of each camera's model), then camera poses (6 each: Rodrigues vector,
    translation), then chart poses (6 per view)."""

    models: tuple[str, ...]  # per camera
    views: int

    @property
    def cameras(self) -> int:
        return len(self.models)

    def size(self, c: int) -> int:
        """How many intrinsic parameters camera ``c`` has: fx, fy, cx, cy, D."""
        return 4 + DISTORTION_SIZES[self.models[c]]

    @property
    def camera_offset(self) -> int:
        return self.intrinsics(self.cameras)

    @property
    def chart_offset(self) -> int:
        return self.camera_offset + 6 * self.cameras

    def intrinsics(self, c: int) -> int:
        return sum(self.size(k) for k in range(c))

    def camera(self, c: int) -> slice:
        """Slice of camera ``c``'s T_camera_ref (rvec, tvec)."""
        return slice(self.camera_offset + 6 * c, self.camera_offset + 6 * c + 6)

    def chart(self, i: int) -> slice:
        """Slice of view ``i``'s T_ref_chart (rvec, tvec)."""
        return slice(self.chart_offset + 6 * i, self.chart_offset + 6 * i + 6)

    def K(self, x: FloatArray, c: int) -> FloatArray:
        a = self.intrinsics(c)
        return np.array([[x[a], 0, x[a + 2]], [0, x[a + 1], x[a + 3]], [0, 0, 1.0]])

    def D(self, x: FloatArray, c: int) -> FloatArray:
        a = self.intrinsics(c)
        return x[a + 4 : a + self.size(c)].copy()


def _start_camera_poses_from_known_charts(
    names: Sequence[str],
    views: Views,
    known: Sequence[FloatArray | None],
    T_camera_chart: Sequence[Mapping[str, FloatArray]],
) -> dict[str, FloatArray]:
    """{name: T_camera_ref} with ref = base_link: the mean over the views with a known
    chart pose that the camera saw."""
    T_camera_ref = {}
    for name in names:
        samples = [
            T_camera_chart[i][name] @ invert_transform(T_ref_chart)
            for i in range(len(views))
            if (T_ref_chart := known[i]) is not None and name in views[i]
        ]
        if not samples:
            raise CalibrationError(f'{name} never saw the chart in a view with a target pose')
        T_camera_ref[name] = _mean_transform(samples)
    return T_camera_ref


def _start_camera_poses_from_reference(
    names: Sequence[str], views: Views, T_camera_chart: Sequence[Mapping[str, FloatArray]]
) -> dict[str, FloatArray]:
    """{name: T_camera_ref} with ref = the first camera (identity): the mean over the views
    that the camera saw together with the reference."""
    reference = names[0]
    T_camera_ref = {reference: np.eye(4)}
    for name in names[1:]:
        samples = [
            T_camera_chart[i][name] @ invert_transform(T_camera_chart[i][reference])
            for i in range(len(views))
            if name in views[i] and reference in views[i]
        ]
        if not samples:
            raise CalibrationError(f'{name} never saw the chart together with {reference}')
        T_camera_ref[name] = _mean_transform(samples)
    return T_camera_ref


def _start_chart_poses(
    views: Views,
    known: Sequence[FloatArray | None],
    T_camera_ref: Mapping[str, FloatArray],
    T_camera_chart: Sequence[Mapping[str, FloatArray]],
) -> list[FloatArray]:
    """[T_ref_chart] per view: the known pose, else the mean over the cameras that saw it."""
    T_ref_chart = []
    for i, view in enumerate(views):
        if known[i] is not None:
            T_ref_chart.append(np.asarray(known[i], dtype=float))
            continue
        samples = [invert_transform(T_camera_ref[n]) @ T_camera_chart[i][n] for n in view]
        T_ref_chart.append(_mean_transform(samples))
    return T_ref_chart


def _parameter_vector(
    names: Sequence[str],
    intrinsics: Intrinsics,
    T_camera_ref: Mapping[str, FloatArray],
    T_ref_chart: Sequence[FloatArray],
) -> FloatArray:
    """The start x0 in the order of :class:`_Layout`."""
    x0: list[float] = []
    for name in names:
        K, D = intrinsics[name]
        x0 += [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *D]
    for name in names:
        x0 += [*np.concatenate(_rt(T_camera_ref[name]))]
    for T in T_ref_chart:
        x0 += [*np.concatenate(_rt(T))]
    return np.array(x0, dtype=float)


def _free_parameters(
    size: int,
    layout: _Layout,
    known: Sequence[FloatArray | None],
    has_known: bool,
    fit_tangential: bool,
    fit_k3: bool,
) -> BoolArray:
    """(size,) bool: the parameters the adjustment moves."""
    free = np.ones(size, dtype=bool)
    for c, model in enumerate(layout.models):
        if model != 'equidistant':  # k1, k2, p1, p2, k3 (, k4, k5, k6)
            a = layout.intrinsics(c)
            free[a + 6 : a + 8] = fit_tangential
            free[a + 8] = fit_k3 or model == 'rational_polynomial'
    if not has_known:
        free[layout.camera(0)] = False  # the reference camera is the frame
    for i in range(layout.views):
        if known[i] is not None:
            free[layout.chart(i)] = False
    return free


def _reprojection(
    chart: FloatArray,
    x0: FloatArray,
    free: BoolArray,
    pairs: Sequence[tuple[int, int]],
    observed: FloatArray,
    layout: _Layout,
) -> Callable[[FloatArray], tuple[FloatArray, FloatArray]]:
    """evaluate(xf) -> (residuals [px], Jacobian w.r.t. the free parameters) over every
    (camera, view) pair's corners; the last evaluation is cached, as least_squares asks
    for the residuals and the Jacobian at the same point."""
    n2 = 2 * len(chart)
    cache: dict[bytes, tuple[FloatArray, FloatArray]] = {}

    def evaluate(xf: FloatArray) -> tuple[FloatArray, FloatArray]:
        key = xf.tobytes()
        if key in cache:
            return cache[key]
        x = x0.copy()
        x[free] = xf
        residuals = np.empty(len(pairs) * n2)
        J = np.zeros((len(pairs) * n2, len(x)))
        for row, (c, i) in enumerate(pairs):
            rows = slice(row * n2, (row + 1) * n2)
            residuals[rows] = _pair_reprojection(chart, x, c, i, layout, observed[rows], J[rows])
        missing = ~np.isfinite(residuals)
        residuals[missing] = 0.0
        J[missing] = 0.0
        cache.clear()
        cache[key] = (residuals, J[:, free])
        return cache[key]

    return evaluate


def _pair_reprojection(
    chart: FloatArray,
    x: FloatArray,
    c: int,
    i: int,
    layout: _Layout,
    observed: FloatArray,
    J: FloatArray,
) -> np.ndarray:
    """Residuals (2N,) [px] of camera ``c`` in view ``i``; fills their Jacobian rows ``J``
    (2N, len(x), zero on entry) in place: ``project_points``' derivatives chained
    through ``cv2.composeRT``'s."""
    a = layout.intrinsics(c)
    cam = x[layout.camera(c)]
    board = x[layout.chart(i)]
    r3, t3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
        board[:3], board[3:], cam[:3], cam[3:]
    )
    uv, Jp = project_points(chart, r3, t3, layout.K(x, c), layout.D(x, c), layout.models[c])
    residuals = uv.ravel() - observed
    J_rt = Jp[:, :6]
    J[:, a : a + layout.size(c)] = Jp[:, 6:]
    J[:, layout.chart(i)] = J_rt @ np.block([[dr3dr1, dr3dt1], [dt3dr1, dt3dt1]])
    J[:, layout.camera(c)] = J_rt @ np.block([[dr3dr2, dr3dt2], [dt3dr2, dt3dt2]])
    return residuals


def _camera_fits(
    x: FloatArray,
    free: BoolArray,
    names: Sequence[str],
    pairs: Sequence[tuple[int, int]],
    residual_pairs: FloatArray,
    layout: _Layout,
    seen_pairs: npt.NDArray[np.bool_],
) -> dict[str, CameraFit]:
    """{name: CameraFit} from the adjusted x; ``residual_pairs`` (pairs, N, 2) [px] of
    which ``seen_pairs`` (pairs, N) were observed. A fit's ``parameters`` are its free
    intrinsics and 6 for its pose (held or not: the count ``calibrate_camera_lm`` gives a
    camera, so ``select_rig_models``' BIC compares the two alike).

    Raises:
        CalibrationError: a camera's focal length came out negative.
    """
    fits: dict[str, CameraFit] = {}
    for c, name in enumerate(names):
        K = layout.K(x, c)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f'{name}: bundle adjustment gave a negative focal length')
        pose = x[layout.camera(c)]
        T_camera = _T(pose[:3], pose[3:])
        mine = np.concatenate(
            [residual_pairs[k][seen_pairs[k]] for k, (cc, _) in enumerate(pairs) if cc == c]
        )
        a = layout.intrinsics(c)
        fits[name] = CameraFit(
            K,
            layout.D(x, c),
            invert_transform(T_camera),
            float(np.sqrt(np.mean(np.sum(mine**2, axis=1)))),
            len(mine),
            {},
            model=layout.models[c],
            parameters=int(free[a : a + layout.size(c)].sum()) + 6,
        )
    return fits


def _uncertainty(
    chart: FloatArray,
    x: FloatArray,
    free: BoolArray,
    final: tuple[FloatArray, FloatArray],
    names: Sequence[str],
    image_sizes: Mapping[str, tuple[int, int]],
    pairs: Sequence[tuple[int, int]],
    T_ref_chart: Sequence[FloatArray],
    layout: _Layout,
    hold_to_charts: bool,
    observed_rows: npt.NDArray[np.bool_],
) -> Uncertainty:
    """The adjusted rig's :class:`Uncertainty` from the final residuals and Jacobian (the
    chart poses' uncertainty is part of the covariance the cameras' block is taken from);
    the points held fixed in base_link when a chart pose is known, else to the charts
    (``hold_to_charts``) or in the reference camera's frame."""
    # Each camera's view its own noise level (residuals are in pair order, 2N each).
    groups = np.repeat(np.arange(len(pairs)), 2 * len(chart))
    if not np.all(observed_rows):  # leave out a ChArUco view's corners not seen
        final = (final[0][observed_rows], final[1][observed_rows])
        groups = groups[observed_rows]
    covariance = parameter_covariance(final[1], final[0], groups)
    row = np.full(len(x), -1)
    row[free] = np.arange(int(free.sum()))
    models = {}
    for c, name in enumerate(names):
        a = layout.intrinsics(c)
        pose = x[layout.camera(c)]
        T_camera_ref = _T(pose[:3], pose[3:])
        seen = np.concatenate(
            [
                chart @ T[:3, :3].T + T[:3, 3]
                for T in (T_camera_ref @ T_ref_chart[i] for cc, i in pairs if cc == c)
            ]
        )
        index = np.concatenate(
            [
                np.arange(layout.camera(c).start, layout.camera(c).stop),
                np.arange(a, a + layout.size(c)),
            ]
        )
        models[name] = RigCamera(
            PinholeCamera(
                *image_sizes[name],
                layout.K(x, c),
                layout.D(x, c),
                invert_transform(T_camera_ref),
                layout.models[c],
            ),
            working_range(seen),
            row[index],
        )
    chart_rows = [
        row[np.arange(layout.chart(i).start, layout.chart(i).stop)] for i in range(layout.views)
    ]
    # A known chart pose: base_link, a physical frame.
    if not hold_to_charts or any((rows < 0).all() for rows in chart_rows):
        return rig_uncertainty(models, covariance)
    return rig_uncertainty(models, covariance, charts=ChartPoses(T_ref_chart, chart_rows))
