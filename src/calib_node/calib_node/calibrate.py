"""Calibration of each camera of the rig from chart corners whose base_link positions are
known (the precision stage): a non-coplanar 3D-2D calibration per camera (the thesis's
setting, ALGORITHMS.md §3), published as plumb_bob. No rclpy.

Methods (``METHODS``):

- ``lm`` (ours, default): normalised DLT (closed form) or the LX-PM GA as the start, then
  Levenberg-Marquardt on the reprojection error over fx, fy, cx, cy, k1, k2 (p1, p2, k3
  optional) and the camera pose, with OpenCV's analytic projection Jacobian. Every camera
  sees its own points in base_link, so the joint problem over the rig is block diagonal:
  solving it camera by camera gives the same optimum.
- ``lxpm_ga`` (the thesis): the seed camera model with f = 1 (so Nx, Ny are fx, fy in
  px and k is the normalised kappa), LX-PM GA over the stereo pair jointly (24 genes,
  (4.3.2)) and over aux alone, then the seed's network refinement per camera; the
  division coefficient is converted to plumb_bob k1, k2 (``division_to_plumb_bob``).
- ``opencv``: ``cv2.calibrateCamera`` on the same points as one non-planar view, from the
  DLT intrinsic guess (the reference).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
import scipy.linalg
from scipy.optimize import OptimizeResult, least_squares

from calib_node.lxpm_ga import LX_DRAWS, LX_VARIANTS, lxpm_ga, rig_objective
from calib_node.seed_calibration import dlt_camera
from calib_node.seed_camera import identifiable
from calib_node.thesis import NETWORK_ACCEPT, NETWORK_WEIGHTS, network_refine
from calib_node.uncertainty import (
    RigCamera,
    Uncertainty,
    canonical_rotations,
    parameter_covariance,
    rig_uncertainty,
    working_range,
)
from vgm_common.camera_model import DISTORTION_SIZES, PinholeCamera, project_points
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.geometry import FloatArray, invert_transform, make_transform
from vgm_common.settings import setting

METHODS = ('lm', 'lxpm_ga', 'opencv')
LM_STARTS = ('dlt', 'ga')
FIT_MODELS = ('plumb_bob', 'rational_polynomial', 'equidistant')  # what lm fits
# calib_node's distortion_model: one of FIT_MODELS, or auto (the best by BIC)
MODEL_CHOICES = ('auto', *FIT_MODELS)

# {name: (points_base (N, 3) [m], pixels (N, 2) [px], (width, height) [px])}
Observations = Mapping[str, tuple[FloatArray, FloatArray, tuple[int, int]]]
# (K (3, 3), D (5,), R (3, 3), t (3,)): a camera's world->camera start
CameraStart = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class CalibrationError(VgmError, ValueError):
    """The observations cannot give a calibration (too few, degenerate, diverged)."""


class CameraFit(NamedTuple):
    """One camera's calibration: intrinsics and distortion of ``model``, its pose in
    base_link and the fit's reprojection RMS [px]."""

    K: np.ndarray  # (3, 3) [px]
    D: np.ndarray  # (5,) plumb_bob (k1, k2, p1, p2, k3), or as ``model`` takes it
    T_base_camera: np.ndarray  # (4, 4) optical frame in base_link
    rms_px: float  # reprojection RMS per point (sqrt of the mean squared distance) [px]
    points: int
    std: dict[str, float]  # standard errors of fx, fy, cx, cy [px] (LM, OpenCV; empty for the GA)
    # lm: (10 + len(D))^2 covariance of rvec, tvec (world->camera), fx, fy, cx, cy, D
    # (cv2.projectPoints' order; zero rows for parameters held), else None
    covariance: np.ndarray | None = None
    model: str = 'plumb_bob'  # the distortion model (``FIT_MODELS``)
    parameters: int = 0  # how many parameters the fit estimated (lm; 0: not counted)

    def camera(self, image_size: tuple[int, int]) -> PinholeCamera:
        """The fitted camera for images of ``image_size`` (width, height) [px]: K, D of
        its ``model`` and its pose in base_link."""
        return PinholeCamera(*image_size, self.K, self.D, self.T_base_camera, self.model)


@dataclass(frozen=True)
class GAOptions:
    """Settings of the thesis's method (:func:`calibrate_rig_ga`): the LX-PM GA's
    (:func:`~calib_node.lxpm_ga.lxpm_ga`) and the network refinement's that follows it;
    calib_node's ga.* and network.* parameters."""

    population: int = setting(
        240, 'GA population (thesis 240).', range=(4, 100000), name='ga.population'
    )
    generations: int = setting(
        200, 'GA generations (thesis 200).', range=(1, 100000), name='ga.generations'
    )
    crossover: float = setting(
        0.9,
        'Laplace crossover probability per pair (thesis 0.9).',
        range=(0.0, 1.0),
        name='ga.crossover',
    )
    mutation: float = setting(
        0.005,
        'Power mutation probability per gene (thesis 0.005).',
        range=(0.0, 1.0),
        name='ga.mutation',
    )
    pm_index: float = setting(
        0.25,
        'Power mutation index p, s = s1^(1/p) (not in the thesis; ALGORITHMS.md A4.4) [C].',
        range=(1e-3, 100.0),
        name='ga.pm_index',
    )
    lx_variant: str = setting(
        'printed',
        'Laplace crossover: as printed in the thesis, or the symmetric Laplace quantile (A4.5).',
        choices=LX_VARIANTS,
        name='ga.lx_variant',
    )
    max_distance: float = setting(
        3.0,
        'Bound of the GA translation genes: camera to chart-centroid distance [C].',
        unit='m',
        range=(0.01, 1000.0),
        name='ga.max_distance',
    )
    network_epochs: int = setting(
        3000,
        'Gradient-descent epochs of the thesis network refinement [C].',
        range=(0, 1000000),
        name='network.epochs',
    )
    lx_draw: str = setting(
        'gene',
        'Laplace spread phi drawn per gene (ALGORITHMS.md A4.5) or per parent pair [C].',
        choices=LX_DRAWS,
        name='ga.lx_draw',
    )
    tournament: int = setting(
        3, 'Tournament size of the selection (A4.6) [C].', range=(1, 1000), name='ga.tournament'
    )
    elitism: int = setting(
        1,
        'Best individuals carried over each generation (A4.6) [C].',
        range=(0, 1000),
        name='ga.elitism',
    )
    network_weights: str = setting(
        'structured',
        'structured: train only the entries of D = [A | 0] and B = [R T; 0 1] that stand '
        "for parameters, read out as ALGORITHMS.md 3.5 (D's entries, B's 3x3 block "
        'projected onto SO(3)); free: every weight, read out by RQ of D B (the old '
        'behaviour; it moves the principal point by 1000s of px) [C].',
        choices=NETWORK_WEIGHTS,
        name='network.weights',
    )
    network_accept: str = setting(
        'if_better',
        "if_better: keep the network's camera only if its full-model reprojection RMS is "
        "below the GA camera's, else keep the GA camera; always: keep it [C].",
        choices=NETWORK_ACCEPT,
        name='network.accept',
    )


def solve_lm(
    evaluate: Callable[[FloatArray], tuple[FloatArray, np.ndarray]],
    x0: FloatArray,
    max_nfev: int,
) -> OptimizeResult:
    """Levenberg-Marquardt on ``evaluate(x) -> (residuals, Jacobian)`` from ``x0``, the
    calibrations' tolerances (1e-12 on x, cost and gradient; Jacobian scaling)."""
    return least_squares(
        lambda x: evaluate(x)[0],
        x0,
        jac=lambda x: evaluate(x)[1],
        method='lm',
        x_scale='jac',
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
        max_nfev=max_nfev,
    )


def degeneracy(
    points_base: npt.ArrayLike, min_points: int = 12, min_thickness: float = 0.02
) -> str:
    """Reason why (N, 3) points cannot calibrate a camera, or '' if they can.

    The non-coplanar calibration needs the points to span 3D: the smallest principal
    spread must be at least ``min_thickness`` times the largest (all views on one plane,
    e.g. a chart moved within its plane, give 0).
    """
    points_base = np.asarray(points_base, dtype=float)
    if len(points_base) < min_points:
        return f'{len(points_base)} points, need at least {min_points}'
    spread = np.linalg.svd(points_base - points_base.mean(axis=0), compute_uv=False)
    if spread[-1] < min_thickness * spread[0]:
        return (
            f'degenerate views: all points lie on one plane (thickness '
            f'{spread[-1] / spread[0]:.2g} of the extent, need {min_thickness:g}); '
            'tilt or move the chart along its normal'
        )
    return ''


def _rms(residuals: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.sum(residuals.reshape(-1, 2) ** 2, axis=1))))


def _pose(R: np.ndarray, t: npt.ArrayLike) -> FloatArray:
    """World->camera (R, t) -> T_base_camera."""
    return make_transform(R.T, -R.T @ np.asarray(t, dtype=float).ravel())


def _dlt_start(
    points_base: npt.ArrayLike, pixels: npt.ArrayLike, image_size: tuple[int, int]
) -> CameraStart:
    K, R, t = dlt_camera(points_base, pixels)
    K[0, 1] = 0.0  # no skew in plumb_bob
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError('the closed-form (DLT) start failed')
    return K, np.zeros(5), R, t


def calibrate_camera_lm(
    points_base: npt.ArrayLike,
    pixels: npt.ArrayLike,
    image_size: tuple[int, int],
    start: CameraStart | None = None,
    fit_tangential: bool = True,
    fit_k3: bool = False,
    view_size: int | None = None,
    model: str = 'plumb_bob',
) -> CameraFit:
    """LM calibration of one camera from (N, 3) base_link points and (N, 2) pixels.

    Args:
        image_size: (width, height) [px].
        start: (K, D, R, t) world->camera start; None: the DLT. Its D (plumb_bob) starts
            a rational_polynomial fit (k4..k6 = 0 is the same lens), not an equidistant
            one (from 0).
        fit_tangential: estimate p1, p2 (else 0); fit_k3: estimate k3 (else 0; a
            rational_polynomial fit always estimates k3..k6).
        view_size: the points come in views of this many (each its own noise level in the
            covariance); None: one noise level.
        model: the distortion model (``FIT_MODELS``): plumb_bob, rational_polynomial
            (k1..k6, p1, p2) or equidistant (cv2.fisheye's k1..k4, no tangential terms).

    Returns:
        :class:`CameraFit`.
    """
    points_base = np.ascontiguousarray(points_base, dtype=float)
    pixels = np.asarray(pixels, dtype=float)
    if model not in FIT_MODELS:
        raise InvalidInput(
            f'model: expected one of {", ".join(FIT_MODELS)}, got {model!r}', key='model'
        )
    K, D, R, t = start if start is not None else _dlt_start(points_base, pixels, image_size)
    size = DISTORTION_SIZES[model]
    D_start = [0.0] * size if model == 'equidistant' else (list(np.ravel(D)) + [0.0] * size)
    x0 = np.concatenate(
        [
            cv2.Rodrigues(np.asarray(R, dtype=float))[0].ravel(),
            np.ravel(t),
            [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
            D_start[:size],
        ]
    )
    free = np.ones(10 + size, dtype=bool)
    if model != 'equidistant':
        free[12:14] = fit_tangential
        free[14] = fit_k3 or model == 'rational_polynomial'
    x0[~free] = 0.0
    cache: dict[bytes, tuple[FloatArray, np.ndarray]] = {}  # residuals, Jacobian

    def full(xf: FloatArray) -> FloatArray:
        x = x0.copy()
        x[free] = xf
        return x

    def evaluate(xf: FloatArray) -> tuple[FloatArray, np.ndarray]:
        key = xf.tobytes()
        if key not in cache:
            x = full(xf)
            K = np.array([[x[6], 0, x[8]], [0, x[7], x[9]], [0, 0, 1.0]])
            uv, J = project_points(points_base, x[0:3], x[3:6], K, x[10:], model)
            cache.clear()
            cache[key] = ((uv - pixels).ravel(), J[:, free])
        return cache[key]

    result = solve_lm(evaluate, x0[free], max_nfev=500)
    x = full(result.x)
    if not np.all(np.isfinite(x)) or x[6] <= 0 or x[7] <= 0:
        raise CalibrationError('LM diverged')
    K = np.array([[x[6], 0, x[8]], [0, x[7], x[9]], [0, 0, 1.0]])
    R = cv2.Rodrigues(x[0:3])[0]
    residuals, jacobian = evaluate(canonical_rotations(x, [0])[free])
    covariance = np.zeros((len(x), len(x)))
    groups = None if view_size is None else np.arange(len(residuals)) // (2 * view_size)
    covariance[np.ix_(free, free)] = parameter_covariance(jacobian, residuals, groups)
    std = dict(zip(('fx', 'fy', 'cx', 'cy'), np.sqrt(np.diag(covariance)[6:10]).tolist()))
    return CameraFit(
        K,
        x[10:].copy(),
        _pose(R, x[3:6]),
        _rms(result.fun),
        len(pixels),
        std,
        covariance,
        model,
        int(np.count_nonzero(free)),
    )


def stage_uncertainty(
    fits: Mapping[str, CameraFit], observations: Observations
) -> Uncertainty | None:
    """The :class:`~calib_node.uncertainty.Uncertainty` of cameras calibrated one by one
    on base_link points (independent fits: a block-diagonal covariance); None when a fit
    has no covariance (lxpm_ga, opencv)."""
    if any(fit.covariance is None for fit in fits.values()):
        return None
    models = {}
    blocks: list[np.ndarray] = []
    row = 0
    for name, fit in fits.items():
        assert fit.covariance is not None  # checked above
        T_camera_base = invert_transform(fit.T_base_camera)
        points = observations[name][0] @ T_camera_base[:3, :3].T + T_camera_base[:3, 3]
        models[name] = RigCamera(
            fit.camera(observations[name][2]),
            working_range(points),
            np.arange(row, row + len(fit.covariance)),
        )
        row += len(fit.covariance)
        blocks.append(fit.covariance)
    return rig_uncertainty(models, scipy.linalg.block_diag(*blocks))


def calibrate_camera_opencv(
    points_base: npt.ArrayLike,
    pixels: FloatArray,
    image_size: tuple[int, int],
    fit_tangential: bool = True,
    fit_k3: bool = False,
) -> CameraFit:
    """``cv2.calibrateCamera`` on the points as one non-planar view (DLT intrinsic guess)."""
    points_base = np.asarray(points_base, dtype=float)
    K0 = _dlt_start(points_base, pixels, image_size)[0]
    K0[:2, 2] = np.clip(K0[:2, 2], 0.0, np.asarray(image_size, dtype=float) - 1.0)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    flags |= 0 if fit_tangential else cv2.CALIB_ZERO_TANGENT_DIST
    flags |= 0 if fit_k3 else cv2.CALIB_FIX_K3
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs, std_intrinsics, _, _ = cv2.calibrateCameraExtended(
        [points_base.astype(np.float32).reshape(-1, 1, 3)],
        [np.asarray(pixels, dtype=np.float32).reshape(-1, 1, 2)],
        tuple(int(s) for s in image_size),
        K0,
        np.zeros(5),
        flags=flags,
        criteria=criteria,
    )
    R = cv2.Rodrigues(rvecs[0])[0]
    std = dict(zip(('fx', 'fy', 'cx', 'cy'), std_intrinsics.ravel()[:4].tolist()))
    D = np.array((list(dist.ravel()) + [0.0] * 5)[:5])
    return CameraFit(K, D, _pose(R, tvecs[0]), float(rms), len(pixels), std)


def division_to_plumb_bob(
    kappa: float, max_radius: float, fit_k3: bool = False, samples: int = 200
) -> tuple[FloatArray, float]:
    """plumb_bob radial coefficients closest to the seed's division model (A4.2).

    The division model x_d = x_u / (1 + kappa |x_d|^2) (normalised coordinates) maps the
    undistorted radius r_u to r_d; plumb_bob writes r_d = r_u (1 + k1 r_u^2 + k2 r_u^4
    [+ k3 r_u^6]). We fit k1, k2 (k3) by linear least squares on r_d / r_u - 1 over
    r_u in (0, max_radius] (the image corner's normalised radius), so the two agree over
    the whole image; for small kappa r^2 this tends to k1 = -kappa, k2 = 3 kappa^2.

    Returns:
        (D (5,), largest distortion disagreement over the range, as a normalised radius).
    """
    r_u = np.linspace(max_radius / samples, max_radius, samples)
    from vgm_common.camera_model import division_distorted_radius

    r_d = division_distorted_radius(r_u, kappa)
    powers = 3 if fit_k3 else 2
    A = np.column_stack([r_u ** (2 * (j + 1)) for j in range(powers)])
    coefficients = np.linalg.lstsq(A, r_d / r_u - 1, rcond=None)[0]
    D = np.zeros(5)
    D[0], D[1] = coefficients[0], coefficients[1]
    if fit_k3:
        D[4] = coefficients[2]
    residual = np.max(np.abs(r_u * (1 + A @ coefficients) - r_d))
    return D, float(residual)


def _ga_bounds(
    points_base: FloatArray, image_size: tuple[int, int], max_distance: float
) -> FloatArray:
    """Seed-model bounds [C] for a camera of ``image_size`` seeing points centred at 0."""
    width, height = image_size
    return np.array(
        [
            [0, width],
            [0, height],
            [0.25 * width, 4 * width],
            [0.25 * width, 4 * width],
            [1, 1],
            [0, 1],
            [-np.pi, np.pi],
            [-np.pi, np.pi],
            [-np.pi, np.pi],
            [-max_distance, max_distance],
            [-max_distance, max_distance],
            [0, max_distance],
        ],
        dtype=float,
    )


def calibrate_rig_ga(
    observations: Observations,
    rng: np.random.Generator,
    options: GAOptions | None = None,
    fit_k3: bool = False,
) -> tuple[dict[str, CameraFit], dict[str, FloatArray], dict[str, FloatArray]]:
    """The thesis's method on the rig: {name: (points (N, 3), pixels (N, 2), (w, h))} ->
    ({name: CameraFit}, {name: seed params after the GA}, {name: after the network}).

    Points are shifted to their common centroid first (the translation genes are then
    camera-to-chart offsets, bounded by ``options.max_distance``) [C]. The stereo pair
    ('left', 'right' when both are present) is one 24-gene GA as in (4.3.2); any other
    camera its own 12-gene GA.
    """
    options = options or GAOptions()
    names = list(observations)
    centre = np.mean(np.concatenate([observations[n][0] for n in names]), axis=0)
    groups = [[n for n in ('left', 'right') if n in observations]]
    groups = [g for g in groups if g] + [[n] for n in names if n not in ('left', 'right')]
    fits: dict[str, CameraFit] = {}
    after_ga: dict[str, FloatArray] = {}
    after_network: dict[str, FloatArray] = {}
    for group in groups:
        data = [(observations[n][0] - centre, observations[n][1]) for n in group]
        bounds = np.concatenate(
            [
                _ga_bounds(p, observations[n][2], options.max_distance)
                for n, (p, _) in zip(group, data)
            ]
        )
        result = lxpm_ga(
            rig_objective(data),
            bounds[:, 0],
            bounds[:, 1],
            rng,
            population=options.population,
            generations=options.generations,
            crossover_probability=options.crossover,
            mutation_probability=options.mutation,
            pm_index=options.pm_index,
            lx_variant=options.lx_variant,
            lx_draw=options.lx_draw,
            tournament=options.tournament,
            elitism=options.elitism,
        )
        for c, (name, (points, pixels)) in enumerate(zip(group, data)):
            params = result.best[12 * c : 12 * c + 12]
            after_ga[name] = params
            refined, _ = network_refine(
                params,
                points,
                pixels,
                epochs=options.network_epochs,
                weights=options.network_weights,
                accept=options.network_accept,
            )
            after_network[name] = refined
            ident = identifiable(refined)
            K = np.array([[ident.fx, 0, ident.u0], [0, ident.fy, ident.v0], [0, 0, 1.0]])
            width, height = observations[name][2]
            corner = np.max(
                np.abs(np.array([[0, 0], [width, height]]) - [ident.u0, ident.v0])
                / [ident.fx, ident.fy],
                axis=0,
            )
            D, _ = division_to_plumb_bob(float(ident.kappa), float(np.hypot(*corner)), fit_k3)
            T = ident.T - ident.R @ centre  # back to base_link: R (x - centre) + T
            uv = cv2.projectPoints(
                np.ascontiguousarray(observations[name][0]), cv2.Rodrigues(ident.R)[0], T, K, D
            )[0].reshape(-1, 2)
            fits[name] = CameraFit(
                K, D, _pose(ident.R, T), _rms(uv - observations[name][1]), len(pixels), {}
            )
    return fits, after_ga, after_network


# No corner is located better than this: a fit's residual below it is rounding, not lens
# (noise-free synthetic corners), and must not make a model with more coefficients win.
BIC_NOISE_FLOOR_PX = 1e-4  # [px]


def bic(rss: float, residuals: int, parameters: int) -> float:
    """Schwarz's criterion of a least-squares fit, n ln(RSS / n) + p ln(n) (Gaussian
    residuals of one unknown variance; lower is better), RSS / n at least
    ``BIC_NOISE_FLOOR_PX``^2.

    Args:
        rss: sum of squared residuals [px^2]; residuals: n, residual components;
        parameters: p, the parameters estimated.
    """
    variance = max(rss / residuals, BIC_NOISE_FLOOR_PX**2)
    return float(residuals * np.log(variance) + parameters * np.log(residuals))


def select_by_bic(fits: Sequence[CameraFit]) -> CameraFit:
    """The fit of the lowest :func:`bic` among fits of one camera's same points (e.g.
    one per distortion model), in order (ties: the earlier, i.e. the simpler, when
    given simplest first)."""
    scores = [bic(fit.rms_px**2 * fit.points, 2 * fit.points, fit.parameters) for fit in fits]
    return fits[int(np.argmin(scores))]


def tangential_pays(
    rss_with: float, rss_without: float, residuals: int, cameras: int = 1
) -> bool | np.bool_:
    """Whether fitting p1, p2 lowers the residual enough to be kept (BIC, Schwarz).

    Fitting p1, p2 to a lens without tangential distortion leaves the RMS where it was but
    trades the principal point and the rotation against them (measured on generated rigs:
    cx, cy errors 2-4x, rotations 3x larger). BIC keeps the two parameters per camera only
    when n ln(RSS0 / RSS1) exceeds 2 ln(n) per camera.

    Args:
        rss_with, rss_without: sums of squared residuals [px^2] with and without p1, p2.
        residuals: n, the number of residual components.
    """
    if rss_with <= 0:
        return rss_without > 0
    return residuals * np.log(rss_without / rss_with) > 2 * cameras * np.log(residuals)


def calibrate_camera_models(
    points_base: npt.ArrayLike,
    pixels: npt.ArrayLike,
    image_size: tuple[int, int],
    start: CameraStart | None = None,
    fit_tangential: bool = True,
    fit_k3: bool = False,
    select_model: bool = True,
    view_size: int | None = None,
    distortion_model: str = 'auto',
) -> dict[str, CameraFit]:
    """{model: :func:`calibrate_camera_lm` fit} of ``distortion_model``
    (``MODEL_CHOICES``), or of every model of ``FIT_MODELS`` with ``auto`` and
    ``select_model`` (plumb_bob with ``auto`` alone), simplest first: plumb_bob,
    equidistant, rational_polynomial. Each model's fit is with or without p1, p2 by
    :func:`select_by_bic` when ``fit_tangential`` and ``select_model``. plumb_bob starts
    from ``start``; the others from the plumb_bob fit (its K and pose, and its D for
    rational_polynomial, of which plumb_bob is the case k4 = k5 = k6 = 0).
    """
    if distortion_model != 'auto':
        models: tuple[str, ...] = (distortion_model,)
    else:  # without select_model nothing is chosen: plumb_bob, as fit_tangential says
        models = FIT_MODELS if select_model else ('plumb_bob',)
    tangential = (False, True) if fit_tangential and select_model else (fit_tangential,)

    def fit(model: str, with_tangential: bool, start: CameraStart | None) -> CameraFit:
        return calibrate_camera_lm(
            points_base, pixels, image_size, start, with_tangential, fit_k3, view_size, model
        )

    plumb_bob = select_by_bic([fit('plumb_bob', t, start) for t in tangential])
    fits = {'plumb_bob': plumb_bob} if 'plumb_bob' in models else {}
    T_camera_base = invert_transform(plumb_bob.T_base_camera)
    from_plumb_bob = (plumb_bob.K, plumb_bob.D, T_camera_base[:3, :3], T_camera_base[:3, 3])
    if 'equidistant' in models:
        fits['equidistant'] = fit('equidistant', False, from_plumb_bob)
    if 'rational_polynomial' in models:
        fits['rational_polynomial'] = select_by_bic(
            [fit('rational_polynomial', t, from_plumb_bob) for t in tangential]
        )
    return fits


def select_rig_models(candidates: Mapping[str, Mapping[str, CameraFit]]) -> dict[str, CameraFit]:
    """Each camera's fit among its ``candidates`` {name: {model: fit}} of the lowest BIC;
    left and right share one model, that of the lowest sum of their BICs (their
    rectification needs compatible models: cv2.fisheye rectifies only a fisheye pair).
    Ties keep the earlier model (the simpler, in :func:`calibrate_camera_models`' order)."""

    def score(fit: CameraFit) -> float:
        return bic(fit.rms_px**2 * fit.points, 2 * fit.points, fit.parameters)

    groups = [[n] for n in candidates if n not in ('left', 'right')]
    pair = [n for n in ('left', 'right') if n in candidates]
    fits = {}
    for group in [pair, *groups] if pair else groups:
        models = [m for m in candidates[group[0]] if all(m in candidates[n] for n in group)]
        best = min(models, key=lambda m: sum(score(candidates[n][m]) for n in group))
        fits.update({n: candidates[n][best] for n in group})
    return {n: fits[n] for n in candidates}


class RigResult(NamedTuple):
    """Every camera's fit (:class:`CameraFit`), the method that gave them (``METHODS``)
    and the wall time the calibration took [s]."""

    fits: dict[str, CameraFit]
    method: str
    seconds: float


def calibrate_rig(
    observations: Observations,
    method: str = 'lm',
    seed: int = 0,
    lm_start: str = 'dlt',
    ga: GAOptions | None = None,
    fit_tangential: bool = True,
    fit_k3: bool = False,
    select_model: bool = True,
    view_size: int | None = None,
    distortion_model: str = 'auto',
) -> RigResult:
    """Calibrate every camera of ``observations`` = {name: (points_base (N, 3),
    pixels (N, 2), (width, height))} with ``method`` (``METHODS``). ``select_model``
    (``lm``): p1, p2 are kept per camera only where they pay (:func:`tangential_pays`).
    ``view_size``: points per view (views of one chart; see :func:`calibrate_camera_lm`).
    ``distortion_model`` (``MODEL_CHOICES``; ``lm``, the other methods fit plumb_bob):
    the model fitted, or ``auto``: with ``select_model`` every one of ``FIT_MODELS`` per
    camera, the lowest BIC kept (:func:`select_rig_models`, the rule of p1, p2 extended
    to the models; the stereo pair shares its model), without it plumb_bob.

    Raises:
        CalibrationError: a camera's points are too few or degenerate, or a fit failed.
    """
    if method not in METHODS:
        raise InvalidInput(f'method: expected one of {METHODS}, got {method!r}', key='method')
    if distortion_model not in MODEL_CHOICES:
        raise InvalidInput(
            f'distortion_model: expected one of {", ".join(MODEL_CHOICES)}, got '
            f'{distortion_model!r}',
            key='distortion_model',
        )
    for name, (points, _, _) in observations.items():
        reason = degeneracy(points)
        if reason:
            raise CalibrationError(f'{name}: {reason}')
    started = time.perf_counter()
    rng = np.random.default_rng(seed)
    if method == 'lxpm_ga':
        fits = calibrate_rig_ga(observations, rng, ga, fit_k3)[0]
    elif method == 'opencv':
        fits = {
            name: calibrate_camera_opencv(p, uv, size, fit_tangential, fit_k3)
            for name, (p, uv, size) in observations.items()
        }
    else:
        starts: dict[str, CameraStart | None] = {name: None for name in observations}
        if lm_start == 'ga':
            for name, fit in calibrate_rig_ga(observations, rng, ga, fit_k3)[0].items():
                T_camera_base = np.linalg.inv(fit.T_base_camera)
                starts[name] = (fit.K, fit.D, T_camera_base[:3, :3], T_camera_base[:3, 3])
        fits = select_rig_models(
            {
                name: calibrate_camera_models(
                    p,
                    uv,
                    size,
                    starts[name],
                    fit_tangential,
                    fit_k3,
                    select_model,
                    view_size,
                    distortion_model,
                )
                for name, (p, uv, size) in observations.items()
            }
        )
    return RigResult(fits, method, time.perf_counter() - started)
