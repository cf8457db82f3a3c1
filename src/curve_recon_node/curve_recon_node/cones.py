"""Cones over image curves and 3D curve reconstruction by intersecting them (ALGORITHMS §2.3).

A view is ``CurveView(coefficients, R_camera_base, centre_base)``: the unit-norm image curve
a (in normalised coordinates, f = 1, see ``algebraic_curves``), the rotation taking base
vectors to the camera optical frame, and the optical centre in base [m]. Its cone is

    G(x) = sum_jl a_jl x1^j x2^l x3^(n - j - l),   x~ = R_camera_base (x - centre_base),

the homogenisation of g (§2.3 step 2): G(x) = x3^n g(x1/x3, x2/x3). G is in [m^n].

Two solvers, both ordered by the image-1 sample each point came from:

- ``reconstruct_ray_roots`` (``method: ray_roots``): the real roots of G2 along each
  image-1 ray;
- ``reconstruct_cone_lsq`` (the thesis's ``f_min``): minima of G1^2 + G2^2 from seeds on the
  image-1 rays.

Both select among candidates with a third view (Sampson distance to its curve, ``tol3`` in
normalised image units = pixels / f). With two views a conic's ray meets the second cone at
the true point and at a point of a 'ghost' conic (A3.17), so only unambiguous rays are kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, TypedDict

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from curve_recon_node.algebraic_curves import (
    IntArray,
    check_coefficients,
    monomial_exponents,
    sampson_distance,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray


class CurveView(NamedTuple):
    """One calibrated view of the curve (a plain tuple of the three also works)."""

    coefficients: np.ndarray  # (M,) unit-norm image curve, normalised coordinates
    R_camera_base: np.ndarray  # (3, 3)
    centre_base: np.ndarray  # (3,) [m]


# A CurveView, or a plain (coefficients, R_camera_base, centre_base) tuple of array-likes
ViewLike = tuple[npt.ArrayLike, npt.ArrayLike, npt.ArrayLike]


class SelectionInfo(TypedDict):
    """The info dict of the reconstructions (see ``reconstruct_ray_roots``)."""

    sample_index: IntArray  # (K,) the image-1 sample of each point
    n_samples: int
    n_candidates: int
    n_without_candidates: int
    n_rejected_view3: int
    n_ambiguous: int


def _homogeneous_exponents(degree: int) -> IntArray:
    """(M, 3) exponents (j, l, n - j - l) of x1^j x2^l x3^k, in the order of the 2D ones."""
    jl = monomial_exponents(degree)
    return np.column_stack([jl, degree - jl.sum(axis=1)])


def _to_camera(
    R_camera_base: npt.ArrayLike, centre_base: npt.ArrayLike, points_base: npt.ArrayLike
) -> FloatArray:
    points_base = np.asarray(points_base, dtype=float)
    if points_base.ndim != 2 or points_base.shape[1] != 3:
        raise InvalidInput(
            f'points_base: expected shape (N, 3), got {points_base.shape}',
            key='points_base',
            value=points_base.shape,
        )
    return (points_base - np.asarray(centre_base, dtype=float)) @ np.asarray(R_camera_base).T


def cone_value(
    a: npt.ArrayLike,
    degree: int,
    R_camera_base: npt.ArrayLike,
    centre_base: npt.ArrayLike,
    points_base: npt.ArrayLike,
) -> FloatArray:
    """Cone polynomial G at (N, 3) base points, shape (N,) [m^degree]."""
    a = check_coefficients(a, degree)
    x = _to_camera(R_camera_base, centre_base, points_base)
    return np.prod(x[:, None, :] ** _homogeneous_exponents(degree), axis=2) @ a


def cone_gradient(
    a: npt.ArrayLike,
    degree: int,
    R_camera_base: npt.ArrayLike,
    centre_base: npt.ArrayLike,
    points_base: npt.ArrayLike,
) -> FloatArray:
    """Gradient of G with respect to the base point, shape (N, 3) [m^(degree - 1)]."""
    a = check_coefficients(a, degree)
    x = _to_camera(R_camera_base, centre_base, points_base)
    exponents = _homogeneous_exponents(degree)
    grad_camera = np.empty_like(x)
    for axis in range(3):
        lowered = exponents.copy()
        lowered[:, axis] = np.maximum(lowered[:, axis] - 1, 0)  # factor 0 where it was 0
        grad_camera[:, axis] = (exponents[:, axis] * np.prod(x[:, None, :] ** lowered, axis=2)) @ a
    return grad_camera @ np.asarray(R_camera_base)


def _view(view: ViewLike, degree: int) -> CurveView:
    a, R, c = view
    R = np.asarray(R, dtype=float)
    c = np.asarray(c, dtype=float)
    if R.shape != (3, 3) or c.shape != (3,):
        raise InvalidInput(
            f'view: expected R_camera_base (3, 3) and centre_base (3,), got '
            f'{R.shape} and {c.shape}',
            key='view',
            value=(R.shape, c.shape),
        )
    return CurveView(check_coefficients(a, degree), R, c)


def _camera_xy_depth(view: CurveView, points_base: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Normalised image coordinates (N, 2) and depth (N,) [m] of base points in a view."""
    x = _to_camera(view.R_camera_base, view.centre_base, points_base)
    with np.errstate(divide='ignore', invalid='ignore'):
        return x[:, :2] / x[:, 2:], x[:, 2]


def _third_view_distance(view3: CurveView, degree: int, points_base: FloatArray) -> FloatArray:
    """Sampson distance of the points' projections to view 3's curve; inf behind it."""
    xy, depth = _camera_xy_depth(view3, points_base)
    distance = np.full(len(points_base), np.inf)
    front = depth > 0
    distance[front] = sampson_distance(view3.coefficients, xy[front], degree)
    return np.nan_to_num(distance, nan=np.inf)


def _rays_base(view1: CurveView, samples_xy1: npt.ArrayLike) -> FloatArray:
    """Unit-depth ray directions R1^T (X, Y, 1) of (N, 2) image-1 samples, (N, 3)."""
    samples_xy1 = np.asarray(samples_xy1, dtype=float)
    if samples_xy1.ndim != 2 or samples_xy1.shape[1] != 2:
        raise InvalidInput(
            f'samples_xy1: expected shape (N, 2), got {samples_xy1.shape}',
            key='samples_xy1',
            value=samples_xy1.shape,
        )
    return np.column_stack([samples_xy1, np.ones(len(samples_xy1))]) @ view1.R_camera_base


def _select(
    candidates: Sequence[FloatArray], view3: CurveView | None, degree: int, tol3: float
) -> tuple[FloatArray, SelectionInfo]:
    """Pick one point per sample from ``candidates`` (list of (K_i, 3) arrays).

    Returns (points (K, 3), info dict)."""
    points: list[FloatArray] = []
    index: list[int] = []
    n_rejected = n_ambiguous = 0
    for i, cands in enumerate(candidates):
        if len(cands) == 0:
            continue
        if view3 is not None:
            distance = _third_view_distance(view3, degree, cands)
            best = int(np.argmin(distance))
            if distance[best] < tol3:
                points.append(cands[best])
                index.append(i)
            else:
                n_rejected += 1
        elif len(cands) == 1:
            points.append(cands[0])
            index.append(i)
        else:
            n_ambiguous += 1
    info: SelectionInfo = {
        'sample_index': np.array(index, dtype=int),
        'n_samples': len(candidates),
        'n_candidates': sum(len(c) for c in candidates),
        'n_without_candidates': sum(len(c) == 0 for c in candidates),
        'n_rejected_view3': n_rejected,
        'n_ambiguous': n_ambiguous,
    }
    return np.array(points).reshape(-1, 3), info


def reconstruct_ray_roots(
    view1: ViewLike,
    view2: ViewLike,
    view3: ViewLike | None = None,
    *,
    degree: int,
    samples_xy1: npt.ArrayLike,
    tol3: float = 1e-3,
    imag_tol: float = 1e-7,
) -> tuple[FloatArray, SelectionInfo]:
    """Reconstruct curve points from the real roots of G2 along image-1 rays.

    For each image-1 sample (X, Y) the ray x(s) = c1 + s R1^T (X, Y, 1) lies on cone 1 and s
    is the camera-1 depth [m]. h(s) = G2(x(s)) is a polynomial of degree <= n, fitted
    exactly from n + 1 evaluations (s = 0..n); its real roots (|Im| <= imag_tol (1 + |Re|))
    with s > 0 and positive camera-2 depth are the candidates.

    Args:
        view1, view2, view3: ``CurveView`` (or (a, R_camera_base, centre_base) tuples);
            view3 is optional.
        degree: n, the degree of the image curves.
        samples_xy1: (N, 2) normalised image-1 points, ideally on curve 1.
        tol3: third-view threshold on the Sampson distance [normalised image units].
        imag_tol: relative imaginary part below which a root counts as real.

    Returns:
        points_base (K, 3) [m] ordered by sample, and an info dict: ``sample_index`` (K,)
        the image-1 sample of each point, ``n_samples``, ``n_candidates``,
        ``n_without_candidates``, ``n_rejected_view3`` (samples whose best candidate failed
        view 3) and ``n_ambiguous`` (two views only: samples with several candidates,
        dropped).
    """
    view1, view2 = _view(view1, degree), _view(view2, degree)
    view3 = None if view3 is None else _view(view3, degree)
    rays = _rays_base(view1, samples_xy1)
    nodes = np.arange(degree + 1.0)  # s values; exact for a degree-n polynomial
    points = view1.centre_base + nodes[:, None, None] * rays  # (n + 1, N, 3)
    h = cone_value(
        view2.coefficients, degree, view2.R_camera_base, view2.centre_base, points.reshape(-1, 3)
    ).reshape(len(nodes), -1)
    coefficients = np.linalg.solve(np.vander(nodes, increasing=True), h)  # (n + 1, N)
    candidates = []
    for ray, c in zip(rays, coefficients.T):
        c = np.polynomial.polynomial.polytrim(c, 1e-12 * np.abs(c).max())
        roots = np.polynomial.polynomial.polyroots(c) if len(c) > 1 else np.empty(0)
        real = np.abs(roots.imag) <= imag_tol * (1 + np.abs(roots.real))
        s = np.unique(roots.real[real & (roots.real > 0)])
        cands = view1.centre_base + s[:, None] * ray
        candidates.append(cands[_camera_xy_depth(view2, cands)[1] > 0])
    return _select(candidates, view3, degree, tol3)


def reconstruct_cone_lsq(
    view1: ViewLike,
    view2: ViewLike,
    view3: ViewLike | None = None,
    *,
    degree: int,
    samples_xy1: npt.ArrayLike,
    seed_depths: Sequence[float] = (0.5, 1.0, 2.0, 4.0),
    eps_F: float = 1e-20,
    dedup_tol: float = 1e-6,
    tol3: float = 1e-3,
) -> tuple[FloatArray, SelectionInfo]:
    """Reconstruct curve points by minimising F = G1^2 + G2^2 (the thesis's ``f_min``).

    Seeds are s R1^T (X, Y, 1) + c1 for each image-1 sample and each depth s in
    ``seed_depths`` [m]. Each seed is refined by ``scipy.optimize.least_squares``
    (Levenberg-Marquardt, analytic Jacobian) on the residual (G1, G2); minima with
    F < ``eps_F`` [m^(2n)] and positive depth in cameras 1 and 2 are kept, and minima
    closer than ``dedup_tol`` [m] to one already kept for the same sample are dropped.
    Then, as in ``reconstruct_ray_roots``, view 3 picks one point per sample (with two
    views only samples whose seeds all reach one minimum are kept). Minima need not lie on
    the seed's ray, only on S1 ∩ S2 (the curve or, for conics, the ghost conic). Near
    epipolar tangencies S1 and S2 touch, F is flat across the curve and view 3 rejects the
    minima; ``reconstruct_ray_roots`` has no such problem.

    Returns points_base (K, 3) [m] and the same info dict as ``reconstruct_ray_roots``.
    """
    view1, view2 = _view(view1, degree), _view(view2, degree)
    view3 = None if view3 is None else _view(view3, degree)
    rays = _rays_base(view1, samples_xy1)
    cones = (view1, view2)

    # (G1, G2, 0): the zero row lets MINPACK's Levenberg-Marquardt (which needs as many
    # residuals as unknowns) take minimum-norm steps towards S1 ∩ S2 from the seed
    def residual(x: FloatArray) -> FloatArray:
        return np.array(
            [
                cone_value(v.coefficients, degree, v.R_camera_base, v.centre_base, x[None])[0]
                for v in cones
            ]
            + [0.0]
        )

    def jacobian(x: FloatArray) -> FloatArray:
        return np.vstack(
            [
                cone_gradient(v.coefficients, degree, v.R_camera_base, v.centre_base, x[None])
                for v in cones
            ]
            + [np.zeros((1, 3))]
        )

    candidates = []
    for ray in rays:
        kept: list[FloatArray] = []
        for s in seed_depths:
            result = least_squares(
                residual,
                view1.centre_base + s * ray,
                jac=jacobian,
                method='lm',
                xtol=1e-15,
                ftol=1e-15,
                gtol=1e-15,
            )
            x = result.x
            if 2 * result.cost >= eps_F or any(
                _camera_xy_depth(v, x[None])[1][0] <= 0 for v in cones
            ):
                continue
            if all(np.linalg.norm(x - k) > dedup_tol for k in kept):
                kept.append(x)
        candidates.append(np.array(kept).reshape(-1, 3))
    return _select(candidates, view3, degree, tol3)


def fit_plane(points: npt.ArrayLike) -> tuple[FloatArray, float]:
    """Unit normal (3,) and offset d of the SVD plane n.x + d = 0 through (N, 3) points."""
    points = np.asarray(points, dtype=float)
    centroid = points.mean(axis=0)
    normal = np.linalg.svd(points - centroid, full_matrices=False)[2][-1]
    return normal, -normal @ centroid


def plane_angle_error_deg(true_points: npt.ArrayLike, reconstructed: npt.ArrayLike) -> float:
    """Angle [deg] between the SVD planes of (N, 3) true and (K, 3) reconstructed points
    (§2.5, |cos delta|, computed as atan2(|n1 x n2|, |n1 . n2|) for accuracy near 0)."""
    n1, _ = fit_plane(true_points)
    n2, _ = fit_plane(reconstructed)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(n1, n2)), abs(n1 @ n2))))
