"""The thesis's cone intersection (``method: cone_lsq``; ALGORITHMS §2.3 steps 3-4, the
spec's ``f_min``): the 3D curve as the minima of F = G1^2 + G2^2, the squared cone
polynomials of views 1 and 2, from seeds on the view-1 rays. It runs on the node's
piecewise curves (``piecewise``), with the same supports and view-3 selection as ours,
``piecewise.reconstruct_ray_roots``, which is exact and faster: it needs no seeds and
finds every intersection, where a minimisation may stop at a local minimum.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import numpy as np
import numpy.typing as npt

from curve_recon_node.algebraic_curves import IntArray, monomial_exponents
from curve_recon_node.piecewise import (
    CandidateInfo,
    View,
    cone_values,
    intersect_cones,
    view1_rays,
)
from vgm_common.geometry import FloatArray


def reconstruct_cone_lsq(
    view1: View,
    view2: View,
    view3: View | None = None,
    *,
    samples: npt.ArrayLike | None = None,
    tol3_px: float = 2.0,
    support_px: float = 3.0,
    on_curve_px: float = 0.5,
    distinct_m: float = 2e-3,
    seed_depths: Sequence[float] | FloatArray = (0.25, 0.5, 1.0, 2.0, 4.0),
    iterations: int = 25,
    max_depth: float = np.inf,
) -> tuple[FloatArray, CandidateInfo]:
    """``piecewise.intersect_cones`` with the thesis's solver, ``cone_lsq_candidates``
    (``method: cone_lsq``), from every view-1 chain point by default (ours: the measured
    ones); view 3's chain support is the selection's default (3 px) whatever
    ``support_px`` the solver is given. Arguments as there and in
    ``cone_lsq_candidates``."""
    samples = np.arange(len(view1.curve.xy)) if samples is None else np.asarray(samples)
    solver = partial(
        cone_lsq_candidates,
        support_px=support_px,
        on_curve_px=on_curve_px,
        seed_depths=seed_depths,
        iterations=iterations,
        max_depth=max_depth,
    )
    return intersect_cones(
        view1, view2, view3, solver, samples=samples, tol3_px=tol3_px, distinct_m=distinct_m
    )


def cone_lsq_candidates(
    view1: View,
    view2: View,
    samples: IntArray,
    *,
    support_px: float = 3.0,
    on_curve_px: float = 0.5,
    seed_depths: Sequence[float] | FloatArray = (0.25, 0.5, 1.0, 2.0, 4.0),
    iterations: int = 25,
    max_depth: float = np.inf,
) -> tuple[IntArray, FloatArray]:
    """The thesis's ``CandidateSolver``: minima of F = G1^2 + G2^2 from seeds on the
    view-1 rays of chain points ``samples``.

    For each view-1 chain point, its owning view-1 piece's cone G1 and every view-2
    piece's cone G2 are paired; each pair is refined from each seed s R1^T (X, Y, 1) + c1,
    s in ``seed_depths`` [m], by damped minimum-norm Gauss-Newton steps (Levenberg-
    Marquardt on the residual (G1, G2), batched over all seeds). A minimum is a candidate
    if it lies in front of both cameras (shallower than ``max_depth`` [m] in view 1), its
    projections are within ``on_curve_px`` of both curves and inside the two pieces'
    supports (within ``support_px`` of their chain points). Returns (position in
    ``samples`` of each candidate's view-1 chain point (C,), points_base (C, 3)).
    """
    rays = view1_rays(view1, samples)
    c1, c2 = view1.curve, view2.curve
    degree = c1.degree
    n_seeds = len(seed_depths)
    # pair each ray only with the view-2 pieces its epipolar line crosses (within
    # support_px of one of the piece's chain points): the others cannot meet it
    near = _epipolar_distance_px(view1, view2, rays) <= support_px  # (R, N2)
    pair_ray, pair_piece = np.nonzero((near.astype(float) @ c2.member.T.astype(float)) > 0)
    ray_index = np.repeat(pair_ray, n_seeds)
    piece2 = np.repeat(pair_piece, n_seeds)
    seeds = np.tile(np.asarray(seed_depths, dtype=float), len(pair_ray))
    piece1 = c1.owner[samples][ray_index]
    a1, a2 = c1.coefficient_matrix[piece1], c2.coefficient_matrix[piece2]
    x = view1.centre_base + seeds[:, None] * rays[ray_index]

    def residual_and_jacobian(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        x1 = (x - view1.centre_base) @ view1.R_camera_base.T
        x2 = (x - view2.centre_base) @ view2.R_camera_base.T
        r = np.column_stack([cone_values(a1, degree, x1), cone_values(a2, degree, x2)])
        J = np.stack(
            [
                cone_gradients(a1, degree, x1, view1.R_camera_base),
                cone_gradients(a2, degree, x2, view2.R_camera_base),
            ],
            axis=1,
        )
        return r, J

    x = _minimise(residual_and_jacobian, x, iterations)
    _, depth1 = view1.project(x)
    _, depth2 = view2.project(x)
    keep = (
        (depth1 > 0)
        & (depth1 < max_depth)
        & (depth2 > 0)
        & (view1.distance_px(x) <= on_curve_px)
        & (view2.distance_px(x) <= on_curve_px)
        & view2.in_support(x, piece2, support_px)
        & view1.in_support(x, piece1, support_px)
    )
    # a minimum need not lie on its seed's ray: file it under the view-1 chain point its
    # projection is nearest to, which keeps the output ordered along the curve
    chain_index, _ = c1.nearest(view1.project(x[keep])[0])
    position = np.full(len(c1.xy), -1)
    position[samples] = np.arange(len(samples))
    sample_of = position[chain_index]
    inside = sample_of >= 0
    return sample_of[inside], x[keep][inside]


def _minimise(
    residual_and_jacobian: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
    x: FloatArray,
    iterations: int,
) -> FloatArray:
    """Levenberg-Marquardt on Q independent problems at once: points x (Q, 3), residuals
    (Q, 2) and Jacobians (Q, 2, 3); minimum-norm damped steps, a step kept only where it
    lowers that problem's cost."""
    x = x.copy()
    damping = np.full(len(x), 1e-3)
    r, J = residual_and_jacobian(x)
    cost = np.sum(r**2, axis=1)
    for _ in range(iterations):
        # minimum-norm damped step dx = -J^T (J J^T + mu I)^-1 r (2 residuals, 3 unknowns)
        JJt = J @ np.swapaxes(J, 1, 2)
        mu = (damping * np.trace(JJt, axis1=1, axis2=2))[:, None, None] * np.eye(2) + 1e-300
        with np.errstate(all='ignore'):
            step = -np.einsum(
                'qij,qj->qi',
                np.swapaxes(J, 1, 2),
                np.linalg.solve(JJt + mu, r[:, :, None])[:, :, 0],
            )
        trial = x + np.nan_to_num(step)
        r_t, J_t = residual_and_jacobian(trial)
        cost_t = np.sum(r_t**2, axis=1)
        better = cost_t < cost
        x[better], r[better], J[better], cost[better] = (
            trial[better],
            r_t[better],
            J_t[better],
            cost_t[better],
        )
        damping = np.where(better, damping * 0.3, damping * 10.0)
        damping = np.clip(damping, 1e-12, 1e6)
    return x


def cone_gradients(
    coefficients: FloatArray, degree: int, x_camera: FloatArray, R_camera_base: np.ndarray
) -> FloatArray:
    """Gradient (Q, 3) in base coordinates of each row's cone at its camera point."""
    jl = monomial_exponents(degree)
    exponents = np.column_stack([jl, degree - jl.sum(axis=1)])
    grad = np.empty_like(x_camera)
    for axis in range(3):
        lowered = exponents.copy()
        lowered[:, axis] = np.maximum(lowered[:, axis] - 1, 0)
        grad[:, axis] = np.einsum(
            'qm,qm->q',
            exponents[:, axis] * np.prod(x_camera[:, None, :] ** lowered, axis=2),
            coefficients,
        )
    return grad @ R_camera_base


def _epipolar_distance_px(view1: View, view2: View, rays: FloatArray) -> FloatArray:
    """Distance [px] of every view-2 chain point to the epipolar line of every view-1
    ray (R, 3): (R, N2)."""

    def homogeneous(points_base: FloatArray) -> FloatArray:
        x = (points_base - view2.centre_base) @ view2.R_camera_base.T
        return x  # homogeneous image point (x, y, z) of view 2

    centre = homogeneous(view1.centre_base[None])[0]
    lines = np.cross(centre[None], homogeneous(view1.centre_base + rays))  # (R, 3)
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-300)
    xy1 = np.column_stack([view2.curve.xy, np.ones(len(view2.curve.xy))])
    return np.abs(lines @ xy1.T) * view2.curve.focal_px
