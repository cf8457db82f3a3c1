"""Generalised Lambertian (Oren-Nayar) reflectance, shared by the renderer that makes
the images and the shape-from-shading that inverts them (ALGORITHMS.md §4.3, A5.1).

R = M cos(theta_i) with M = A + B max(0, cos(phi_r - phi_i)) sin(alpha) f(beta),
A = 1 - 0.5 s^2 / (s^2 + 0.33), B = 0.45 s^2 / (s^2 + 0.09), s = roughness [rad],
alpha = max(theta_i, theta_r), beta = min(theta_i, theta_r); f = tan (``'oren_nayar'``,
the published model) or sin (``'thesis'``, as the thesis prints it). Lambert's
cos(theta_i) when the roughness is 0. Albedo and source radiance are the caller's.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

VARIANTS = ('oren_nayar', 'thesis')


def oren_nayar_terms(
    normals: npt.ArrayLike,
    light: npt.ArrayLike,
    views: npt.ArrayLike,
    roughness: float,
    variant: str = 'oren_nayar',
) -> tuple[FloatArray, FloatArray]:
    """(M, cos_theta_i) on broadcast arrays of unit vectors (..., 3).

    ``cos_theta_i`` is not clamped (Tsai-Shah's residual uses it as is); ``M`` is the
    bracket above, exactly ``A`` (a constant array) when the roughness is 0.
    """
    if variant not in VARIANTS:
        raise InvalidInput(
            f'variant: expected one of {VARIANTS}, got {variant!r}', key='variant', value=variant
        )
    normals, light, views = np.broadcast_arrays(
        np.asarray(normals, dtype=float),
        np.asarray(light, dtype=float),
        np.asarray(views, dtype=float),
    )
    cos_i = np.sum(normals * light, axis=-1)
    s2 = roughness**2
    A, B = 1 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)
    if B == 0:
        return np.full(cos_i.shape, A), cos_i
    cos_r = np.sum(normals * views, axis=-1)
    theta_i = np.arccos(np.clip(cos_i, -1.0, 1.0))
    theta_r = np.arccos(np.clip(cos_r, -1.0, 1.0))
    alpha, beta = np.maximum(theta_i, theta_r), np.minimum(theta_i, theta_r)
    # cos(phi_r - phi_i): angle between light and view projected on the tangent plane.
    light_tangent = light - cos_i[..., None] * normals
    view_tangent = views - cos_r[..., None] * normals
    lengths = np.linalg.norm(light_tangent, axis=-1) * np.linalg.norm(view_tangent, axis=-1)
    with np.errstate(divide='ignore', invalid='ignore'):
        cos_phi = np.where(
            lengths > 1e-12, np.sum(light_tangent * view_tangent, axis=-1) / lengths, 0.0
        )
        f_beta = np.tan(beta) if variant == 'oren_nayar' else np.sin(beta)
    return A + B * np.maximum(0.0, cos_phi) * np.sin(alpha) * f_beta, cos_i


def oren_nayar(
    normals: npt.ArrayLike,
    light: npt.ArrayLike,
    views: npt.ArrayLike,
    roughness: float,
    variant: str = 'oren_nayar',
) -> FloatArray:
    """Reflectance factor M cos(theta_i), without albedo; 0 where the light or the
    viewer is behind the surface."""
    M, cos_i = oren_nayar_terms(normals, light, views, roughness, variant)
    cos_r = np.sum(np.asarray(normals) * np.asarray(views), axis=-1)
    lit = (cos_i > 0) & (cos_r > 0)
    with np.errstate(invalid='ignore'):  # tan(beta) of unlit points is discarded here
        return np.where(lit, M * cos_i, 0.0)
