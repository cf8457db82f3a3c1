"""Piecewise algebraic image curves and 3D reconstruction from their cones (issue 4,
steps 2-3; the seed's chapter 7 fits a long curve piece by piece).

A view's curve is one ordered chain of normalised image points (undistorted, f = 1). It
is split into overlapping pieces until the degree-n fit of each piece has an RMS Sampson
residual below ``fit_tolerance_px``; a curve that one conic fits stays one piece (the
thesis's method unchanged). Each piece is a ``CurveView``-style cone, valid only near
the chain points it was fitted to: a candidate 3D point counts for a piece only if its
projection's nearest chain point belongs to that piece (the piece's "support"); this
throws out the far branches of a piece's conic.

Reconstruction (both ordered by the view-1 chain point each 3D point came from):

- ``reconstruct_ray_roots`` (``method: ray_roots``, ours): the view-1 ray of each chain
  point, substituted into each view-2 piece's cone, gives a degree-n polynomial in the
  ray depth; its real positive roots (companion-matrix eigenvalues, batched) inside the
  piece's support are the candidates;
- ``reconstruct_cone_lsq`` (``method: cone_lsq``, the thesis): minimise G1^2 + G2^2 by
  Levenberg-Marquardt (batched, minimum-norm damped Gauss-Newton steps) from seeds on the
  view-1 ray at ``seed_depths``, for the view-1 piece of the point and each view-2 piece;
  minima whose projections lie on both curves within ``on_curve_px`` are candidates.

View 3 then keeps per chain point the candidate whose projection is nearest view 3's
curve, if nearer than ``tol3_px``. With two views, a chain point with several distinct
candidates is ambiguous and dropped (counted). ``refine_points`` finally moves each
point to minimise its summed squared distances to the curves of all views, in pixels
(ALGORITHMS §8: the geometric reprojection error), which removes the bad conditioning
of the two-view intersection where the curve runs along the epipolar lines.
"""
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from curve_recon_node.algebraic_curves import (
    fit_implicit_curve,
    monomial_exponents,
    monomials,
    powers,
)
from vgm_common.errors import InvalidInput


@dataclass(frozen=True)
class CurvePiece:
    """One fitted piece: unit-norm coefficients (M,), the chain indices it was fitted to
    (K,), and the RMS Sampson residual of those points [px]."""

    coefficients: np.ndarray
    indices: np.ndarray
    rms_px: float


class PiecewiseCurve:
    """A view's curve: the ordered chain ``xy`` (N, 2) [normalised], ``closed`` or not,
    split into degree-``degree`` pieces.

    Args:
        xy: (N, 2) undistorted normalised image points in chain order.
        closed: the chain is a closed loop.
        degree: n of the implicit pieces.
        focal_px: the camera's focal length [px], to state residuals in pixels.
        fit_tolerance_px: largest RMS Sampson residual of a piece [px]; inf: one piece.
        min_piece_points: pieces are not split below this many points.
        overlap: fraction of a piece's length shared with each neighbour.
    """

    def __init__(self, xy, closed, degree, focal_px, fit_tolerance_px=0.1,
                 min_piece_points=30, overlap=0.25):
        xy = np.asarray(xy, dtype=float)
        size = len(monomial_exponents(degree))
        if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < max(size, 3):
            raise InvalidInput(f'chain: expected (N >= {max(size, 3)}, 2) points, got '
                               f'{xy.shape}', key='chain', value=xy.shape)
        self.xy = xy.copy()
        self.closed = bool(closed)
        self.degree = int(degree)
        self.focal_px = float(focal_px)
        self.fit_tolerance_px = float(fit_tolerance_px)
        self.min_piece_points = max(int(min_piece_points), size + 2)
        self.overlap = float(overlap)
        self.pieces = []
        n = len(xy)
        self._split(0, n, depth=0)
        self._tree = cKDTree(self.xy)
        # owner of each chain point: the piece in which it lies most centrally, so the
        # distance to the curve is measured away from the ends of a piece's fit
        centrality = np.full((len(self.pieces), n), -np.inf)
        for p, piece in enumerate(self.pieces):
            k = len(piece.indices)
            centrality[p, piece.indices] = np.minimum(np.arange(k), k - 1 - np.arange(k))
        self.owner = np.argmax(centrality, axis=0)
        self.member = np.isfinite(centrality)  # (P, N): chain point in piece's support
        self.coefficient_matrix = np.array([p.coefficients for p in self.pieces])

    # --- fitting ---------------------------------------------------------------------

    def _indices(self, start, length):
        idx = np.arange(start, start + length)
        return idx % len(self.xy) if self.closed else idx

    def _fit(self, indices):
        points = self.xy[indices]
        a = fit_implicit_curve(points, self.degree)
        residual = _sampson(a[None], monomials(points, self.degree),
                            _monomial_gradients(points, self.degree))[0]
        return a, float(np.sqrt(np.mean(residual**2)) * self.focal_px)

    def _split(self, start, length, depth):
        indices = self._indices(start, length)
        a, rms = self._fit(indices)
        too_short = length < 2 * self.min_piece_points
        if rms <= self.fit_tolerance_px or too_short or depth > 12:
            self.pieces.append(CurvePiece(a, indices, rms))
            return
        half = length // 2
        extra = int(np.ceil(self.overlap * half))
        if self.closed and length >= len(self.xy):  # the whole loop: halves wrap around
            self._split(start - extra, half + 2 * extra, depth + 1)
            self._split(start + half - extra, length - half + 2 * extra, depth + 1)
            return
        first_stop = min(start + half + extra, start + length)
        second_start = max(start + half - extra, start)
        self._split(start, first_stop - start, depth + 1)
        self._split(second_start, start + length - second_start, depth + 1)

    # --- queries ---------------------------------------------------------------------

    def nearest(self, xy):
        """Nearest chain point index (Q,) and distance to it (Q,) [normalised]."""
        distance, index = self._tree.query(np.asarray(xy, dtype=float).reshape(-1, 2))
        return index, distance

    def distance(self, xy):
        """Signed Sampson distance of (Q, 2) points to the curve [normalised units],
        (Q,), and the unit gradient direction of g (Q, 2), using the piece that owns the
        nearest chain point. NaN inputs give NaN."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        finite = np.all(np.isfinite(xy), axis=1)
        distance = np.full(len(xy), np.nan)
        direction = np.full((len(xy), 2), np.nan)
        if finite.any():
            index, _ = self.nearest(xy[finite])
            a = self.coefficient_matrix[self.owner[index]]
            gradient = np.sum(_monomial_gradients(xy[finite], self.degree) * a[:, :, None],
                              axis=1)
            norm = np.linalg.norm(gradient, axis=1)
            value = np.sum(monomials(xy[finite], self.degree) * a, axis=1)
            with np.errstate(divide='ignore', invalid='ignore'):
                distance[finite] = value / norm
                direction[finite] = gradient / norm[:, None]
        return distance, direction

    @property
    def rms_px(self):
        return float(np.sqrt(np.mean([p.rms_px**2 for p in self.pieces])))


def _monomial_gradients(xy, degree):
    """(Q, M, 2) derivatives of each monomial with respect to X and Y."""
    jx, jy = monomial_exponents(degree).T
    px, py = powers(xy[:, 0], degree), powers(xy[:, 1], degree)
    d_dx = jx * px[:, np.maximum(jx - 1, 0)] * py[:, jy]
    d_dy = jy * px[:, jx] * py[:, np.maximum(jy - 1, 0)]
    return np.stack([d_dx, d_dy], axis=2)


def _sampson(coefficients, mono, mono_gradients):
    """|g| / ||grad g|| for each row of coefficients (P, M) at Q points, (P, Q)."""
    value = coefficients @ mono.T
    gradient = np.einsum('qmk,pm->pqk', mono_gradients, coefficients)
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.abs(value) / np.linalg.norm(gradient, axis=2)


@dataclass(frozen=True)
class View:
    """A calibrated view of the curve: its piecewise curve and the camera's rotation
    (base -> optical) and centre in base [m]."""

    curve: PiecewiseCurve
    R_camera_base: np.ndarray
    centre_base: np.ndarray

    def project(self, points_base):
        """Normalised image points (N, 2) and depth (N,) [m]; NaN behind the camera."""
        x = (np.asarray(points_base, dtype=float) - self.centre_base) @ self.R_camera_base.T
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = x[:, :2] / x[:, 2:]
        xy[x[:, 2] <= 0] = np.nan
        return xy, x[:, 2]

    def distance_px(self, points_base):
        """Unsigned distance [px] of the points' projections to the curve; inf behind."""
        xy, _ = self.project(points_base)
        distance, _ = self.curve.distance(xy)
        return np.nan_to_num(np.abs(distance) * self.curve.focal_px, nan=np.inf)

    def in_support(self, points_base, pieces, support_px):
        """(N,) bool: each point's projection has its nearest chain point in piece
        ``pieces[i]``'s support and within ``support_px`` of the chain."""
        xy, _ = self.project(points_base)
        ok = np.all(np.isfinite(xy), axis=1)
        result = np.zeros(len(xy), dtype=bool)
        if ok.any():
            index, distance = self.curve.nearest(xy[ok])
            result[ok] = (self.curve.member[np.asarray(pieces)[ok], index]
                          & (distance * self.curve.focal_px <= support_px))
        return result


def _cone_values(coefficients, degree, x_camera):
    """Cone polynomial of each row's piece at each row's camera point: (Q,) for
    coefficients (Q, M) and x_camera (Q, 3)."""
    jl = monomial_exponents(degree)
    exponents = np.column_stack([jl, degree - jl.sum(axis=1)])
    return np.einsum('qm,qm->q', np.prod(x_camera[:, None, :] ** exponents, axis=2),
                     coefficients)


def _cone_gradients(coefficients, degree, x_camera, R_camera_base):
    """Gradient (Q, 3) in base coordinates of each row's cone at its camera point."""
    jl = monomial_exponents(degree)
    exponents = np.column_stack([jl, degree - jl.sum(axis=1)])
    grad = np.empty_like(x_camera)
    for axis in range(3):
        lowered = exponents.copy()
        lowered[:, axis] = np.maximum(lowered[:, axis] - 1, 0)
        grad[:, axis] = np.einsum('qm,qm->q', exponents[:, axis]
                                  * np.prod(x_camera[:, None, :] ** lowered, axis=2),
                                  coefficients)
    return grad @ R_camera_base


def _real_positive_roots(poly):
    """Real roots > 0 of polynomials with coefficients (Q, n + 1) in increasing order:
    returns (row index (K,), root (K,)). Leading coefficients near zero lower the degree
    (handled by the companion matrix of the trimmed polynomial, per degree)."""
    rows, roots = [], []
    scale = np.abs(poly).max(axis=1)
    scale[scale == 0] = 1.0
    p = poly / scale[:, None]
    n = p.shape[1] - 1
    # effective degree: highest coefficient above 1e-12 (relative)
    significant = np.abs(p) > 1e-12
    degree = np.where(significant.any(axis=1),
                      n - np.argmax(significant[:, ::-1], axis=1), 0)
    for d in range(1, n + 1):
        sel = np.nonzero(degree == d)[0]
        if len(sel) == 0:
            continue
        c = p[sel, :d + 1]
        companion = np.zeros((len(sel), d, d))
        companion[:, 0, :] = -c[:, d - 1::-1] / c[:, d:d + 1]
        if d > 1:
            companion[:, np.arange(1, d), np.arange(d - 1)] = 1.0
        eig = np.linalg.eigvals(companion)  # (S, d)
        real = np.abs(eig.imag) <= 1e-7 * (1 + np.abs(eig.real))
        positive = real & (eig.real > 0)
        r, k = np.nonzero(positive)
        rows.append(sel[r])
        roots.append(eig.real[r, k])
    if not rows:
        return np.empty(0, dtype=int), np.empty(0)
    return np.concatenate(rows), np.concatenate(roots)


def _rays(view1, samples):
    """Unit-depth rays R1^T (X, Y, 1) of view-1 chain points ``samples`` (indices)."""
    xy = view1.curve.xy[samples]
    return np.column_stack([xy, np.ones(len(xy))]) @ view1.R_camera_base


def reconstruct_ray_roots(view1, view2, view3=None, *, samples=None, tol3_px=2.0,
                          support_px=3.0, distinct_m=2e-3, max_depth=np.inf):
    """Candidates from the real roots of each view-2 piece's cone along view-1 rays.

    Args:
        view1, view2, view3: ``View``; view3 optional.
        samples: indices of view-1 chain points to reconstruct (default all).
        tol3_px: third-view threshold on the distance to view 3's curve [px].
        support_px: a candidate must project within this of view 2's chain [px].
        distinct_m: two-view case: candidates farther apart than this are distinct [m].
        max_depth: candidates deeper than this in view 1 are dropped [m]: far away, all
            cameras look along nearly the same direction, so a far point whose direction
            meets all image curves passes every test without lying on the curve.

    Returns:
        (points_base (K, 3), info) as ``select_candidates``.
    """
    samples = np.arange(len(view1.curve.xy)) if samples is None else np.asarray(samples)
    rays = _rays(view1, samples)
    curve2 = view2.curve
    degree = curve2.degree
    n_pieces = len(curve2.pieces)
    nodes = np.arange(degree + 1.0)
    # every (ray, piece) pair: evaluate the cone at n + 1 depths and solve exactly
    ray_index = np.repeat(np.arange(len(samples)), n_pieces)
    piece_index = np.tile(np.arange(n_pieces), len(samples))
    values = np.empty((len(ray_index), len(nodes)))
    for k, s in enumerate(nodes):
        x_cam = (view1.centre_base + s * rays[ray_index] - view2.centre_base) \
            @ view2.R_camera_base.T
        values[:, k] = _cone_values(curve2.coefficient_matrix[piece_index], degree, x_cam)
    poly = np.linalg.solve(np.vander(nodes, increasing=True), values.T).T
    rows, depth = _real_positive_roots(poly)
    points = view1.centre_base + depth[:, None] * rays[ray_index[rows]]
    _, depth2 = view2.project(points)
    keep = ((depth2 > 0) & (depth < max_depth)
            & view2.in_support(points, piece_index[rows], support_px))
    return select_candidates(ray_index[rows][keep], points[keep], len(samples), samples,
                             view3, tol3_px, distinct_m)


def reconstruct_cone_lsq(view1, view2, view3=None, *, samples=None, tol3_px=2.0,
                         support_px=3.0, on_curve_px=0.5, distinct_m=2e-3,
                         seed_depths=(0.25, 0.5, 1.0, 2.0, 4.0), iterations=25,
                         max_depth=np.inf):
    """The thesis's method: minima of F = G1^2 + G2^2 from seeds on the view-1 rays.

    For each view-1 chain point, its owning view-1 piece's cone G1 and every view-2
    piece's cone G2 are paired; each pair is refined from each seed s R1^T (X, Y, 1) + c1,
    s in ``seed_depths`` [m], by damped minimum-norm Gauss-Newton steps (Levenberg-
    Marquardt on the residual (G1, G2), batched over all seeds). A minimum is a candidate
    if it lies in front of both cameras, its projections are within ``on_curve_px`` of
    both curves and inside the two pieces' supports. Other arguments as
    ``reconstruct_ray_roots``.
    """
    samples = np.arange(len(view1.curve.xy)) if samples is None else np.asarray(samples)
    rays = _rays(view1, samples)
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

    def residual_and_jacobian(x):
        x1 = (x - view1.centre_base) @ view1.R_camera_base.T
        x2 = (x - view2.centre_base) @ view2.R_camera_base.T
        r = np.column_stack([_cone_values(a1, degree, x1), _cone_values(a2, degree, x2)])
        J = np.stack([_cone_gradients(a1, degree, x1, view1.R_camera_base),
                      _cone_gradients(a2, degree, x2, view2.R_camera_base)], axis=1)
        return r, J

    damping = np.full(len(x), 1e-3)
    r, J = residual_and_jacobian(x)
    cost = np.sum(r**2, axis=1)
    for _ in range(iterations):
        # minimum-norm damped step dx = -J^T (J J^T + mu I)^-1 r (2 residuals, 3 unknowns)
        JJt = J @ np.swapaxes(J, 1, 2)
        mu = (damping * np.trace(JJt, axis1=1, axis2=2))[:, None, None] * np.eye(2) + 1e-300
        with np.errstate(all='ignore'):
            step = -np.einsum('qij,qj->qi', np.swapaxes(J, 1, 2),
                              np.linalg.solve(JJt + mu, r[:, :, None])[:, :, 0])
        trial = x + np.nan_to_num(step)
        r_t, J_t = residual_and_jacobian(trial)
        cost_t = np.sum(r_t**2, axis=1)
        better = cost_t < cost
        x[better], r[better], J[better], cost[better] = (trial[better], r_t[better],
                                                          J_t[better], cost_t[better])
        damping = np.where(better, damping * 0.3, damping * 10.0)
        damping = np.clip(damping, 1e-12, 1e6)
    _, depth1 = view1.project(x)
    _, depth2 = view2.project(x)
    keep = ((depth1 > 0) & (depth1 < max_depth) & (depth2 > 0)
            & (view1.distance_px(x) <= on_curve_px) & (view2.distance_px(x) <= on_curve_px)
            & view2.in_support(x, piece2, support_px)
            & view1.in_support(x, piece1, support_px))
    # a minimum need not lie on its seed's ray: file it under the view-1 chain point its
    # projection is nearest to, which keeps the output ordered along the curve
    chain_index, _ = c1.nearest(view1.project(x[keep])[0])
    position = np.full(len(c1.xy), -1)
    position[samples] = np.arange(len(samples))
    sample_of = position[chain_index]
    inside = sample_of >= 0
    return select_candidates(sample_of[inside], x[keep][inside], len(samples), samples,
                             view3, tol3_px, distinct_m)


def _epipolar_distance_px(view1, view2, rays):
    """Distance [px] of every view-2 chain point to the epipolar line of every view-1
    ray (R, 3): (R, N2)."""
    def homogeneous(points_base):
        x = (points_base - view2.centre_base) @ view2.R_camera_base.T
        return x  # homogeneous image point (x, y, z) of view 2

    centre = homogeneous(view1.centre_base[None])[0]
    lines = np.cross(centre[None], homogeneous(view1.centre_base + rays))  # (R, 3)
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-300)
    xy1 = np.column_stack([view2.curve.xy, np.ones(len(view2.curve.xy))])
    return np.abs(lines @ xy1.T) * view2.curve.focal_px


def select_candidates(ray_of_candidate, candidates, n_samples, samples, view3, tol3_px,
                      distinct_m):
    """One point per view-1 sample from its candidates.

    With ``view3``: the candidate nearest view 3's curve, if within ``tol3_px``. Without:
    the candidate if all of the sample's candidates lie within ``distinct_m`` of each
    other (else the sample is ambiguous).

    Returns points_base (K, 3) in sample order and info: ``sample_index`` (K,) view-1
    chain indices, ``third_view_px`` (K,), ``n_samples``, ``n_candidates``,
    ``n_without_candidates``, ``n_rejected_view3``, ``n_ambiguous``.
    """
    order = np.argsort(ray_of_candidate, kind='stable')
    ray_of_candidate, candidates = ray_of_candidate[order], candidates[order]
    distance3 = (view3.distance_px(candidates) if view3 is not None
                 else np.zeros(len(candidates)))
    bounds = np.searchsorted(ray_of_candidate, np.arange(n_samples + 1))
    points, index, d3 = [], [], []
    rejected = ambiguous = empty = 0
    for i in range(n_samples):
        lo, hi = bounds[i], bounds[i + 1]
        if lo == hi:
            empty += 1
            continue
        if view3 is not None:
            best = lo + int(np.argmin(distance3[lo:hi]))
            if distance3[best] <= tol3_px:
                points.append(candidates[best])
                index.append(samples[i])
                d3.append(distance3[best])
            else:
                rejected += 1
        else:
            group = candidates[lo:hi]
            if np.linalg.norm(group - group.mean(axis=0), axis=1).max() <= distinct_m / 2:
                points.append(group.mean(axis=0))
                index.append(samples[i])
                d3.append(0.0)
            else:
                ambiguous += 1
    info = {'sample_index': np.array(index, dtype=int), 'third_view_px': np.array(d3),
            'n_samples': n_samples, 'n_candidates': len(candidates),
            'n_without_candidates': empty, 'n_rejected_view3': rejected,
            'n_ambiguous': ambiguous}
    return np.array(points, dtype=float).reshape(-1, 3), info


def refine_points(points_base, views, tangents=None, iterations=3, max_step_m=0.01):
    """Move each point to minimise sum_k (f_k d_k)^2, its squared distances [px] to the
    curves of all ``views`` (d_k the signed Sampson distance in view k, f_k its focal
    length): minimum-norm Gauss-Newton steps, batched. The along-curve direction is
    (nearly) in the null space; steps are also kept normal to ``tangents`` (N, 3) if
    given, so that points do not slide along the curve and keep their order.
    Returns (points (N, 3), residuals (N, V) [px])."""
    x = np.array(points_base, dtype=float).reshape(-1, 3)
    for _ in range(iterations):
        residuals, J = _distance_jacobian(x, views)
        ok = np.all(np.isfinite(residuals), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
        if not ok.any():
            break
        # minimum-norm Gauss-Newton step: nothing along the (near-)null direction, the
        # curve's tangent, so points do not slide along the curve
        step = -np.einsum('qiv,qv->qi', np.linalg.pinv(J[ok], rcond=1e-2), residuals[ok])
        if tangents is not None:
            t = tangents[ok]
            step -= np.sum(step * t, axis=1, keepdims=True) * t
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        step *= np.minimum(1.0, max_step_m / np.maximum(norm, 1e-300))
        x[ok] += step
    residuals, _ = _distance_jacobian(x, views)
    return x, residuals


def _distance_jacobian(x, views):
    """Signed distances [px] (N, V) and their Jacobians (N, V, 3) [px/m]."""
    residuals = np.empty((len(x), len(views)))
    J = np.empty((len(x), len(views), 3))
    for k, view in enumerate(views):
        x_cam = (x - view.centre_base) @ view.R_camera_base.T
        z = x_cam[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = x_cam[:, :2] / z[:, None]
            xy[z <= 0] = np.nan
            distance, direction = view.curve.distance(xy)
            f = view.curve.focal_px
            # d(xy)/d(x_cam): [[1/z, 0, -X/z], [0, 1/z, -Y/z]]
            d_xy = np.zeros((len(x), 2, 3))
            d_xy[:, 0, 0] = d_xy[:, 1, 1] = 1.0 / z
            d_xy[:, :, 2] = -xy / z[:, None]
        residuals[:, k] = f * distance
        J[:, k] = f * np.einsum('qi,qij->qj', direction, d_xy) @ view.R_camera_base
    return residuals, J
