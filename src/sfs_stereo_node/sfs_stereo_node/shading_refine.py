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
evaluations of the model; the sparse normal equations are solved by scipy's spsolve on
small grids and by Jacobi-preconditioned CG on large ones. w_i, v_i are Cauchy (IRLS)
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
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.reflectance import oren_nayar

BoolArray = npt.NDArray[np.bool_]
IndexArray = npt.NDArray[np.int64]  # unknown index of each grid pixel, -1 off the surface

# Levels with more unknowns than this take conjugate-gradient steps instead of a sparse
# direct solve (SuperLU fill-in grows fast with the grid; the coarser levels have fixed
# the smooth part of the update already, which is what CG converges slowly on).
DIRECT_SOLVE_LIMIT = 2000
CG_ITERATIONS = 300
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
    normals = np.stack([fx * Zu, fy * Zv, -(Z + (u - cx) * Zu + (v - cy) * Zv)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    views = -np.stack([xn, yn, np.ones_like(xn)], axis=-1)
    views /= np.linalg.norm(views, axis=-1, keepdims=True)
    R = oren_nayar(normals, model.light, views, model.roughness)
    return np.clip(255.0 * model.albedo * (model.intensity * R + model.ambient), 0.0, 255.0)


def _grid_index(mask: BoolArray) -> IndexArray:
    index = np.full(mask.shape, -1, dtype=np.int64)
    index[mask] = np.arange(int(mask.sum()))
    return index


def _first_derivative(
    mask: BoolArray, index: IndexArray, axis: int
) -> tuple[sp.csr_matrix, BoolArray]:
    """Sparse derivative along ``axis`` (1 = u, columns; 0 = v, rows) of the unknowns
    (the ``mask`` pixels): central where both neighbours are unknowns, one-sided where
    one is; ``has`` marks rows with a derivative."""
    H, W = mask.shape
    fwd = np.zeros_like(mask)
    bwd = np.zeros_like(mask)
    if axis == 1:
        fwd[:, :-1] = mask[:, :-1] & mask[:, 1:]
        bwd[:, 1:] = mask[:, 1:] & mask[:, :-1]
        step = 1
    else:
        fwd[:-1] = mask[:-1] & mask[1:]
        bwd[1:] = mask[1:] & mask[:-1]
        step = W
    flat = np.flatnonzero(mask.ravel())
    f, b = fwd.ravel()[flat], bwd.ravel()[flat]
    rows, cols, vals = [], [], []
    n = np.arange(len(flat))
    both = f & b
    only_f, only_b = f & ~b, b & ~f
    idx = index.ravel()
    for sel, terms in (
        (both, ((step, 0.5), (-step, -0.5))),
        (only_f, ((step, 1.0), (0, -1.0))),
        (only_b, ((0, 1.0), (-step, -1.0))),
    ):
        for offset, value in terms:
            rows.append(n[sel])
            cols.append(idx[flat[sel] + offset])
            vals.append(np.full(int(sel.sum()), value))
    D = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(len(flat), len(flat)),
    )
    return D, f | b


def _second_differences(mask: BoolArray, index: IndexArray) -> sp.csr_matrix:
    """Sparse Z_uu, Z_vv and Z_uv (forward cross difference) rows wherever all their
    pixels are unknowns: the thin-plate smoothness operator."""
    H, W = mask.shape
    blocks = []
    idx = index.ravel()
    stencils = (
        ((0, -1, 1.0), (0, 0, -2.0), (0, 1, 1.0)),
        ((-1, 0, 1.0), (0, 0, -2.0), (1, 0, 1.0)),
        ((0, 0, 1.0), (0, 1, -1.0), (1, 0, -1.0), (1, 1, 1.0)),
    )
    for stencil in stencils:
        ok = mask.copy()
        for dv, du, _ in stencil:
            shifted = np.zeros_like(mask)
            src = mask[max(dv, 0) : H + min(dv, 0), max(du, 0) : W + min(du, 0)]
            shifted[max(-dv, 0) : H + min(-dv, 0), max(-du, 0) : W + min(-du, 0)] = src
            ok &= shifted
        centres = np.flatnonzero(ok.ravel())
        n = len(centres)
        rows = np.repeat(np.arange(n), len(stencil))
        cols = np.stack([idx[centres + dv * W + du] for dv, du, _ in stencil], axis=1).ravel()
        vals = np.tile([w for _, _, w in stencil], n)
        blocks.append(sp.csr_matrix((vals, (rows, cols)), shape=(n, int(mask.sum()))))
    return sp.vstack(blocks).tocsr()


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
    level: _Level, sigma_z: float, curvature_sigma: float, robust_iterations: int = 6
) -> FloatArray:
    """Thin-plate interpolation of the stereo depths on the level's surface."""
    index = _grid_index(level.surface)
    has = np.isfinite(level.stereo[level.surface])
    if has.sum() < 3:
        raise InvalidInput(
            f'only {int(has.sum())} stereo depths on the coarsest grid: '
            'too few to start the shading refinement',
            key='Z_stereo',
        )
    D2 = _second_differences(level.surface, index) / curvature_sigma
    smooth = D2.T @ D2
    w0 = np.where(has, level.stereo_count[level.surface], 0.0) / sigma_z**2
    target = np.nan_to_num(level.stereo[level.surface])
    # A weak pull (0.1 m std) toward the median stereo depth holds surface pieces
    # without any match, which the thin plate alone leaves undetermined.
    prior_depth, prior_weight = float(np.median(target[has])), 1.0 / 0.1**2
    w = w0
    for _ in range(robust_iterations):  # IRLS: wrong matches lose their weight
        A = sp.diags(w + prior_weight) + smooth
        z = spsolve(A.tocsc(), w * target + prior_weight * prior_depth)
        r = (z - target)[has]
        scale = _robust_scale(r, 3 * sigma_z)
        w = w0 * np.where(has, 1.0 / (1.0 + ((z - target) / scale) ** 2), 0.0)
    return z


def _jacobi_cg(A: sp.csr_matrix, b: FloatArray, iterations: int, rtol: float = 1e-4) -> FloatArray:
    """x ~ A^-1 b for a symmetric positive definite sparse ``A`` by Jacobi-preconditioned
    conjugate gradients from x = 0. Own loop with plain numpy reductions: scipy's cg
    calls BLAS dot products, whose threads stall on a loaded machine."""
    inv_diag = 1.0 / A.diagonal()
    x = np.zeros_like(b)
    r = b.copy()
    z = inv_diag * r
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
        z = inv_diag * r
        rz, rz_old = float(np.sum(r * z)), rz
        d = z + (rz / rz_old) * d
    return x


def _gauss_newton(
    level: _Level,
    z: FloatArray,
    model: ShadingModel,
    sigma_i: float,
    sigma_z: float,
    curvature_sigma: float,
    steps: int,
    cauchy: float,
    max_step: float | None,
) -> tuple[FloatArray, float]:
    mask = level.surface
    index = _grid_index(mask)
    Du, has_u = _first_derivative(mask, index, axis=1)
    Dv, has_v = _first_derivative(mask, index, axis=0)
    D2 = _second_differences(mask, index) / curvature_sigma
    rows, cols = np.nonzero(mask)
    u_grid, v_grid = cols.astype(float), rows.astype(float)
    shade = level.shade[mask] & has_u & has_v
    observed = level.image[mask][shade]
    u_s, v_s = u_grid[shade], v_grid[shade]
    has = np.isfinite(level.stereo[mask])
    w_stereo = np.where(has, level.stereo_count[mask], 0.0) / sigma_z**2
    target = np.nan_to_num(level.stereo[mask])
    S = sp.diags(shade.astype(float), format='csr')[shade]  # selects the shading rows
    smooth = D2.T @ D2
    K = level.K
    rms = float('nan')
    for _ in range(steps):
        Zs, Zu, Zv = z[shade], (Du @ z)[shade], (Dv @ z)[shade]
        pred = predicted_grey(Zs, Zu, Zv, u_s, v_s, K, model)
        r = observed - pred
        # Model derivatives w.r.t. Zu, Zv by central differences; the model depends on
        # (Zu/Z, Zv/Z) only, so dI/dZ = -(Zu dI/dZu + Zv dI/dZv) / Z.
        h = 1e-4 * Zs
        g_u = (
            predicted_grey(Zs, Zu + h, Zv, u_s, v_s, K, model)
            - predicted_grey(Zs, Zu - h, Zv, u_s, v_s, K, model)
        ) / (2 * h)
        g_v = (
            predicted_grey(Zs, Zu, Zv + h, u_s, v_s, K, model)
            - predicted_grey(Zs, Zu, Zv - h, u_s, v_s, K, model)
        ) / (2 * h)
        g_z = -(Zu * g_u + Zv * g_v) / Zs
        # Cauchy scale from the residuals themselves while they are large (a poor start
        # is not outvoted by its own misfit), cauchy sigma_i once they are small.
        weight = 1.0 / (1.0 + (r / _robust_scale(r, cauchy * sigma_i)) ** 2) / sigma_i**2
        r_z = (z - target)[has]
        scale = _robust_scale(r_z, cauchy * sigma_z)
        w_z = w_stereo * np.where(has, 1.0 / (1.0 + ((z - target) / scale) ** 2), 0.0)
        J = sp.diags(g_z) @ S + sp.diags(g_u) @ (S @ Du) + sp.diags(g_v) @ (S @ Dv)
        JW = J.T @ sp.diags(weight)
        # + a 1 m prior on the update keeps A positive definite where a pixel has lost
        # every term (e.g. an island between cut edges); negligible elsewhere.
        A = JW @ J + sp.diags(w_z + 1.0) + smooth
        b = JW @ r - w_z * (z - target) - smooth @ z
        if len(z) <= DIRECT_SOLVE_LIMIT:
            dz = spsolve(A.tocsc(), b)
        else:  # the coarser levels fixed the smooth part: a few Jacobi-CG iterations suffice
            dz = _jacobi_cg(A.tocsr(), b, CG_ITERATIONS)
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
    z = _initial_depth(levels[0], sigma_z, curvature_sigma * levels[0].factor ** 2)
    Z = np.full(levels[0].surface.shape, np.nan)
    Z[levels[0].surface] = z
    report: list[tuple[int, int, int]] = []
    rms = float('nan')
    for i, level in enumerate(levels):
        if i > 0:
            z = _upsampled_start(Z, levels[i - 1], level)
        n_steps = finest_steps if level.factor == 1 else steps[min(i, len(steps) - 1)]
        z, rms = _gauss_newton(
            level,
            z,
            model,
            sigma_i,
            sigma_z,
            curvature_sigma * level.factor**2,
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
