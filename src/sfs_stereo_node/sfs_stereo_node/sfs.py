"""Shape from shading by the Tsai-Shah linearisation with a generalised Lambertian map
(ALGORITHMS.md §4.3, A5.1-A5.4, A5.10).

Gradients are per pixel: p = dZ/dx along columns, q = dZ/dy along rows, surface normal
(-p, -q, 1), light (-ps, -qs, 1), viewer (0, 0, 1); Z is the height towards the viewer.
The source radiance E0 is taken as pi, so R = albedo cos(theta_i) when roughness = 0.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.reflectance import oren_nayar_terms


def reflectance_terms(
    p: npt.ArrayLike,
    q: npt.ArrayLike,
    ps: float,
    qs: float,
    albedo: float,
    roughness: float,
    variant: str = 'thesis',
) -> tuple[FloatArray, FloatArray]:
    """(M, cos_theta_i) of (5.3.5), R = M cos_theta_i, on broadcast arrays p, q: the
    shared Oren-Nayar model with normal (-p, -q, 1), light (-ps, -qs, 1), viewer (0, 0, 1).

    ``'thesis'`` uses sin(alpha) sin(beta) as printed, ``'oren_nayar'`` sin(alpha)
    tan(beta) (A5.1); both reduce to M = albedo for roughness = 0.
    """
    p, q = np.broadcast_arrays(np.asarray(p, dtype=float), np.asarray(q, dtype=float))
    normals = np.stack([-p, -q, np.ones_like(p)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    light = np.array([-ps, -qs, 1.0]) / np.sqrt(1 + ps**2 + qs**2)
    M, cos_i = oren_nayar_terms(normals, light, np.array([0.0, 0.0, 1.0]), roughness, variant)
    return albedo * M, cos_i


def reflectance_terms_fast(
    p: npt.ArrayLike,
    q: npt.ArrayLike,
    ps: float,
    qs: float,
    albedo: float,
    roughness: float,
    variant: str = 'thesis',
) -> tuple[FloatArray, FloatArray]:
    """``reflectance_terms`` in closed form for the fixed viewer (0, 0, 1): the same
    Oren-Nayar values (equal to rounding, unit-tested) without building normal vectors
    or calling arccos, ~4x faster; sfs_depth's inner loop uses it.

    cos_i = (1 + p ps + q qs) / (|n| |s|), cos_r = 1 / |n|; sin(alpha), sin(beta) from
    the smaller / larger cosine; cos(phi_r - phi_i) = (l_z - cos_i cos_r) /
    (sin_i sin_r), the angle between light and viewer projected on the tangent plane.
    """
    p, q = np.broadcast_arrays(np.asarray(p, dtype=float), np.asarray(q, dtype=float))
    grad2 = p * p + q * q
    norm_n = np.sqrt(1.0 + grad2)
    norm_s = np.sqrt(1.0 + ps * ps + qs * qs)
    cos_i = (1.0 + p * ps + q * qs) / (norm_n * norm_s)
    s2 = roughness**2
    A, B = 1 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)
    if B == 0:
        return albedo * np.full(cos_i.shape, A), cos_i
    cos_r = 1.0 / norm_n
    ci, cr = np.clip(cos_i, -1.0, 1.0), np.clip(cos_r, -1.0, 1.0)
    sin2_i = np.maximum(1.0 - ci * ci, 0.0)
    sin2_r = grad2 / (1.0 + grad2)  # 1 - cos_r^2 without cancellation
    lengths = np.sqrt(sin2_i * sin2_r)
    with np.errstate(divide='ignore', invalid='ignore'):
        cos_phi = np.where(lengths > 1e-12, (1.0 / norm_s - cos_i * cos_r) / lengths, 0.0)
        sin_alpha = np.sqrt(np.maximum(1.0 - np.minimum(ci, cr) ** 2, 0.0))
        cos_beta = np.maximum(ci, cr)
        sin_beta = np.sqrt(np.maximum(1.0 - cos_beta**2, 0.0))
        f_beta = sin_beta / cos_beta if variant == 'oren_nayar' else sin_beta
    if variant not in ('oren_nayar', 'thesis'):
        raise InvalidInput(
            f'variant: expected oren_nayar or thesis, got {variant!r}',
            key='variant',
            value=variant,
        )
    return albedo * (A + B * np.maximum(0.0, cos_phi) * sin_alpha * f_beta), cos_i


def reflectance(
    p: npt.ArrayLike,
    q: npt.ArrayLike,
    ps: float,
    qs: float,
    albedo: float,
    roughness: float,
    variant: str = 'thesis',
) -> FloatArray:
    """Image irradiance R(p, q) = M max(0, cos_theta_i) (5.3.5), attached shadows at 0."""
    M, cos_i = reflectance_terms(p, q, ps, qs, albedo, roughness, variant)
    return M * np.maximum(cos_i, 0.0)


def light_gradient(light_optical: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """(ps, qs) of a unit light direction (surface -> light) given in an optical frame (x
    right, y down, z forward): the SFS frame has the same x, y and z toward the viewer,
    so (-ps, -qs, 1) ~ (lx, ly, -lz), ps = lx / lz, qs = ly / lz. The light must be on
    the camera's side of the scene (lz < 0)."""
    lx, ly, lz = (float(v) for v in np.ravel(light_optical))
    if not lz < -1e-3 * np.sqrt(lx**2 + ly**2 + lz**2):
        raise InvalidInput(
            f'light direction {light_optical} is not on the camera side '
            '(z must be < 0 in the optical frame)',
            key='light_direction',
        )
    return lx / lz, ly / lz


def upwind_signs(light: tuple[float, float]) -> tuple[float, float]:
    """(sx, sy) in {-1, +1}: the difference direction along each axis facing the light.

    With p = sx (Z(x) - Z(x - sx)) (backward differences for sx = +1, forward for -1),
    dp/dZ(x) = sx and the Newton derivative at a flat start is
    -M (sx ps + sy qs) / |s| = -M (|ps| + |qs|) / |s|: never zero for an oblique light.
    The thesis's fixed backward differences give -M (ps + qs) / |s|, which vanishes for
    a light along the image's anti-diagonal (ps = -qs) and is weak near it; that was
    the old restriction to lights near the diagonal.
    """
    ps, qs = light
    return (1.0 if ps >= 0 else -1.0), (1.0 if qs >= 0 else -1.0)


def _gradients(Z: FloatArray, sx: float = 1.0, sy: float = 1.0) -> tuple[FloatArray, FloatArray]:
    """p = sx (Z(x, y) - Z(x - sx, y)), q = sy (Z(x, y) - Z(x, y - sy)); missing
    neighbours count as 0. sx = sy = 1 are the thesis's backward differences."""
    if sx > 0:
        p = Z - np.pad(Z, ((0, 0), (1, 0)))[:, :-1]
    else:
        p = np.pad(Z, ((0, 0), (0, 1)))[:, 1:] - Z
    if sy > 0:
        q = Z - np.pad(Z, ((1, 0), (0, 0)))[:-1, :]
    else:
        q = np.pad(Z, ((0, 1), (0, 0)))[1:, :] - Z
    return p, q


def sfs_depth(
    E: npt.ArrayLike,
    light: tuple[float, float],
    albedo: float = 1.0,
    roughness: float = 0.0,
    iterations: int = 200,
    tol: float = 1e-4,
    eps_c: float = 1e-3,
    variant: str = 'thesis',
    mask: npt.ArrayLike | None = None,
    upwind: bool = True,
    max_step: float | None = None,
) -> FloatArray:
    """Relative height map from one image by the Jacobi-Newton iteration (5.3.11).

    ``E`` (H, W) irradiance scaled to [0, 1]; ``light`` (ps, qs). Starts from Z = 0 and
    updates every pixel at once, Z <- Z - f / (df/dZ) with f = E - M max(0, cos_theta_i),
    M lagged from the previous iterate (A5.2), the (1 + p^2 + q^2)^(3/2) denominator
    (A5.3) and |df/dZ| clamped from below at ``eps_c`` keeping its sign (A5.4). Stops after
    ``iterations`` or when max |dZ| < ``tol``. Returns (H, W) float, up to scale and offset.

    ``upwind`` (default) takes each axis's difference from the side facing the light
    (``upwind_signs``), so any oblique light works; False is the thesis's backward
    differences (good only for lights near the image diagonal, ps + qs far from 0).
    ``max_step`` > 0 limits |dZ| per iteration (damped Newton): all pixels move at once,
    so an undamped step taken while the upstream neighbours still lag can jump past the
    reflectance maximum onto the wrong branch and diverge (measured on a Gaussian bump
    lit along x); None or 0 is the thesis's full step.
    ``mask`` (H, W) bool, optional: only these pixels are updated (the others, e.g. the
    background, stay at 0).
    """
    E = np.asarray(E, dtype=float)
    if E.ndim != 2:
        raise InvalidInput(
            f'E: expected an (H, W) image, got shape {E.shape}', key='E', value=E.shape
        )
    if mask is not None and np.shape(mask) != E.shape:
        raise InvalidInput(f'mask {np.shape(mask)} differs from E {E.shape}', key='mask')
    ps, qs = light
    sx, sy = upwind_signs(light) if upwind else (1.0, 1.0)
    norm_s = np.sqrt(1 + ps**2 + qs**2)
    Z = np.zeros_like(E)
    for _ in range(iterations):
        p, q = _gradients(Z, sx, sy)
        M, cos_i = reflectance_terms_fast(p, q, ps, qs, albedo, roughness, variant)
        f = E - M * np.maximum(cos_i, 0.0)
        pq = 1 + p**2 + q**2
        # df/dZ = -(sx dR/dp + sy dR/dq), M held constant (A5.2)
        df = -M * (
            (sx * ps + sy * qs) / (np.sqrt(pq) * norm_s)
            - (sx * p + sy * q) * (1 + p * ps + q * qs) / (pq**1.5 * norm_s)
        )
        df = np.where(np.abs(df) < eps_c, np.where(df < 0, -eps_c, eps_c), df)
        step = f / df
        if max_step:
            step = np.clip(step, -max_step, max_step)
        if mask is not None:
            step = np.where(mask, step, 0.0)
        Z = Z - step
        if np.max(np.abs(step)) < tol:
            break
    return Z
