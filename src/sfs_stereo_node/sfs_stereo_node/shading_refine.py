"""Our fusion ``shading_refine``: variational shading-based depth refinement (in the
manner of Wu et al. 2011, Or-El et al. 2015) on the processing grid. No rclpy.

Minimises over the metric depth Z of the surface pixels

    sum_shading w_i ((I_i - I_hat_i(Z)) / sigma_I)^2            (shading term)
  + sum_stereo v_i ((Z_i - Z_stereo_i) / sigma_Z)^2              (confident stereo)
  + sum ((D2 Z)_i / sigma_c)^2                                   (thin-plate smoothness)

with I_hat = 255 albedo (R + ambient), R the SAME Oren-Nayar model the renderer uses
(``vgm_common.reflectance.oren_nayar``, perspective: per-pixel viewer direction toward
the camera centre), normals of the perspective depth map
n ~ (fx Z_u, fy Z_v, -(Z + (u - cx) Z_u + (v - cy) Z_v)), and D2 the second differences
Z_uu, Z_vv, Z_uv. Gauss-Newton: the residual of a pixel depends on (Z, Z_u, Z_v) there,
so its Jacobian is diag(a) + diag(b) D_u + diag(c) D_v with (a, b, c) from vectorised
evaluations of the model; the normal equations (a 13-point stencil, assembled on the
image grid into a CSR pattern made once per level) are solved by scipy's spsolve on
small grids and by conjugate gradients with a multigrid V-cycle preconditioner on large
ones. w_i, v_i are Cauchy (IRLS)
weights whose scale follows the residuals' median (a poor start is not outvoted by its
own misfit).

What the shading term must not see: pixels on thin dark lines (the drawn curve, a
morphological black-hat), which break the uniform albedo; mixed pixels on the surface
outline; saturated pixels. What the stereo term must not see: matches where the image
has no horizontal gradient (along near-horizontal edges a horizontal search slides:
the aperture problem), matches far from the median depth (global gate), and matches
beside likely occlusion edges (steps in the image); depth is not tied across those
edges either (they are left out of the grid and filled from their neighbours).

Coarse to fine: the start is a robust (IRLS) thin-plate interpolation of the stereo
depths (block medians) on the coarsest grid; each finer level starts from the coarser
solution (bilinear) and takes a few Gauss-Newton steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import splu, spsolve

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.reflectance import oren_nayar

BoolArray = npt.NDArray[np.bool_]

# Levels with more unknowns than this solve their Gauss-Newton steps by conjugate
# gradients preconditioned with a multigrid V-cycle (SuperLU fill-in grows fast with the
# grid). Jacobi-preconditioned CG needed > 300 iterations for a relative residual of
# 5e-3 on a 320x240 grid (the thin plate is a fourth-order operator); the V-cycle gets
# 1e-3 in about 10.
DIRECT_SOLVE_LIMIT = 1000
CG_ITERATIONS = 30
CG_TOLERANCE = 1e-3  # relative residual
MULTIGRID_COARSEST = 400  # unknowns of the multigrid's coarsest grid (a direct solve)
STEP_TOLERANCE = 5e-5  # [m] median update of a converged Gauss-Newton level


class ShadingModel(NamedTuple):
    """Known photometry, as the renderer makes the images."""

    light: FloatArray  # (3,) unit, surface -> light, in the depth map's camera frame
    albedo: float
    ambient: float  # fraction of the source (grey = 255 albedo (intensity R + ambient))
    roughness: float  # Oren-Nayar sigma [rad]
    intensity: float = 1.0


# The coarsest level's shading residual beyond this many sigma_i: the image is not the
# uniform-albedo shading of a surface under the given light (texture, another light,
# a non-Lambertian scene), and refining by it would bend the depth. Measured residuals
# [grey levels] on the coarsest level: Middlebury Aloe 35; the default scene 2.2; the
# textureless scene families 0.6-16.7 (a 320x240 sphere the highest).
MAX_MISFIT_SIGMAS = 12.0


class ShadingModelMismatch(InvalidInput):
    """The image is not explained by the shading model (see ``MAX_MISFIT_SIGMAS``)."""


class RefineResult(NamedTuple):
    """What :func:`refine_depth` made: the refined depth, the final shading residual and
    what each level of the coarse-to-fine solve did."""

    depth: FloatArray  # (H, W) [m], NaN off the surface
    shading_rms: float  # RMS shading residual at the end [grey levels], shading pixels
    levels: list[tuple[int, int, int]]  # per level: (width, unknowns, Gauss-Newton steps)


def predicted_grey(
    Z: FloatArray,
    Zu: FloatArray,
    Zv: FloatArray,
    u: FloatArray,
    v: FloatArray,
    K: FloatArray,
    model: ShadingModel,
) -> FloatArray:
    """Grey levels the renderer gives a surface point of depth ``Z`` with image-plane
    depth derivatives ``Zu``, ``Zv`` [m/px] at pixel (``u``, ``v``) of the camera ``K``
    (all broadcast arrays); clipped to [0, 255] as the renderer does."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xn, yn = (u - cx) / fx, (v - cy) / fy
    # Unit vectors normalised component-wise: norms along a length-3 last axis are slow.
    nx, ny = fx * Zu, fy * Zv
    nz = -(Z + (u - cx) * Zu + (v - cy) * Zv)
    length = np.sqrt(nx * nx + ny * ny + nz * nz)
    normals = np.stack([nx / length, ny / length, nz / length], axis=-1)
    length = np.sqrt(xn * xn + yn * yn + 1.0)
    views = np.stack([-xn / length, -yn / length, -1.0 / length], axis=-1)
    R = oren_nayar(normals, model.light, views, model.roughness)
    return np.clip(255.0 * model.albedo * (model.intensity * R + model.ambient), 0.0, 255.0)


# Every operator of the normal equations couples a pixel only to the 13 pixels within
# city-block distance 2 (the thin plate's second differences, and J^T W J of a Jacobian
# that reads a pixel and its 4 neighbours): the system matrix is assembled in this
# stencil form on the image grid (numpy slices, no sparse products) and gathered into a
# CSR pattern built once per level. Ascending (dv, du) = ascending column in a CSR row.
OFFSETS: tuple[tuple[int, int], ...] = tuple(
    (dv, du) for dv in range(-2, 3) for du in range(-2, 3) if abs(dv) + abs(du) <= 2
)
_OFFSET_INDEX = {offset: k for k, offset in enumerate(OFFSETS)}
_CENTRE = _OFFSET_INDEX[(0, 0)]

# A residual row of the normal equations in stencil form: (offset, weight image) terms,
# the row at pixel p reading sum_k weight_k[p] x[p + offset_k].
StencilRow = list[tuple[tuple[int, int], FloatArray | float]]  # float: the same everywhere


def _shifted(image: np.ndarray, dv: int, du: int) -> np.ndarray:
    """``out[v, u] = image[v - dv, u - du]``, zero where that falls outside."""
    H, W = image.shape
    out = np.zeros_like(image)
    out[max(dv, 0) : H + min(dv, 0), max(du, 0) : W + min(du, 0)] = image[
        max(-dv, 0) : H + min(-dv, 0), max(-du, 0) : W + min(-du, 0)
    ]
    return out


def _apply_row(row: StencilRow, x: FloatArray) -> FloatArray:
    """The residual rows ``row`` applied to the grid image ``x``: sum_k w_k[p] x[p + o_k]."""
    return sum((weight * _shifted(x, -dv, -du) for (dv, du), weight in row), np.zeros_like(x))


def _apply_row_transposed(row: StencilRow, y: FloatArray) -> FloatArray:
    """The transpose of ``row`` applied to the grid image ``y`` (residual space)."""
    return sum((_shifted(weight * y, dv, du) for (dv, du), weight in row), np.zeros_like(y))


def _add_shifted(target: FloatArray, image: FloatArray, dv: int, du: int) -> None:
    """``target[v, u] += image[v - dv, u - du]`` where that lies inside."""
    H, W = image.shape
    target[max(dv, 0) : H + min(dv, 0), max(du, 0) : W + min(du, 0)] += image[
        max(-dv, 0) : H + min(-dv, 0), max(-du, 0) : W + min(-du, 0)
    ]


def _add_normal_rows(coefficients: FloatArray, row: StencilRow, weight: FloatArray) -> None:
    """``coefficients`` (13, H, W) += the stencil of row^T diag(weight) row: a row centred
    at c adds weight[c] w_a[c] w_b[c] at pixel c + o_a, offset o_b - o_a. Only the
    centre and the offsets after it (raster order): ``_mirrored`` completes the rest."""
    for (dva, dua), wa in row:
        weighted = weight * wa
        for (dvb, dub), wb in row:
            offset = (dvb - dva, dub - dua)
            if offset >= (0, 0):
                _add_shifted(coefficients[_OFFSET_INDEX[offset]], weighted * wb, dva, dua)


def _mirrored(coefficients: FloatArray) -> FloatArray:
    """``coefficients`` (13, H, W) with the offsets before the centre filled from those
    after it: the matrix is symmetric, A[p, p + o] = A[p + o, p]."""
    for k, (dv, du) in enumerate(OFFSETS[:_CENTRE]):
        coefficients[k] = _shifted(coefficients[_OFFSET_INDEX[(-dv, -du)]], -dv, -du)
    return coefficients


class _Pattern:
    """The CSR pattern of the 13-point stencil on the unknowns ``mask`` of one grid."""

    def __init__(self, mask: BoolArray) -> None:
        self.mask = mask
        index = np.full(mask.shape, -1, dtype=np.int64)
        index[mask] = np.arange(int(mask.sum()))
        self.n = int(mask.sum())
        # neighbours[k, i]: unknown at OFFSETS[k] from unknown i, -1 where none.
        neighbours = np.stack([_shifted(index + 1, -dv, -du)[mask] - 1 for dv, du in OFFSETS])
        self._present = (neighbours >= 0).T  # (n, 13), row-major = CSR order
        self._indices = neighbours.T[self._present]
        self._indptr = np.concatenate([[0], np.cumsum(self._present.sum(axis=1))])

    def matrix(self, coefficients: FloatArray) -> sp.csr_matrix:
        """The CSR matrix whose row i holds ``coefficients[k]`` at unknown i's pixel for
        the unknown at ``OFFSETS[k]`` from it."""
        data = coefficients[:, self.mask].T[self._present]
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(self.n, self.n))

    def grid(self, x: FloatArray) -> FloatArray:
        """The unknowns ``x`` (n,) as a grid image, 0 off the mask."""
        out = np.zeros(self.mask.shape)
        out[self.mask] = x
        return out


def _first_derivative(mask: BoolArray, axis: int) -> tuple[StencilRow, BoolArray]:
    """Derivative along ``axis`` (1 = u, columns; 0 = v, rows) of the unknowns (the
    ``mask`` pixels) as a stencil row: central where both neighbours are unknowns,
    one-sided where one is; ``has`` marks pixels with a derivative."""
    step = (0, 1) if axis == 1 else (1, 0)
    back = (-step[0], -step[1])
    fwd = mask & _shifted(mask, *back)  # the next pixel along the axis is an unknown
    bwd = mask & _shifted(mask, *step)
    both = fwd & bwd
    row: StencilRow = [
        (step, np.where(both, 0.5, 0.0) + (fwd & ~bwd)),
        ((0, 0), -1.0 * (fwd & ~bwd) + (bwd & ~fwd)),
        (back, np.where(both, -0.5, 0.0) - (bwd & ~fwd)),
    ]
    return row, fwd | bwd


def _thin_plate(mask: BoolArray, curvature_sigma: float) -> FloatArray:
    """Stencil coefficients (13, H, W) of D2^T D2 / curvature_sigma^2, D2 the Z_uu, Z_vv
    and Z_uv (forward cross difference) rows wherever all their pixels are unknowns."""
    stencils = (
        ((0, -1, 1.0), (0, 0, -2.0), (0, 1, 1.0)),
        ((-1, 0, 1.0), (0, 0, -2.0), (1, 0, 1.0)),
        ((0, 0, 1.0), (0, 1, -1.0), (1, 0, -1.0), (1, 1, 1.0)),
    )
    coefficients = np.zeros((len(OFFSETS), *mask.shape))
    for stencil in stencils:
        centres = mask.copy()
        for dv, du, _ in stencil:
            centres &= _shifted(mask, -dv, -du)
        row: StencilRow = [((dv, du), w) for dv, du, w in stencil]
        _add_normal_rows(coefficients, row, centres / curvature_sigma**2)
    return _mirrored(coefficients)


def dark_line_mask(
    image: npt.ArrayLike, surface: BoolArray, size: int = 7, threshold: float = 8.0
) -> BoolArray:
    """Pixels on thin dark lines (the drawn curve): black-hat of a ``size`` square
    structuring element above ``threshold`` grey levels, dilated by one pixel."""
    kernel = np.ones((size, size), np.uint8)
    filled = np.where(surface, image, np.nan)
    filled = np.where(surface, image, np.nanmedian(filled)).astype(np.float32)
    blackhat = cv2.morphologyEx(filled, cv2.MORPH_BLACKHAT, kernel)
    lines = (blackhat > threshold).astype(np.uint8)
    return cv2.dilate(lines, np.ones((3, 3), np.uint8)).astype(bool)


def horizontal_texture(image: npt.ArrayLike, axis: int = 1) -> FloatArray:
    """Mean |dI/du| over the 3 x 3 neighbourhood [grey levels/px]: what a horizontal
    disparity search can lock onto. Along edges near the rows (the aperture problem)
    it is small, and matches there slide along the edge. ``axis`` 0: |dI/dv|, for a
    search along the columns (a vertical baseline)."""
    dx, dy = (1, 0) if axis == 1 else (0, 1)
    gradient = (
        np.abs(cv2.Sobel(np.asarray(image, dtype=np.float32), cv2.CV_32F, dx, dy, ksize=3)) / 8.0
    )
    return cv2.blur(gradient, (3, 3)).astype(float)


def _fill(Z: FloatArray, mask: BoolArray) -> FloatArray:
    """``Z`` with every pixel outside ``mask`` set to its nearest mask pixel's value."""
    if mask.all():
        return Z
    _, labels = cv2.distanceTransformWithLabels(
        (~mask).astype(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    values = np.zeros(labels.max() + 1)
    values[labels[mask]] = Z[mask]
    return values[labels]


def _downsample(array: np.ndarray, factor: int, interpolation: int = cv2.INTER_AREA) -> FloatArray:
    H, W = array.shape
    h, w = H // factor, W // factor
    return cv2.resize(
        np.ascontiguousarray(array[: h * factor, : w * factor], dtype=np.float32),
        (w, h),
        interpolation=interpolation,
    ).astype(float)


def _block_median(Z: FloatArray, valid: BoolArray, factor: int) -> tuple[FloatArray, FloatArray]:
    """Median of the ``valid`` values of ``Z`` in each ``factor`` x ``factor`` block (a
    median, so one wrong match does not drag its block) and their count."""
    H, W = Z.shape
    h, w = H // factor, W // factor
    rows, cols = np.nonzero(valid[: h * factor, : w * factor])
    if not len(rows):
        return np.full((h, w), np.nan), np.zeros((h, w))
    block = (rows // factor) * w + cols // factor
    values = Z[rows, cols]
    order = np.lexsort((values, block))
    block, values = block[order], values[order]
    starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
    counts = np.diff(np.r_[starts, len(block)])
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    median = np.full(h * w, np.nan)
    count = np.zeros(h * w)
    median[block[starts]] = 0.5 * (values[lo] + values[hi])
    count[block[starts]] = counts
    return median.reshape(h, w), count.reshape(h, w)


def _robust_scale(residual: FloatArray, floor: float) -> float:
    """Cauchy scale from the residuals' median absolute value, at least ``floor``."""
    return (
        max(floor, 2.0 * 1.4826 * float(np.median(np.abs(residual)))) if len(residual) else floor
    )


def _level_K(K: FloatArray, factor: int) -> FloatArray:
    S = np.array(
        [[1.0 / factor, 0, 0.5 / factor - 0.5], [0, 1.0 / factor, 0.5 / factor - 0.5], [0, 0, 1]]
    )
    return S @ K


class _Level(NamedTuple):
    image: FloatArray
    surface: BoolArray  # unknowns
    shade: BoolArray  # pixels whose shading is modelled
    stereo: FloatArray  # (H, W) mean stereo depth of the block, NaN where none
    stereo_count: FloatArray  # matches in the block
    K: FloatArray
    factor: int


def step_edges(
    image: npt.ArrayLike, surface: BoolArray, lines: BoolArray, threshold: float = 15.0
) -> BoolArray:
    """Likely occlusion boundaries inside the surface: a 3 x 3 morphological gradient
    above ``threshold`` [grey levels] that is not a drawn dark line and not the
    surface's own outline (3 px). Depth is not tied across them."""
    kernel = np.ones((3, 3), np.uint8)
    grey = np.asarray(image, dtype=np.float32)
    gradient = cv2.morphologyEx(grey, cv2.MORPH_GRADIENT, kernel)
    interior = cv2.erode(surface.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    near_line = cv2.dilate(lines.astype(np.uint8), kernel).astype(bool)
    return (gradient > threshold) & interior & ~near_line


def _levels(
    image: FloatArray,
    Z_stereo: FloatArray,
    surface: BoolArray,
    K: FloatArray,
    lines: BoolArray,
    min_width: int,
    cuts: BoolArray | None = None,
) -> list[_Level]:
    H, W = image.shape
    factors = [1]
    while W // (factors[-1] * 2) >= min_width:
        factors.append(factors[-1] * 2)
    matched = np.isfinite(Z_stereo) & surface
    cuts = np.zeros_like(surface) if cuts is None else cuts
    out = []
    for k in factors:
        if k == 1:
            img, surf = image.astype(float), surface & ~cuts
            clean = surface & ~lines
            count = matched.astype(float)
            stereo = np.where(matched, Z_stereo, np.nan)
        else:
            img = _downsample(image, k)
            surf = (_downsample(surface, k) > 0.5) & ~(_downsample(cuts, k) > 0)
            clean = _downsample(surface & ~lines, k) > 0.999
            stereo, count = _block_median(Z_stereo, matched, k)
        # Shading needs the whole 3x3 neighbourhood on the surface (no mixed edge pixels)
        # and no saturation.
        inner = cv2.erode(surf.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        shade = clean & inner & (img < 254.0)
        stereo = np.where(surf, stereo, np.nan)
        out.append(_Level(img, surf, shade, stereo, np.where(surf, count, 0.0), _level_K(K, k), k))
    return out[::-1]


def _initial_depth(
    level: _Level,
    pattern: _Pattern,
    smooth: FloatArray,
    sigma_z: float,
    robust_iterations: int = 6,
) -> FloatArray:
    """Thin-plate interpolation of the stereo depths on the level's surface (``pattern``
    its unknowns, ``smooth`` the thin plate's stencil coefficients)."""
    has = np.isfinite(level.stereo[level.surface])
    if has.sum() < 3:
        raise InvalidInput(
            f'only {int(has.sum())} stereo depths on the coarsest grid: '
            'too few to start the shading refinement',
            key='Z_stereo',
        )
    w0 = np.where(has, level.stereo_count[level.surface], 0.0) / sigma_z**2
    target = np.nan_to_num(level.stereo[level.surface])
    # A weak pull (0.1 m std) toward the median stereo depth holds surface pieces
    # without any match, which the thin plate alone leaves undetermined.
    prior_depth, prior_weight = float(np.median(target[has])), 1.0 / 0.1**2
    w = w0
    coefficients = smooth.copy()
    multigrid = _Multigrid(pattern.mask) if pattern.n > DIRECT_SOLVE_LIMIT else None
    z = np.full(pattern.n, prior_depth)
    for _ in range(robust_iterations):  # IRLS: wrong matches lose their weight
        coefficients[_CENTRE] = smooth[_CENTRE] + pattern.grid(w + prior_weight)
        A = pattern.matrix(coefficients)
        z = z + _solve(A, w * target + prior_weight * prior_depth - A @ z, multigrid)
        r = (z - target)[has]
        scale = _robust_scale(r, 3 * sigma_z)
        w = w0 * np.where(has, 1.0 / (1.0 + ((z - target) / scale) ** 2), 0.0)
    return z


def _coarser(mask: BoolArray) -> BoolArray:
    """The unknowns of the grid of half the resolution: every 2 x 2 block holding one."""
    H, W = mask.shape
    padded = np.zeros((H + H % 2, W + W % 2), dtype=bool)
    padded[:H, :W] = mask
    blocks = padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2)
    return np.asarray(blocks.any(axis=(1, 3)), dtype=bool)


def _prolongation(fine: BoolArray, coarse: BoolArray) -> sp.csr_matrix:
    """Bilinear interpolation (fine unknowns, coarse unknowns) from the grid ``coarse``
    of half the resolution (``_coarser(fine)``), pixel centres as ``cv2.resize`` puts
    them, weights renormalised over the coarse neighbours that are unknowns."""
    h, w = coarse.shape
    coarse_index = np.full(coarse.shape, -1, dtype=np.int64)
    coarse_index[coarse] = np.arange(int(coarse.sum()))
    v, u = np.nonzero(fine)
    # A fine pixel lies 1/4 coarse pixel from its own block's centre, toward a neighbour.
    own_v, own_u = v // 2, u // 2
    next_v = np.clip(np.where(v % 2 == 0, own_v - 1, own_v + 1), 0, h - 1)
    next_u = np.clip(np.where(u % 2 == 0, own_u - 1, own_u + 1), 0, w - 1)
    columns, weights = [], []
    for cv, wv in ((own_v, 0.75), (next_v, 0.25)):
        for cu, wu in ((own_u, 0.75), (next_u, 0.25)):
            columns.append(coarse_index[cv, cu])
            weights.append(np.where(columns[-1] >= 0, wv * wu, 0.0))
    column, weight = np.stack(columns, axis=1), np.stack(weights, axis=1)
    weight /= weight.sum(axis=1, keepdims=True)  # the own block is always an unknown
    present = column >= 0
    indptr = np.concatenate([[0], np.cumsum(present.sum(axis=1))])
    P = sp.csr_matrix(
        (weight[present], column[present], indptr), shape=(len(v), int(coarse.sum()))
    )
    P.sum_duplicates()  # a clipped neighbour on the grid's edge is the own block again
    return P


def _l1_smoother(A: sp.csr_matrix) -> FloatArray:
    """1 / sum_j |A_ij|: the l1-Jacobi smoother's weights (convergent for any symmetric
    positive definite A, unlike plain Jacobi on the thin plate's fourth-order stencil)."""
    return 1.0 / np.add.reduceat(np.abs(A.data), A.indptr[:-1])


class _Multigrid:
    """Conjugate gradients preconditioned by a geometric multigrid V-cycle on the
    unknowns ``mask`` of one grid: coarser grids by ``_coarser`` down to
    ``MULTIGRID_COARSEST`` unknowns, bilinear prolongation P, Galerkin operators
    P^T A P, one l1-Jacobi sweep before and after the coarse correction (symmetric, and
    convergent for any symmetric positive definite A, so the V-cycle is a valid CG
    preconditioner), a direct solve on the coarsest grid. The grids are built once per
    level; the coarse operators from the first system solved and kept for the next
    ones (the Gauss-Newton steps of one level differ little; any fixed symmetric
    positive definite preconditioner keeps CG exact)."""

    def __init__(self, mask: BoolArray) -> None:
        self._coarse: list[tuple[sp.csr_matrix, FloatArray]] = []  # operator, smoother
        self._coarsest: Any = None  # SuperLU of the coarsest operator
        self._prolongations: list[tuple[sp.csr_matrix, sp.csr_matrix]] = []
        while mask.sum() > MULTIGRID_COARSEST:
            coarse = _coarser(mask)
            if coarse.sum() == mask.sum():
                break
            P = _prolongation(mask, coarse)
            self._prolongations.append((P, sp.csr_matrix(P.T)))
            mask = coarse

    def solve(self, A: sp.csr_matrix, b: FloatArray, iterations: int, rtol: float) -> FloatArray:
        """x ~ A^-1 b for a symmetric positive definite ``A`` on the mask's unknowns, from
        x = 0, until the residual is ``rtol`` |b| or after ``iterations``. Own loop with
        plain numpy reductions: scipy's cg calls BLAS dot products, whose threads stall
        on a loaded machine."""
        if self._coarsest is None:
            coarse = A
            for P, PT in self._prolongations:
                coarse = sp.csr_matrix(PT @ coarse @ P)
                self._coarse.append((coarse, _l1_smoother(coarse)))
            self._coarsest = splu(coarse.tocsc())
        operators = [(A, _l1_smoother(A)), *self._coarse]

        def v_cycle(r: FloatArray, level: int = 0) -> FloatArray:
            if level == len(self._prolongations):
                return np.asarray(self._coarsest.solve(r))
            (A_l, smoother), (P, PT) = operators[level], self._prolongations[level]
            x = smoother * r
            x += P @ v_cycle(PT @ (r - A_l @ x), level + 1)
            return x + smoother * (r - A_l @ x)

        x = np.zeros_like(b)
        r = b.copy()
        z = v_cycle(r)
        d = z.copy()
        rz = float(np.sum(r * z))
        stop = rtol**2 * float(np.sum(b * b))
        for _ in range(iterations):
            Ad = A @ d
            step = rz / float(np.sum(d * Ad))
            x += step * d
            r -= step * Ad
            if float(np.sum(r * r)) <= stop:
                break
            z = v_cycle(r)
            rz, rz_old = float(np.sum(r * z)), rz
            d = z + (rz / rz_old) * d
        return x


def _solve(A: sp.csr_matrix, b: FloatArray, multigrid: _Multigrid | None) -> FloatArray:
    """A^-1 b: direct without ``multigrid`` (small grids), else its preconditioned CG."""
    if multigrid is None:
        return np.asarray(spsolve(A.tocsc(), b))
    return multigrid.solve(A, b, CG_ITERATIONS, CG_TOLERANCE)


def _gauss_newton(
    level: _Level,
    pattern: _Pattern,
    smooth: FloatArray,
    z: FloatArray,
    model: ShadingModel,
    sigma_i: float,
    sigma_z: float,
    steps: int,
    cauchy: float,
    max_step: float | None,
) -> tuple[FloatArray, float]:
    mask = level.surface
    du_row, has_u = _first_derivative(mask, axis=1)
    dv_row, has_v = _first_derivative(mask, axis=0)
    smooth_matrix = pattern.matrix(smooth)
    multigrid = _Multigrid(mask) if pattern.n > DIRECT_SOLVE_LIMIT else None
    shade_grid = level.shade & mask & has_u & has_v
    observed = level.image[shade_grid]
    v_s, u_s = (a.astype(float) for a in np.nonzero(shade_grid))
    has = np.isfinite(level.stereo[mask])
    w_stereo = np.where(has, level.stereo_count[mask], 0.0) / sigma_z**2
    target = np.nan_to_num(level.stereo[mask])
    K = level.K
    rms = float('nan')
    for _ in range(steps):
        z_grid = pattern.grid(z)
        Zs = z_grid[shade_grid]
        Zu, Zv = _apply_row(du_row, z_grid)[shade_grid], _apply_row(dv_row, z_grid)[shade_grid]
        # The prediction and the model derivatives w.r.t. Zu, Zv by forward differences,
        # in one evaluation (central ones cost two more for the same fused depth within
        # 0.01 mm); the model depends on (Zu/Z, Zv/Z) only, so
        # dI/dZ = -(Zu dI/dZu + Zv dI/dZv) / Z.
        h = 1e-4 * Zs
        pred, u_plus, v_plus = predicted_grey(
            np.tile(Zs, 3),
            np.concatenate([Zu, Zu + h, Zu]),
            np.concatenate([Zv, Zv, Zv + h]),
            np.tile(u_s, 3),
            np.tile(v_s, 3),
            K,
            model,
        ).reshape(3, -1)
        r = observed - pred
        g_u = (u_plus - pred) / h
        g_v = (v_plus - pred) / h
        g_z = -(Zu * g_u + Zv * g_v) / Zs
        # Cauchy scale from the residuals themselves while they are large (a poor start
        # is not outvoted by its own misfit), cauchy sigma_i once they are small.
        weight = 1.0 / (1.0 + (r / _robust_scale(r, cauchy * sigma_i)) ** 2) / sigma_i**2
        r_z = (z - target)[has]
        scale = _robust_scale(r_z, cauchy * sigma_z)
        w_z = w_stereo * np.where(has, 1.0 / (1.0 + ((z - target) / scale) ** 2), 0.0)
        # The Jacobian J = diag(g_z) + diag(g_u) D_u + diag(g_v) D_v on the shading
        # pixels, in stencil form.
        g_u_grid, g_v_grid, g_z_grid = (np.zeros(mask.shape) for _ in range(3))
        g_u_grid[shade_grid], g_v_grid[shade_grid], g_z_grid[shade_grid] = g_u, g_v, g_z
        jacobian: StencilRow = [((0, 0), g_z_grid)]
        jacobian += [(offset, g_u_grid * w) for offset, w in du_row]
        jacobian += [(offset, g_v_grid * w) for offset, w in dv_row]
        weight_grid = np.zeros(mask.shape)
        weight_grid[shade_grid] = weight
        coefficients = smooth.copy()
        _add_normal_rows(coefficients, jacobian, weight_grid)
        # + a 1 m prior on the update keeps A positive definite where a pixel has lost
        # every term (e.g. an island between cut edges); negligible elsewhere.
        coefficients[_CENTRE] += pattern.grid(w_z + 1.0)
        A = pattern.matrix(_mirrored(coefficients))
        r_grid = np.zeros(mask.shape)
        r_grid[shade_grid] = weight * r
        b = _apply_row_transposed(jacobian, r_grid)[mask] - w_z * (z - target) - smooth_matrix @ z
        dz = _solve(A, b, multigrid)
        if max_step:
            dz = np.clip(dz, -max_step, max_step)
        z = z + dz
        rms = float(np.sqrt(np.mean(r**2)))
        if np.median(np.abs(dz)) < STEP_TOLERANCE:  # [m]: converged (the IRLS weights
            break  # keep a few pixels moving, so the largest update is no test)
    return z, rms


def _checked_refine_inputs(
    image: npt.ArrayLike, Z_stereo: npt.ArrayLike, surface: npt.ArrayLike, K: np.ndarray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """``image``, ``Z_stereo`` as float and ``surface`` as bool arrays of one (H, W) shape.

    Raises:
        InvalidInput: on mismatched shapes, or a ``K`` that is not finite with fx, fy > 0.
    """
    image = np.asarray(image, dtype=float)
    Z_stereo = np.asarray(Z_stereo, dtype=float)
    surface = np.asarray(surface, dtype=bool)
    if image.ndim != 2 or image.shape != Z_stereo.shape or image.shape != surface.shape:
        raise InvalidInput(
            f'image {image.shape}, Z_stereo {Z_stereo.shape} and surface '
            f'{surface.shape}: expected one (H, W) shape',
            key='image',
        )
    if not np.all(np.isfinite(K)) or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InvalidInput('K must be finite with fx, fy > 0', key='K')
    return image, Z_stereo, surface


def _without_false_matches(Z_stereo: FloatArray, surface: BoolArray, sigma_z: float) -> FloatArray:
    """``Z_stereo`` [m] with NaN where a depth is more than 6 robust standard deviations
    (+ 3 ``sigma_z``) from the median of the surface's depths."""
    # Global gate: depths more than 6 robust standard deviations from the median match
    # are false matches (a lone one in a corner would otherwise bend the whole corner).
    finite = Z_stereo[np.isfinite(Z_stereo) & surface]
    if len(finite):
        centre = np.median(finite)
        spread = 6 * 1.4826 * np.median(np.abs(finite - centre)) + 3 * sigma_z
        with np.errstate(invalid='ignore'):
            Z_stereo = np.where(np.abs(Z_stereo - centre) <= spread, Z_stereo, np.nan)
    return Z_stereo


def _without_matches_beside_cuts(Z_stereo: FloatArray, cuts: BoolArray) -> FloatArray:
    """``Z_stereo`` [m] with NaN within 2 px of the step-edge pixels ``cuts``."""
    near_cut = cv2.dilate(cuts.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return np.where(near_cut, np.nan, Z_stereo)


def _upsampled_start(Z: FloatArray, prev: _Level, level: _Level) -> FloatArray:
    """Start depths (unknowns,) on ``level`` from the depth map ``Z`` (H, W) [m] of the
    coarser level ``prev``: filled off its surface, doubled bilinearly, edge rows and
    columns repeated where the finer grid is larger."""
    Zfill = _fill(np.nan_to_num(Z), prev.surface)
    up = cv2.resize(
        Zfill,
        (prev.surface.shape[1] * 2, prev.surface.shape[0] * 2),
        interpolation=cv2.INTER_LINEAR,
    )
    H, W = level.surface.shape
    Zfull = np.empty((H, W))
    Zfull[: up.shape[0], : up.shape[1]] = up[:H, :W]
    if up.shape[0] < H:
        Zfull[up.shape[0] :] = Zfull[up.shape[0] - 1]
    if up.shape[1] < W:
        Zfull[:, up.shape[1] :] = Zfull[:, up.shape[1] - 1 : up.shape[1]]
    return Zfull[level.surface]


def refine_depth(
    image: npt.ArrayLike,
    Z_stereo: npt.ArrayLike,
    surface: npt.ArrayLike,
    K: np.ndarray,
    model: ShadingModel,
    sigma_i: float = 2.0,
    sigma_z: float = 0.002,
    curvature_sigma: float = 1e-4,
    steps: Sequence[int] = (12, 6, 3),
    min_width: int = 40,
    cauchy: float = 3.0,
    max_step: float | None = 0.02,
    finest_steps: int = 1,
    min_stereo_gradient: float = 5.0,
    edge_threshold: float = 15.0,
    lines: BoolArray | None = None,
    search_axis: int = 1,
) -> RefineResult:
    """Shading-refined metric depth (module docstring) of one image.

    ``image`` (H, W) grey levels 0..255 of the reference camera (rectified);
    ``Z_stereo`` (H, W) [m] confident stereo depths, NaN elsewhere; ``surface`` (H, W)
    bool, the pixels to estimate; ``K`` (3, 3) intrinsics of this grid; ``model`` a
    ``ShadingModel``. ``sigma_i`` [grey levels] shading noise, ``sigma_z`` [m] stereo
    depth noise, ``curvature_sigma`` [m/px^2 on this grid] thin-plate prior;
    ``steps`` Gauss-Newton steps from the coarsest level on (the last entry repeats;
    ``finest_steps`` on the full grid); ``min_width`` [px] of the coarsest level;
    ``cauchy`` IRLS scale in sigma_i; ``max_step`` [m] clamps each update;
    stereo depths where ``horizontal_texture`` < ``min_stereo_gradient`` [grey levels/px]
    are not used (0 keeps all; ``search_axis`` 0 for a vertical baseline); ``lines``
    (H, W) bool pixels left out of the shading term (default ``dark_line_mask``).
    Returns ``RefineResult``.
    """
    image, Z_stereo, surface = _checked_refine_inputs(image, Z_stereo, surface, K)
    if lines is None:
        lines = dark_line_mask(image, surface)
    if min_stereo_gradient > 0:
        Z_stereo = np.where(
            horizontal_texture(image, search_axis) >= min_stereo_gradient, Z_stereo, np.nan
        )
    Z_stereo = _without_false_matches(Z_stereo, surface, sigma_z)
    cuts = step_edges(image, surface, lines, edge_threshold) if edge_threshold > 0 else None
    if cuts is not None:  # matches beside an occlusion take the foreground's depth
        Z_stereo = _without_matches_beside_cuts(Z_stereo, cuts)
    levels = _levels(image, Z_stereo, surface, np.asarray(K, dtype=float), lines, min_width, cuts)
    pattern = _Pattern(levels[0].surface)
    smooth = _thin_plate(levels[0].surface, curvature_sigma * levels[0].factor ** 2)
    z = _initial_depth(levels[0], pattern, smooth, sigma_z)
    Z = np.full(levels[0].surface.shape, np.nan)
    Z[levels[0].surface] = z
    report: list[tuple[int, int, int]] = []
    rms = float('nan')
    for i, level in enumerate(levels):
        if i > 0:
            z = _upsampled_start(Z, levels[i - 1], level)
            pattern = _Pattern(level.surface)
            smooth = _thin_plate(level.surface, curvature_sigma * level.factor**2)
        n_steps = finest_steps if level.factor == 1 else steps[min(i, len(steps) - 1)]
        z, rms = _gauss_newton(
            level,
            pattern,
            smooth,
            z,
            model,
            sigma_i,
            sigma_z,
            n_steps,
            cauchy,
            max_step,
        )
        if i == 0 and not rms <= MAX_MISFIT_SIGMAS * sigma_i:  # NaN: no pixel is shading
            raise ShadingModelMismatch(
                'the shading model does not explain the image: '
                + (
                    f'residual {rms:.1f} grey levels on the coarsest grid (> '
                    f'{MAX_MISFIT_SIGMAS:g} x {sigma_i:g})'
                    if np.isfinite(rms)
                    else 'no pixel of the coarsest grid is left to the shading term'
                )
                + ': texture, varying albedo or another light',
                key='image',
                value=rms,
            )
        Z = np.full(level.surface.shape, np.nan)
        Z[level.surface] = z
        report.append((level.surface.shape[1], int(level.surface.sum()), n_steps))
    if cuts is not None and cuts.any():  # the cut pixels take their nearest neighbour's depth
        Z = np.where(surface, _fill(np.nan_to_num(Z), levels[-1].surface), np.nan)
    if not np.all(np.isfinite(Z[surface])) or not np.all(Z[surface] > 0):
        raise InvalidInput(
            'shading refinement diverged (non-finite or non-positive depth)', key='Z'
        )
    return RefineResult(Z, rms, report)
