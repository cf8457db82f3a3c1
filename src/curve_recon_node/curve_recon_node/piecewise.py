"""Piecewise algebraic image curves and 3D reconstruction from their cones (steps 2-3
of the pipeline; the seed's chapter 7 fits a long curve piece by piece).

A view's curve is one ordered chain of normalised image points (undistorted, f = 1). It
is split into overlapping pieces until the degree-n fit of each piece has an RMS Sampson
residual below ``fit_tolerance_px``; a curve that one conic fits stays one piece (the
thesis's method unchanged). Each piece's cone is valid only near the chain points it
was fitted to: a candidate 3D point counts for a piece only if its projection's nearest
chain point belongs to that piece (the piece's "support"); this throws out the far
branches of a piece's conic. A ``View`` pairs the curve with the camera that saw it
(``vgm_common.camera_model.PinholeCamera``, the one camera type).

Reconstruction: one driver, ``intersect_cones``, with a solver plugged in for the
candidates (both ordered by the view-1 chain point each 3D point came from):

- ``ray_root_candidates`` (``reconstruct_ray_roots``, ``method: ray_roots``, ours): the
  view-1 ray of each chain point, substituted into each view-2 piece's cone, gives a
  degree-n polynomial in the ray depth; its real positive roots (companion-matrix
  eigenvalues, batched) inside the piece's support are the candidates;
- ``thesis.cone_lsq_candidates`` (``thesis.reconstruct_cone_lsq``, ``method: cone_lsq``,
  the thesis): minimise G1^2 + G2^2 from seeds on the view-1 rays, on the same pieces,
  cones and selection.

View 3 then keeps per chain point the candidate whose projection is nearest view 3's
curve, if nearer than ``tol3_px``. With two views, a chain point with several distinct
candidates is ambiguous and dropped (counted). ``refine_points`` finally moves each
point to minimise its summed squared distances to the curves of all views, in pixels
(ALGORITHMS §8: the geometric reprojection error), which removes the bad conditioning
of the two-view intersection where the curve runs along the epipolar lines.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import NotRequired, TypedDict

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from curve_recon_node.algebraic_curves import (
    FITS,
    IntArray,
    fit_implicit_curves_batch,
    monomial_exponents,
    monomials_and_gradients,
    powers,
)
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

BIAS_WINDOW = 25  # [chain points] a fit's residual is averaged over this many for its bias
BIAS_SHARE = 0.6  # a piece whose bias exceeds this share of the RMS tolerance is split
# [px] a point farther than this from a view's chain polyline than from its fitted curve is
# judged by the chain (PiecewiseCurve.owner_distance): chain points lie within 0.15 px of
# the true projection at noise 4, the fits within 0.1 px of the chain
CHAIN_MARGIN_PX = 0.5
# [px] a candidate this far off the intersecting view's chain (beyond CHAIN_MARGIN_PX)
# ranks after those on it (``select_candidates``'s ``off_chain_last``)
OFF_CHAIN_PX = 1.0


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
        measured: (N,) bool, the chain points seen in the image (default all); the
            others (bridged across a crossing's gap) count for a piece's support and
            the chain's order but not for its fit, nor as view-1 samples.
    """

    def __init__(
        self,
        xy: npt.ArrayLike,
        closed: bool,
        degree: int,
        focal_px: float,
        fit_tolerance_px: float = 0.1,
        min_piece_points: int = 30,
        overlap: float = 0.25,
        measured: npt.ArrayLike | None = None,
    ) -> None:
        xy = np.asarray(xy, dtype=float)
        size = len(monomial_exponents(degree))
        if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < max(size, 3):
            raise InvalidInput(
                f'chain: expected (N >= {max(size, 3)}, 2) points, got {xy.shape}',
                key='chain',
                value=xy.shape,
            )
        self.xy = xy.copy()
        self.closed = bool(closed)
        self.degree = int(degree)
        self.focal_px = float(focal_px)
        self.fit_tolerance_px = float(fit_tolerance_px)
        self.min_piece_points = max(int(min_piece_points), size + 2)
        self.overlap = float(overlap)
        self.measured = (
            np.ones(len(xy), dtype=bool) if measured is None else np.asarray(measured, dtype=bool)
        )
        self.pieces: list[CurvePiece] = []
        n = len(xy)
        self._split()
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
        # (P, 2, 2) lower and upper corner of each piece's chain points [normalised]
        self.piece_boxes = np.array(
            [[self.xy[p.indices].min(axis=0), self.xy[p.indices].max(axis=0)] for p in self.pieces]
        )

    # --- fitting ---------------------------------------------------------------------

    def _indices(self, start: int, length: int) -> IntArray:
        idx = np.arange(start, start + length)
        return idx % len(self.xy) if self.closed else idx

    def _fits(self, pieces: Sequence[IntArray]) -> list[tuple[FloatArray, float, float]]:
        """Each piece's coefficients and RMS Sampson residual [px] (all pieces of one
        level of splitting at once): of Taubin's and the algebraic fit, the one nearer
        its points. Taubin's avoids the algebraic fit's near-singular solutions on long
        gentle pieces (pixels of residual where the points are within 0.05 px of a
        cubic); the algebraic one is sometimes nearer on a piece that no degree-n curve
        fits (a sharp turn too short to split). Both are always tried: stopping at a
        Taubin fit within the tolerance took a helix's coverage at noise 4 from 0.97 to
        0.78 (a single cubic piece, systematic error).

        Returns per piece (coefficients, RMS residual [px], bias [px]): the bias is the
        largest mean signed residual over ``BIAS_WINDOW`` consecutive chain points, the
        fit's systematic error, which the chain's noise averages out of."""
        size = len(monomial_exponents(self.degree))
        fitted = []
        for indices in pieces:
            measured = indices[self.measured[indices]]
            fitted.append(measured if len(measured) >= size + 2 else indices)
        counts = np.array([len(indices) for indices in fitted])
        gather = np.zeros((len(fitted), counts.max()), dtype=int)
        for row, indices in zip(gather, fitted):
            row[: len(indices)] = indices
        coefficients = fit_implicit_curves_batch(self.xy[gather], counts, self.degree, FITS)
        # signed Sampson distances g / ||grad g|| of each piece's chain points, per fit,
        # with the coefficients as they are used (in the chain's coordinates: computed
        # in the fit's normalised ones instead, they came out up to 30 % lower on short
        # near-straight cubic pieces, and the split stopped where the curve as used was
        # still off; near_straight seed 2 at noise 4: 0.21 -> 1.10 mm max)
        valid = np.arange(gather.shape[1])[None, :] < counts[:, None]
        residual = self._residuals(gather, coefficients, valid)
        rms = np.sqrt(np.sum(residual**2, axis=2) / counts) * self.focal_px  # (F, B)
        # the first fit (Taubin's) unless another is strictly nearer (NaN never is)
        best = np.zeros(len(fitted), dtype=int)
        for f in range(1, len(FITS)):
            best = np.where(rms[f] < rms[best, np.arange(len(fitted))], f, best)
        pieces_range = np.arange(len(fitted))
        residual = residual[best, pieces_range]
        # running mean over min(BIAS_WINDOW, count) points, from cumulative sums
        window = np.minimum(BIAS_WINDOW, counts)[:, None]
        cumulative = np.concatenate(
            [np.zeros((len(fitted), 1)), np.cumsum(residual, axis=1)], axis=1
        )
        starts = np.arange(gather.shape[1])[None, :]
        ends = starts + window
        inside = ends <= counts[:, None]
        running = (
            np.take_along_axis(cumulative, np.minimum(ends, gather.shape[1]), axis=1)
            - cumulative[:, :-1]
        ) / window
        bias = np.max(np.where(inside, np.abs(running), -np.inf), axis=1) * self.focal_px
        bias[~np.isfinite(bias)] = np.inf
        return [
            (coefficients[best[b], b], float(rms[best[b], b]), float(bias[b]))
            for b in pieces_range
        ]

    def _residuals(
        self, gather: IntArray, coefficients: FloatArray, valid: npt.NDArray[np.bool_]
    ) -> FloatArray:
        """(F, B, K) signed Sampson distances of chain points ``gather`` (B, K) to fits
        (F, B, M), 0 where not ``valid``."""
        mono, mono_gradients = monomials_and_gradients(self.xy[gather].reshape(-1, 2), self.degree)
        shape = (*gather.shape, -1)
        columns = coefficients.transpose(1, 2, 0)  # (B, M, F)
        value = mono.reshape(shape) @ columns
        dx = mono_gradients[:, :, 0].reshape(shape) @ columns
        dy = mono_gradients[:, :, 1].reshape(shape) @ columns
        with np.errstate(divide='ignore', invalid='ignore'):
            distance = (value / np.hypot(dx, dy)).transpose(2, 0, 1)
        return np.where(valid, distance, 0.0)

    def _split(self) -> None:
        """Split the chain recursively into halves (overlapping by ``overlap``) until
        each piece fits, one level at a time so that each level's fits are batched; the
        pieces are kept in depth-first order (the order of the chain)."""
        # pending pieces: (path of halves from the whole chain, start, length)
        level: list[tuple[tuple[int, ...], int, int]] = [((), 0, len(self.xy))]
        leaves: list[tuple[tuple[int, ...], CurvePiece]] = []
        depth = 0
        while level:
            indices = [self._indices(start, length) for _, start, length in level]
            following: list[tuple[tuple[int, ...], int, int]] = []
            for (path, start, length), piece_indices, (a, rms, bias) in zip(
                level, indices, self._fits(indices)
            ):
                too_short = length < 2 * self.min_piece_points
                # a fit within the RMS tolerance can still miss a stretch of the chain by
                # a steady 0.1-0.2 px (near_straight seed 3: RMS 0.07 px); where the
                # curve runs near the epipolar planes that bias became 0.8 mm in 3D
                fits = rms <= self.fit_tolerance_px and bias <= BIAS_SHARE * self.fit_tolerance_px
                if fits or too_short or depth > 12:
                    leaves.append((path, CurvePiece(a, piece_indices, rms)))
                    continue
                half = length // 2
                extra = int(np.ceil(self.overlap * half))
                if self.closed and length >= len(self.xy):  # the whole loop: halves wrap
                    following.append((path + (0,), start - extra, half + 2 * extra))
                    following.append(
                        (path + (1,), start + half - extra, length - half + 2 * extra)
                    )
                    continue
                first_stop = min(start + half + extra, start + length)
                second_start = max(start + half - extra, start)
                following.append((path + (0,), start, first_stop - start))
                following.append((path + (1,), second_start, start + length - second_start))
            level = following
            depth += 1
        self.pieces = [piece for _, piece in sorted(leaves, key=lambda leaf: leaf[0])]

    # --- queries ---------------------------------------------------------------------

    def nearest(self, xy: npt.ArrayLike, within: float = np.inf) -> tuple[IntArray, FloatArray]:
        """Nearest chain point index (Q,) and distance to it (Q,) [normalised]; points
        with none within ``within`` get index N and distance inf (their search stops
        early: most candidates of a knot's capture project far from view 3's chain)."""
        distance, index = self._tree.query(
            np.asarray(xy, dtype=float).reshape(-1, 2), distance_upper_bound=within
        )
        return index, distance

    def distance(self, xy: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Signed Sampson distance of (Q, 2) points to the curve [normalised units],
        (Q,), and the unit gradient direction of g (Q, 2), using the piece that owns the
        nearest chain point. NaN inputs give NaN."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        finite = np.all(np.isfinite(xy), axis=1)
        if not finite.all():
            distance = np.full(len(xy), np.nan)
            direction = np.full((len(xy), 2), np.nan)
            if finite.any():
                distance[finite], direction[finite] = self.distance(xy[finite])
            return distance, direction
        index, _ = self.nearest(xy)
        return self.owner_distance(xy, index)

    def owner_distance(self, xy: FloatArray, index: IntArray) -> tuple[FloatArray, FloatArray]:
        """``distance`` of finite points (Q, 2) whose nearest chain points are ``index``
        (Q,) (already known)."""
        a = self.coefficient_matrix[self.owner[index]]
        mono, mono_gradients = monomials_and_gradients(xy, self.degree)
        gradient = np.einsum('qmk,qm->qk', mono_gradients, a)
        norm = np.sqrt(gradient[:, 0] ** 2 + gradient[:, 1] ** 2)
        with np.errstate(divide='ignore', invalid='ignore'):
            return np.einsum('qm,qm->q', mono, a) / norm, gradient / norm[:, None]

    def seen_distance(
        self, xy: FloatArray, index: IntArray, to_index: FloatArray | None = None
    ) -> FloatArray:
        """Unsigned distance (Q,) [normalised] of finite points (Q, 2), nearest chain
        points ``index`` (Q,) at distances ``to_index`` (Q,) if known, to the curve as
        the view saw it: the Sampson distance to the owner piece's fit, but at least the
        distance to the chain's polyline less ``CHAIN_MARGIN_PX`` (the chain's own noise
        and the fit's).

        A piece's implicit curve runs on past the stretch of chain it was fitted to (at
        a sharp turn of the image it goes straight on where the chain turns away), so a
        point can lie on it, Sampson distance ~0, yet pixels from anything the view saw
        (sphere_loop seed 3: roots 1-4.6 mm off the curve, 0.6-3.2 px from view 3's
        chain, under 0.02 px from its fitted curve, passed the third view). Past an open
        chain's end and next to points bridged across a crossing the chain says nothing
        and the Sampson distance stands."""
        sampson, _ = self.owner_distance(xy, index)
        distance = np.abs(sampson)
        margin = CHAIN_MARGIN_PX / self.focal_px
        # the polyline is no farther than its nearest point: only points that far
        # beyond their Sampson distance can be raised, and those are few
        check = (
            ~(np.linalg.norm(xy - self.xy[index], axis=1) - margin <= distance)
            if to_index is None
            else ~(to_index - margin <= distance)
        )
        if check.any():
            chain_distance, unknown = self._chain_distance(xy[check], index[check])
            floor = np.where(unknown, 0.0, chain_distance - margin)
            distance[check] = np.maximum(distance[check], floor)
        return distance

    def _chain_distance(
        self, xy: FloatArray, index: IntArray
    ) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        """Distance [normalised] (Q,) of points (Q, 2) to the chain's polyline on the two
        segments at their nearest chain points ``index`` (Q,), and (Q,) bool: the chain
        says nothing there (the nearest chain point bridged across a crossing, up to
        4 px off, or an open chain's end: the others' ends are trimmed differently)."""
        n = len(self.xy)
        best = np.full(len(xy), np.inf)
        for step in (-1, 1):
            other = index + step
            if self.closed:
                other %= n
            valid = (other >= 0) & (other < n)
            other = np.clip(other, 0, n - 1)
            start, segment = self.xy[index], self.xy[other] - self.xy[index]
            length2 = np.sum(segment**2, axis=1)
            with np.errstate(divide='ignore', invalid='ignore'):
                t = np.clip(np.sum((xy - start) * segment, axis=1) / length2, 0.0, 1.0)
            t = np.where(valid & (length2 > 0), t, 0.0)
            best = np.minimum(best, np.linalg.norm(xy - start - t[:, None] * segment, axis=1))
        unknown = ~self.measured[index]
        if not self.closed:
            unknown |= (index == 0) | (index == n - 1)
        return best, unknown

    @property
    def rms_px(self) -> float:
        """The pieces' RMS Sampson residuals combined [px]: the root of their mean square,
        each piece counting once whatever its number of points."""
        return float(np.sqrt(np.mean([p.rms_px**2 for p in self.pieces])))


@dataclass(frozen=True)
class View:
    """A calibrated view of the curve: its piecewise curve (undistorted normalised
    coordinates) and the camera that saw it. ``R_camera_base`` (base -> optical) and
    ``centre_base`` [m] are the camera's, kept for the batched computations."""

    curve: PiecewiseCurve
    camera: PinholeCamera
    R_camera_base: np.ndarray = field(init=False, repr=False)
    centre_base: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, 'R_camera_base', self.camera.R_camera_base)
        object.__setattr__(self, 'centre_base', self.camera.centre_base)

    def project(self, points_base: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Normalised image points (N, 2) and depth (N,) [m]; NaN behind the camera."""
        x = (np.asarray(points_base, dtype=float) - self.centre_base) @ self.R_camera_base.T
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = x[:, :2] / x[:, 2:]
        xy[x[:, 2] <= 0] = np.nan
        return xy, x[:, 2]

    def distance_px(self, points_base: npt.ArrayLike, within_px: float = np.inf) -> FloatArray:
        """Unsigned distance [px] of the points' projections to the curve; inf behind the
        camera and where the projection is over ``within_px`` from every chain point."""
        xy, _ = self.project(points_base)
        result = np.full(len(xy), np.inf)
        finite = np.nonzero(np.all(np.isfinite(xy), axis=1))[0]
        # (a small relative margin on the search bound: the exact test follows)
        bound = within_px / self.curve.focal_px * (1 + 1e-9)
        index, chain_distance = self.curve.nearest(xy[finite], bound)
        near = chain_distance * self.curve.focal_px <= within_px
        if near.any():
            distance = self.curve.seen_distance(
                xy[finite[near]], index[near], chain_distance[near]
            )
            result[finite[near]] = np.nan_to_num(distance * self.curve.focal_px, nan=np.inf)
        return result

    def chain_index(self, points_base: npt.ArrayLike) -> IntArray:
        """Index (N,) of the chain point nearest each point's projection; -1 behind."""
        xy, _ = self.project(points_base)
        finite = np.all(np.isfinite(xy), axis=1)
        index = np.full(len(xy), -1)
        if finite.any():
            index[finite], _ = self.curve.nearest(xy[finite])
        return index

    def in_support(
        self, points_base: npt.ArrayLike, pieces: npt.ArrayLike, support_px: float
    ) -> npt.NDArray[np.bool_]:
        """(N,) bool: each point's projection has its nearest chain point in piece
        ``pieces[i]``'s support and within ``support_px`` of the chain."""
        xy, _ = self.project(points_base)
        pieces = np.asarray(pieces)
        # only a projection inside its piece's box grown by support_px can pass (and NaN
        # fails): the costly nearest-neighbour query is left for those (a small relative
        # margin keeps rounding from dropping a point exactly at the limit)
        reach = support_px / self.curve.focal_px * (1 + 1e-9)
        box = self.curve.piece_boxes[pieces]
        ok = np.all((xy >= box[:, 0] - reach) & (xy <= box[:, 1] + reach), axis=1)
        result = np.zeros(len(xy), dtype=bool)
        inside = np.nonzero(ok)[0]
        index, distance = self.curve.nearest(xy[inside], reach)
        near = distance * self.curve.focal_px <= support_px
        inside, index = inside[near], index[near]
        result[inside] = self.curve.member[pieces[inside], index]
        return result


def _cone_monomials(x_camera: FloatArray, degree: int) -> FloatArray:
    """(Q, M) homogeneous monomials x1^j x2^l x3^(n - j - l) of camera points (Q, 3), in
    the order of the coefficients (products of powers: exact for negative coordinates and
    faster than float exponents)."""
    jx, jy = monomial_exponents(degree).T
    px, py, pz = (powers(x_camera[:, axis], degree) for axis in range(3))
    return px[:, jx] * py[:, jy] * pz[:, degree - jx - jy]


def cone_values(coefficients: FloatArray, degree: int, x_camera: FloatArray) -> FloatArray:
    """Cone polynomial of each row's piece at each row's camera point: (Q,) for
    coefficients (Q, M) and x_camera (Q, 3)."""
    return np.einsum('qm,qm->q', _cone_monomials(x_camera, degree), coefficients)


def _real_positive_roots(poly: FloatArray) -> tuple[IntArray, FloatArray]:
    """Real roots > 0 of polynomials with coefficients (Q, n + 1) in increasing order:
    returns (row index (K,), root (K,)). Leading coefficients near zero lower the degree
    (handled per degree: in closed form up to cubics, else by the eigenvalues of the
    trimmed polynomial's companion matrix)."""
    rows: list[IntArray] = []
    roots: list[FloatArray] = []
    scale = np.abs(poly).max(axis=1)
    scale[scale == 0] = 1.0
    p = poly / scale[:, None]
    n = p.shape[1] - 1
    # effective degree: highest coefficient above 1e-12 (relative)
    significant = np.abs(p) > 1e-12
    degree = np.where(significant.any(axis=1), n - np.argmax(significant[:, ::-1], axis=1), 0)
    for d in range(1, n + 1):
        sel = np.nonzero(degree == d)[0]
        if len(sel) == 0:
            continue
        c = p[sel, : d + 1]
        if d <= 2:
            r, real_roots = _real_roots_up_to_quadratic(c)
        elif d == 3:
            r, real_roots = _real_roots_of_cubics(c)
        else:
            companion = np.zeros((len(sel), d, d))
            companion[:, 0, :] = -c[:, d - 1 :: -1] / c[:, d : d + 1]
            companion[:, np.arange(1, d), np.arange(d - 1)] = 1.0
            eig = np.linalg.eigvals(companion)  # (S, d)
            r, k = np.nonzero(np.abs(eig.imag) <= 1e-7 * (1 + np.abs(eig.real)))
            # (eigvals of float64 matrices is complex128; numpy's stubs say any precision)
            real_roots = eig.real[r, k]  # type: ignore[assignment]
        positive = real_roots > 0
        rows.append(sel[r[positive]])
        roots.append(real_roots[positive])
    if not rows:
        return np.empty(0, dtype=int), np.empty(0)
    return np.concatenate(rows), np.concatenate(roots)


def _real_roots_up_to_quadratic(c: FloatArray) -> tuple[IntArray, FloatArray]:
    """Real roots of the rows of c (S, 2) or (S, 3) (increasing order, leading coefficient
    nonzero): (row (K,), root (K,)). As for the companion matrices' eigenvalues, a complex
    pair whose imaginary part is within 1e-7 (1 + |real part|) counts as a double root."""
    if c.shape[1] == 2:
        return np.arange(len(c)), -c[:, 0] / c[:, 1]
    b, q = c[:, 1] / c[:, 2], c[:, 0] / c[:, 2]  # s^2 + b s + q
    discriminant = b * b - 4.0 * q
    root_of_magnitude = np.sqrt(np.abs(discriminant))
    real_pair = discriminant >= 0
    # the larger root without cancellation, the smaller one from the product q
    larger = -0.5 * (b + np.copysign(root_of_magnitude, b))
    smaller = np.divide(q, larger, out=np.zeros_like(q), where=larger != 0)
    near_double = ~real_pair & (0.5 * root_of_magnitude <= 1e-7 * (1 + np.abs(0.5 * b)))
    real = np.nonzero(real_pair | near_double)[0]
    first = np.where(real_pair, larger, -0.5 * b)[real]
    second = np.where(real_pair, smaller, -0.5 * b)[real]
    return np.concatenate([real, real]), np.concatenate([first, second])


def _real_roots_of_cubics(c: FloatArray) -> tuple[IntArray, FloatArray]:
    """Real roots of the rows of c (S, 4) (increasing order, leading coefficient nonzero):
    (row (K,), root (K,)), in closed form (Viete's cosines for three real roots, Cardano's
    formula for one), each polished by Newton steps on the cubic (kept where they lower
    |f|). As for the companion matrices' eigenvalues (which took a third of a knot
    capture's root finding), a complex pair whose imaginary part is within 1e-7 (1 +
    |real part|) counts as a double root."""
    a2, a1, a0 = (c[:, k] / c[:, 3] for k in (2, 1, 0))  # s^3 + a2 s^2 + a1 s + a0
    shift = a2 / 3.0  # s = t - shift: t^3 + p t + q
    p = a1 - a2 * shift
    q = (2.0 / 27.0) * a2**3 - a1 * shift + a0
    discriminant = (0.5 * q) ** 2 + (p / 3.0) ** 3
    three = discriminant <= 0
    # three real roots (p <= 0): t_k = m cos(phi - 2 pi k / 3)
    with np.errstate(divide='ignore', invalid='ignore'):
        m = 2.0 * np.sqrt(np.maximum(-p, 0.0) / 3.0)
        cosine = np.where(m > 0, 3.0 * q / np.where(m > 0, p * m, 1.0), 0.0)
    phi = np.arccos(np.clip(cosine, -1.0, 1.0)) / 3.0
    trigonometric = m[:, None] * np.cos(phi[:, None] - (2.0 * np.pi / 3.0) * np.arange(3))
    # one real root u + v, u^3 = -q/2 - sign(q) sqrt(D) (no cancellation), u v = -p / 3,
    # and the pair -(u + v) / 2 +- i sqrt(3) / 2 (u - v)
    u = np.cbrt(-0.5 * q - np.copysign(np.sqrt(np.maximum(discriminant, 0.0)), q))
    v = np.divide(-p, 3.0 * u, out=np.zeros_like(u), where=u != 0)
    pair_real = -0.5 * (u + v) - shift
    near_double = ~three & (0.5 * np.sqrt(3.0) * np.abs(u - v) <= 1e-7 * (1 + np.abs(pair_real)))
    rows = np.arange(len(c))
    one = np.nonzero(~three)[0]
    double = np.nonzero(near_double)[0]
    row = np.concatenate([np.repeat(rows[three], 3), one, double, double])
    root = np.concatenate(
        [
            (trigonometric[three] - shift[three, None]).ravel(),
            (u + v - shift)[one],
            pair_real[double],
            pair_real[double],
        ]
    )
    coefficients = np.column_stack([a0, a1, a2])[row]
    for _ in range(2):
        value = ((root + coefficients[:, 2]) * root + coefficients[:, 1]) * root + coefficients[
            :, 0
        ]
        slope = (3.0 * root + 2.0 * coefficients[:, 2]) * root + coefficients[:, 1]
        stepped = root - np.divide(value, slope, out=np.zeros_like(value), where=slope != 0)
        stepped_value = (
            (stepped + coefficients[:, 2]) * stepped + coefficients[:, 1]
        ) * stepped + coefficients[:, 0]
        root = np.where(np.abs(stepped_value) < np.abs(value), stepped, root)
    return row, root


class CandidateInfo(TypedDict):
    """The info of ``select_candidates`` (see there); ``n_second_pair`` only where a
    second camera pair recovered samples (``pipeline``)."""

    sample_index: npt.NDArray[np.int_ | np.float64]  # (K,) view-1 chain indices
    third_view_px: FloatArray  # (K,) [px]
    n_samples: int
    n_candidates: int
    n_without_candidates: int
    n_rejected_view3: int
    n_ambiguous: int
    n_out_of_order: int
    n_second_pair: NotRequired[int]
    n_end_on: NotRequired[int]


def view1_rays(view1: View, samples: IntArray) -> FloatArray:
    """Unit-depth rays R1^T (X, Y, 1) of view-1 chain points ``samples`` (indices)."""
    xy = view1.curve.xy[samples]
    return np.column_stack([xy, np.ones(len(xy))]) @ view1.R_camera_base


# A cone-intersection solver: (view1, view2, samples: view-1 chain indices) -> (the
# position in ``samples`` of each candidate's view-1 chain point (C,), candidate points
# in base (C, 3) [m]). Ours is ``ray_root_candidates``, the thesis's
# ``thesis.cone_lsq_candidates``; options are bound with ``functools.partial``.
CandidateSolver = Callable[[View, View, IntArray], tuple[IntArray, FloatArray]]


def intersect_cones(
    view1: View,
    view2: View,
    view3: View | None,
    solver: CandidateSolver,
    *,
    samples: npt.ArrayLike | None = None,
    tol3_px: float = 2.0,
    support3_px: float = 3.0,
    distinct_m: float = 2e-3,
    off_chain_last: bool = False,
) -> tuple[FloatArray, CandidateInfo]:
    """The cone intersection: ``solver``'s candidates where the cones of views 1 and 2
    meet, one per view-1 chain point chosen by ``select_candidates`` (view 3 and the
    chain order, or the two-view ambiguity test).

    Args:
        view1, view2, view3: ``View``; view3 optional.
        solver: a ``CandidateSolver``.
        samples: indices of view-1 chain points to reconstruct (default all measured).
        tol3_px: third-view threshold on the distance to view 3's curve [px].
        support3_px: a candidate must project within this of view 3's chain [px].
        distinct_m: two-view case: candidates farther apart than this are distinct [m].
        off_chain_last: as ``select_candidates``.

    Returns:
        (points_base (K, 3), info) as ``select_candidates``.
    """
    samples = np.nonzero(view1.curve.measured)[0] if samples is None else np.asarray(samples)
    ray_of_candidate, candidates = solver(view1, view2, samples)
    return select_candidates(
        ray_of_candidate,
        candidates,
        len(samples),
        samples,
        view3,
        tol3_px,
        distinct_m,
        support3_px,
        order_views=(view1, view2),
        off_chain_last=off_chain_last,
    )


def reconstruct_ray_roots(
    view1: View,
    view2: View,
    view3: View | None = None,
    *,
    samples: npt.ArrayLike | None = None,
    tol3_px: float = 2.0,
    support_px: float = 3.0,
    distinct_m: float = 2e-3,
    max_depth: float = np.inf,
    off_chain_last: bool = False,
) -> tuple[FloatArray, CandidateInfo]:
    """``intersect_cones`` with our solver, ``ray_root_candidates`` (``method:
    ray_roots``); ``support_px`` [px] bounds the candidates' distance to view 2's chain
    (the solver) and to view 3's (the selection), ``max_depth`` [m] their view-1 depth:
    far away, all cameras look along nearly the same direction, so a far point whose
    direction meets all image curves passes every test without lying on the curve.
    Other arguments as ``intersect_cones``."""
    solver = partial(ray_root_candidates, support_px=support_px, max_depth=max_depth)
    return intersect_cones(
        view1,
        view2,
        view3,
        solver,
        samples=samples,
        tol3_px=tol3_px,
        support3_px=support_px,
        distinct_m=distinct_m,
        off_chain_last=off_chain_last,
    )


def ray_root_candidates(
    view1: View,
    view2: View,
    samples: IntArray,
    *,
    support_px: float = 3.0,
    max_depth: float = np.inf,
) -> tuple[IntArray, FloatArray]:
    """Our ``CandidateSolver`` (``method: ray_roots``): (position in ``samples`` of each
    candidate's ray (C,), points_base (C, 3)), the real positive
    roots of each view-2 piece's cone along the view-1 rays of chain points ``samples``
    that project within ``support_px`` of that piece's chain points, shallower than
    ``max_depth`` in view 1."""
    rays = view1_rays(view1, samples)
    curve2 = view2.curve
    degree = curve2.degree
    nodes = np.arange(degree + 1.0)
    # only (ray, piece) pairs whose epipolar line in view 2 crosses the piece's box grown
    # by support_px: no root of the others can pass the support test (a knot's image:
    # 170 pieces per view, most rays meet a few of them)
    line = np.cross(
        (view1.centre_base - view2.centre_base) @ view2.R_camera_base.T,
        rays @ view2.R_camera_base.T,
    )  # (R, 3): a X + b Y + c = 0 in view 2's normalised coordinates
    reach = support_px / curve2.focal_px * (1 + 1e-9)
    if np.isfinite(reach):
        low, high = curve2.piece_boxes[:, 0] - reach, curve2.piece_boxes[:, 1] + reach  # (P, 2)
        corner_x = np.stack([low[:, 0], high[:, 0], low[:, 0], high[:, 0]], axis=1)  # (P, 4)
        corner_y = np.stack([low[:, 1], low[:, 1], high[:, 1], high[:, 1]], axis=1)
        side = (
            line[:, 0, None, None] * corner_x[None]
            + line[:, 1, None, None] * corner_y[None]
            + line[:, 2, None, None]
        )  # (R, P, 4)
        crosses = (side.min(axis=2) <= 0) & (side.max(axis=2) >= 0)
    else:
        # an unbounded support (one-piece curves: the thesis experiments) grows every box
        # to the plane; its corners at infinity gave NaN sides and not one pair
        crosses = np.ones((len(rays), len(curve2.pieces)), dtype=bool)
    ray_index, piece_index = np.nonzero(crosses)
    # evaluate each pair's cone at n + 1 depths and solve exactly; the camera-2 points of
    # a ray do not depend on the piece, so their monomials are shared
    x_cam = (
        view1.centre_base + nodes[:, None, None] * rays[None] - view2.centre_base
    ) @ view2.R_camera_base.T  # (n + 1, R, 3)
    monomials = _cone_monomials(x_cam.reshape(-1, 3), degree).reshape(len(nodes), len(rays), -1)
    values = np.einsum(
        'kqm,qm->kq', monomials[:, ray_index], curve2.coefficient_matrix[piece_index]
    )  # (n + 1, pairs)
    poly = np.linalg.solve(np.vander(nodes, increasing=True), values).T
    rows, depth = _real_positive_roots(poly)
    points = view1.centre_base + depth[:, None] * rays[ray_index[rows]]
    _, depth2 = view2.project(points)
    # the cheap tests first: the support test's nearest-neighbour query is the costly one
    plausible = (depth2 > 0) & (depth < max_depth)
    rows, points = rows[plausible], points[plausible]
    keep = view2.in_support(points, piece_index[rows], support_px)
    return ray_index[rows][keep], points[keep]


ORDER_WINDOW = 5  # view-1 samples on each side whose picks a candidate's order is checked against
ORDER_MARGIN = 8  # [chain points] a candidate may stray from its neighbours' chain positions


def select_candidates(
    ray_of_candidate: IntArray,
    candidates: FloatArray,
    n_samples: int,
    samples: IntArray,
    view3: View | None,
    tol3_px: float,
    distinct_m: float,
    support3_px: float = 3.0,
    order_views: tuple[View, View] | None = None,
    off_chain_last: bool = False,
) -> tuple[FloatArray, CandidateInfo]:
    """One point per view-1 sample from its candidates.

    With ``view3``: the candidate nearest view 3's curve, if within ``tol3_px`` of it and
    within ``support3_px`` of view 3's chain, and, given ``order_views`` (views 1 and 2),
    in order along the curve (``_in_chain_order``); with ``off_chain_last`` too, those
    over ``OFF_CHAIN_PX`` from view 2's curve as it saw it rank after the others.
    Without: the candidate if all of the sample's candidates lie within ``distinct_m`` of
    each other (else the sample is ambiguous).

    Returns points_base (K, 3) in sample order and info: ``sample_index`` (K,) view-1
    chain indices, ``third_view_px`` (K,), ``n_samples``, ``n_candidates``,
    ``n_without_candidates``, ``n_rejected_view3`` (samples left without a candidate
    that passes view 3), ``n_ambiguous``, ``n_out_of_order`` (candidates within
    ``tol3_px`` refused as out of order).
    """
    n_out_of_order = 0
    if view3 is not None:
        # a piece's implicit curve runs on beyond its stretch of the chain: a spurious
        # root near that continuation is near "the curve" by its Sampson distance while
        # far from anything view 3 saw, so a candidate must also project near the chain
        distance3 = view3.distance_px(candidates, within_px=support3_px)
        if order_views is not None:
            view1, view2 = order_views
            if off_chain_last:
                distance3 = _off_chain_last(distance3, candidates, view2, tol3_px)
            first = _first_of_each_sample(ray_of_candidate, distance3)
            picked = first[distance3[first] <= tol3_px]
            passing = np.nonzero(distance3 <= tol3_px)[0]
            in_order = _in_chain_order(
                samples[ray_of_candidate[passing]],
                candidates[passing],
                samples[ray_of_candidate[picked]],
                candidates[picked],
                view1.curve,
                (view2, view3),
            )
            distance3[passing[~in_order]] = np.inf
            n_out_of_order = int((~in_order).sum())
    else:
        distance3 = np.zeros(len(candidates))
    first = _first_of_each_sample(ray_of_candidate, distance3)
    empty = n_samples - len(first)
    rejected = ambiguous = 0
    if view3 is not None:
        accepted = distance3[first] <= tol3_px
        rejected = int((~accepted).sum())
        points, d3 = candidates[first[accepted]], distance3[first[accepted]]
    else:
        order = np.argsort(ray_of_candidate, kind='stable')
        ray_sorted, sorted_candidates = ray_of_candidate[order], candidates[order]
        start = np.nonzero(np.diff(ray_sorted, prepend=-1))[0]
        counts = np.diff(np.append(start, len(candidates)))
        group = np.repeat(np.arange(len(start)), counts)
        group_mean = np.zeros((len(start), 3))
        np.add.at(group_mean, group, sorted_candidates)
        group_mean /= counts[:, None]
        widest = np.zeros(len(start))
        np.maximum.at(widest, group, np.linalg.norm(sorted_candidates - group_mean[group], axis=1))
        accepted = widest <= distinct_m / 2
        ambiguous = int((~accepted).sum())
        points, d3 = group_mean[accepted], np.zeros(int(accepted.sum()))
    index = samples[ray_of_candidate[first[accepted]]]
    info: CandidateInfo = {
        'sample_index': np.asarray(index, dtype=int),
        'third_view_px': d3,
        'n_samples': n_samples,
        'n_candidates': len(candidates),
        'n_without_candidates': empty,
        'n_rejected_view3': rejected,
        'n_ambiguous': ambiguous,
        'n_out_of_order': n_out_of_order,
    }
    return np.asarray(points, dtype=float).reshape(-1, 3), info


def _off_chain_last(
    distance3: FloatArray, candidates: FloatArray, view2: View, tol3_px: float
) -> FloatArray:
    """``distance3`` (C,) [px], raised where a candidate within ``tol3_px`` is over
    ``OFF_CHAIN_PX`` from view 2's curve as that view saw it (``View.distance_px``) to
    that distance (at most ``tol3_px``): it still passes, but ranks after the roots on
    view 2's chain."""
    passing = np.nonzero(distance3 <= tol3_px)[0]
    seen2 = np.minimum(view2.distance_px(candidates[passing], within_px=tol3_px), tol3_px)
    off = seen2 > OFF_CHAIN_PX
    ranked = distance3.copy()
    ranked[passing[off]] = np.maximum(distance3[passing[off]], seen2[off])
    return ranked


def _first_of_each_sample(ray_of_candidate: IntArray, distance3: FloatArray) -> IntArray:
    """Per sample (ascending), the index of its candidate with the least ``distance3``."""
    order = np.lexsort((distance3, ray_of_candidate))
    start = np.nonzero(np.diff(ray_of_candidate[order], prepend=-1))[0]
    return order[start]


def _in_chain_order(
    sample: IntArray,
    points: FloatArray,
    picked_sample: IntArray,
    picked: FloatArray,
    curve1: PiecewiseCurve,
    views: Sequence[View],
) -> npt.NDArray[np.bool_]:
    """(C,) bool: each candidate (view-1 chain index ``sample``, 3D ``points``) projects
    in each of ``views`` near the chain position its neighbours' picks project to.

    Three cones also meet at isolated points off the curve (ghosts: where view 1's ray
    crosses view 2's curve at another stretch of it, and the third cone passes nearby).
    Such a point lies on all three image curves, so no distance test rejects it, and it
    can beat the true root by hundredths of a pixel. But its projection lands on a
    stretch of view 2's or 3's chain far (along the chain) from where the neighbouring
    samples' points land: correspondences along a curve are continuous. A candidate is in
    order when, in every view, the median chain offset to the picks (``picked_sample``,
    ``picked``) of the samples within ``ORDER_WINDOW`` of its own is within
    ``ORDER_MARGIN`` plus the spread of those offsets (the local rate of the chain
    positions). Candidates with fewer than 3 picked neighbours are kept."""
    if not len(sample) or not len(picked_sample):
        return np.ones(len(sample), dtype=bool)
    n1 = len(curve1.xy)
    offsets = np.concatenate([np.arange(-ORDER_WINDOW, 0), np.arange(1, ORDER_WINDOW + 1)])
    neighbour = sample[:, None] + offsets[None, :]
    if curve1.closed:
        inside = np.ones(neighbour.shape, dtype=bool)
        neighbour %= n1
    else:
        inside = (neighbour >= 0) & (neighbour < n1)
        neighbour = np.clip(neighbour, 0, n1 - 1)
    position = np.full(n1, -1)
    position[picked_sample] = np.arange(len(picked_sample))
    which = position[neighbour]
    has = inside & (which >= 0)
    enough = has.sum(axis=1) >= 3
    in_order = np.ones(len(sample), dtype=bool)
    for view in views:
        index = view.chain_index(points)
        picked_index = view.chain_index(picked)
        offset = picked_index[which].astype(float) - index[:, None]
        n = len(view.curve.xy)
        if view.curve.closed:
            offset = (offset + 0.5 * n) % n - 0.5 * n
        offset[~has | (picked_index[which] < 0) | (index[:, None] < 0)] = np.nan
        low, middle, high = _row_quantiles(offset, (0.1, 0.5, 0.9))
        in_order &= ~enough | ~(np.abs(middle) > ORDER_MARGIN + (high - low))
    return in_order


def _row_quantiles(values: FloatArray, quantiles: Sequence[float]) -> list[FloatArray]:
    """Quantiles (nearest rank) of each row of (R, K) ``values`` over its non-NaN
    entries, one (R,) array per quantile (NaN for an all-NaN row): sorted once, where
    ``np.nanpercentile`` loops over rows in Python (50 ms on a capture's candidates)."""
    ordered = np.sort(values, axis=1)  # NaN last
    count = np.sum(np.isfinite(values), axis=1)
    rows = np.arange(len(values))
    result = []
    for q in quantiles:
        rank = np.round(q * np.maximum(count - 1, 0)).astype(int)
        result.append(np.where(count > 0, ordered[rows, rank], np.nan))
    return result


def refine_points(
    points_base: npt.ArrayLike,
    views: Sequence[View],
    tangents: FloatArray | None = None,
    iterations: int = 3,
    max_step_m: float = 0.01,
    max_rank: int = 3,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Move each point to minimise sum_k (f_k d_k)^2, its squared distances [px] to the
    curves of all ``views`` (d_k the signed Sampson distance in view k, f_k its focal
    length): minimum-norm Gauss-Newton steps, batched. The along-curve direction is
    (nearly) in the null space; steps are also kept normal to ``tangents`` (N, 3) if
    given, so that points do not slide along the curve and keep their order.
    ``max_rank`` 2: the direction the views determine least (the curve's tangent as
    they see it) is always dropped from the step, however well determined it looks.
    Returns (points (N, 3), their signed residuals (N, V) [px], the residuals before
    refinement (N, V) [px]); NaN where a point is behind a camera."""
    x = np.array(points_base, dtype=float).reshape(-1, 3)
    initial_residuals = None
    owners = [_NearestCache(view.curve) for view in views]
    for _ in range(iterations):
        residuals, J = _distance_jacobian(x, views, owners)
        if initial_residuals is None:
            initial_residuals = residuals
        ok = np.all(np.isfinite(residuals), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
        if not ok.any():
            break
        # minimum-norm Gauss-Newton step: nothing along the (near-)null direction, the
        # curve's tangent, so points do not slide along the curve
        step = -pinv_solve(J[ok], residuals[ok], rcond=1e-2, max_rank=max_rank)
        if tangents is not None:
            t = tangents[ok]
            step -= np.sum(step * t, axis=1, keepdims=True) * t
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        step *= np.minimum(1.0, max_step_m / np.maximum(norm, 1e-300))
        x[ok] += step
    residuals, _ = _distance_jacobian(x, views, owners)
    return x, residuals, residuals if initial_residuals is None else initial_residuals


class _NearestCache:
    """A curve's nearest chain points of a batch of points across Gauss-Newton steps: a
    point is looked up again only once its projection has moved over ``REQUERY_PX``
    since its last lookup (the owner piece changes only near a piece's end, and the
    pieces overlap there); the lookups were 27 % of the refinement's time."""

    REQUERY_PX = 0.5

    def __init__(self, curve: PiecewiseCurve) -> None:
        self.curve = curve
        self.xy: FloatArray | None = None
        self.index: IntArray | None = None

    def distance(self, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``PiecewiseCurve.distance`` of (Q, 2) points, the same Q points each call."""
        finite = np.all(np.isfinite(xy), axis=1)
        if self.xy is None or self.index is None:
            self.xy, self.index = xy.copy(), np.zeros(len(xy), dtype=int)
            stale = finite
        else:
            moved = np.linalg.norm(xy - self.xy, axis=1) * self.curve.focal_px
            stale = finite & ~(moved <= self.REQUERY_PX)
        if stale.any():
            self.index[stale], _ = self.curve.nearest(xy[stale])
            self.xy[stale] = xy[stale]
        distance = np.full(len(xy), np.nan)
        direction = np.full((len(xy), 2), np.nan)
        if finite.any():
            distance[finite], direction[finite] = self.curve.owner_distance(
                xy[finite], self.index[finite]
            )
        return distance, direction


def _distance_jacobian(
    x: FloatArray, views: Sequence[View], owners: Sequence[_NearestCache]
) -> tuple[FloatArray, FloatArray]:
    """Signed distances [px] (N, V) and their Jacobians (N, V, 3) [px/m]; ``owners``
    the views' nearest-chain-point caches for these points."""
    residuals = np.empty((len(x), len(views)))
    J = np.empty((len(x), len(views), 3))
    for k, view in enumerate(views):
        x_cam = (x - view.centre_base) @ view.R_camera_base.T
        z = x_cam[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = x_cam[:, :2] / z[:, None]
            xy[z <= 0] = np.nan
            distance, direction = owners[k].distance(xy)
            f = view.curve.focal_px
            # d(xy)/d(x_cam): [[1/z, 0, -X/z], [0, 1/z, -Y/z]]
            d_xy = np.zeros((len(x), 2, 3))
            d_xy[:, 0, 0] = d_xy[:, 1, 1] = 1.0 / z
            d_xy[:, :, 2] = -xy / z[:, None]
        residuals[:, k] = f * distance
        J[:, k] = f * np.einsum('qi,qij->qj', direction, d_xy) @ view.R_camera_base
    return residuals, J


def pinv_solve(J: FloatArray, r: FloatArray, rcond: float, max_rank: int = 3) -> FloatArray:
    """pinv(J, rcond) @ r for a batch of (Q, V, 3) J and (Q, V) r: the minimum-norm least-
    squares solution that drops singular values at or below ``rcond`` times the largest,
    as ``np.linalg.pinv`` does, and all but the ``max_rank`` largest; in closed form from
    the eigenvalues of the 3 x 3 normal matrices A = J^T J (the squared singular values):
    Q small LAPACK SVDs, one call each, cost 2-3 times more. Returns (Q, 3)."""
    A = np.einsum('qvi,qvj->qij', J, J)
    g = np.einsum('qvi,qv->qi', J, r)
    eigenvalues = _symmetric_eigenvalues_3x3(A)  # descending
    kept = np.minimum((eigenvalues > rcond**2 * eigenvalues[:, :1]).sum(axis=1), max_rank)
    x = np.zeros_like(g)
    full = kept == 3
    x[full] = _solve_3x3(A[full], g[full])
    # rank 2: solve on the plane normal to the dropped eigenvector v3; lifting v3's
    # eigenvalue to the largest one keeps the matrix as well conditioned as the plane's
    two = kept == 2
    v3 = _eigenvector_3x3(A[two], eigenvalues[two, 2])
    lifted = A[two] + eigenvalues[two, 0, None, None] * v3[:, :, None] * v3[:, None, :]
    x[two] = _solve_3x3(lifted, g[two] - np.sum(v3 * g[two], axis=1, keepdims=True) * v3)
    one = kept == 1
    v1 = _eigenvector_3x3(A[one], eigenvalues[one, 0])
    x[one] = v1 * (np.sum(v1 * g[one], axis=1) / eigenvalues[one, 0])[:, None]
    return x


def _symmetric_eigenvalues_3x3(A: FloatArray) -> FloatArray:
    """Eigenvalues (Q, 3), descending, of symmetric (Q, 3, 3) matrices (trigonometric
    closed form)."""
    q = np.trace(A, axis1=1, axis2=2) / 3.0
    B = A - q[:, None, None] * np.eye(3)
    p = np.sqrt(np.sum(B * B, axis=(1, 2)) / 6.0)
    with np.errstate(divide='ignore', invalid='ignore'):
        half_det = _determinant_3x3(B) / (2.0 * p**3)
    angle = np.arccos(np.clip(np.nan_to_num(half_det), -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(angle)
    smallest = q + 2.0 * p * np.cos(angle + 2.0 * np.pi / 3.0)
    return np.column_stack([largest, 3.0 * q - largest - smallest, smallest])


def _eigenvector_3x3(A: FloatArray, eigenvalue: FloatArray) -> FloatArray:
    """Unit eigenvectors (S, 3) of symmetric (S, 3, 3) matrices for simple eigenvalues
    (S,): the longest cross product of two rows of A - eigenvalue I."""
    M = A - eigenvalue[:, None, None] * np.eye(3)
    candidates = np.stack(
        [_cross(M[:, 0], M[:, 1]), _cross(M[:, 0], M[:, 2]), _cross(M[:, 1], M[:, 2])], axis=1
    )
    lengths = np.sqrt(np.sum(candidates**2, axis=2))
    best = np.argmax(lengths, axis=1)
    rows = np.arange(len(M))
    return candidates[rows, best] / np.maximum(lengths[rows, best], 1e-300)[:, None]


def _solve_3x3(M: FloatArray, b: FloatArray) -> FloatArray:
    """Solutions (S, 3) of (S, 3, 3) M x = b by Cramer's rule (batched, no LAPACK)."""
    c0, c1, c2 = M[:, :, 0], M[:, :, 1], M[:, :, 2]
    cofactors = np.stack([_cross(c1, c2), _cross(c2, c0), _cross(c0, c1)], axis=1)
    determinant = np.sum(c0 * cofactors[:, 0], axis=1)
    return np.einsum('sij,sj->si', cofactors, b) / determinant[:, None]


def _determinant_3x3(M: FloatArray) -> FloatArray:
    return np.sum(M[:, :, 0] * _cross(M[:, :, 1], M[:, :, 2]), axis=1)


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross products of (S, 3) arrays (np.cross costs more on small batches)."""
    return np.column_stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ]
    )
