"""Shape from shading by the Tsai-Shah linearisation with a generalised Lambertian map
(ALGORITHMS.md §4.3, A5.1-A5.4, A5.10).

Gradients are per pixel: p = dZ/dx along columns, q = dZ/dy along rows, surface normal
(-p, -q, 1), light (-ps, -qs, 1), viewer (0, 0, 1); Z is the height towards the viewer.
The source radiance E0 is taken as pi, so R = albedo cos(theta_i) when roughness = 0.
"""
import numpy as np

from vgm_common.errors import InvalidInput
from vgm_common.reflectance import oren_nayar_terms


def reflectance_terms(p, q, ps, qs, albedo, roughness, variant='thesis'):
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

def reflectance(p, q, ps, qs, albedo, roughness, variant='thesis'):
    """Image irradiance R(p, q) = M max(0, cos_theta_i) (5.3.5), attached shadows at 0."""
    M, cos_i = reflectance_terms(p, q, ps, qs, albedo, roughness, variant)
    return M * np.maximum(cos_i, 0.0)


def _gradients(Z):
    """Backward differences p = Z(x, y) - Z(x-1, y), q = Z(x, y) - Z(x, y-1); missing
    neighbours count as 0."""
    p = Z - np.pad(Z, ((0, 0), (1, 0)))[:, :-1]
    q = Z - np.pad(Z, ((1, 0), (0, 0)))[:-1, :]
    return p, q


def sfs_depth(E, light, albedo=1.0, roughness=0.0, iterations=200, tol=1e-4, eps_c=1e-3,
              variant='thesis'):
    """Relative height map from one image by the Jacobi-Newton iteration (5.3.11).

    ``E`` (H, W) irradiance scaled to [0, 1]; ``light`` (ps, qs). Starts from Z = 0 and
    updates every pixel at once, Z <- Z - f / (df/dZ) with f = E - M max(0, cos_theta_i),
    M lagged from the previous iterate (A5.2), the (1 + p^2 + q^2)^(3/2) denominator
    (A5.3) and |df/dZ| clamped from below at ``eps_c`` keeping its sign (A5.4). Stops after
    ``iterations`` or when max |dZ| < ``tol``. Returns (H, W) float, up to scale and offset.
    """
    E = np.asarray(E, dtype=float)
    if E.ndim != 2:
        raise InvalidInput(f'E: expected an (H, W) image, got shape {E.shape}', key='E',
                           value=E.shape)
    ps, qs = light
    norm_s = np.sqrt(1 + ps**2 + qs**2)
    Z = np.zeros_like(E)
    for _ in range(iterations):
        p, q = _gradients(Z)
        M, cos_i = reflectance_terms(p, q, ps, qs, albedo, roughness, variant)
        f = E - M * np.maximum(cos_i, 0.0)
        pq = 1 + p**2 + q**2
        df = -M * ((ps + qs) / (np.sqrt(pq) * norm_s)
                   - (p + q) * (1 + p * ps + q * qs) / (pq**1.5 * norm_s))
        df = np.where(np.abs(df) < eps_c, np.where(df < 0, -eps_c, eps_c), df)
        step = f / df
        Z = Z - step
        if np.max(np.abs(step)) < tol:
            break
    return Z
