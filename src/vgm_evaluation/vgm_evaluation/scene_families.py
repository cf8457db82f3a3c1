"""Families of stereo scenes for depth benches and tests: a smooth surface in front of
an already-rectified pair (both cameras K, the right one ``baseline`` to the right),
rendered with the shared Oren-Nayar model (``vgm_common.reflectance``) as the
sensor_sim renderer shades, with ground-truth depth. No rclpy.

Kinds: ``bumps`` (random Gaussian bumps and dents), ``ridges`` (random sinusoidal
ridges), ``saddle``, ``sphere`` (a cap), ``vase`` (Zhang et al. 1999's vase as a
relief). Options: light direction, resolution (focal length scales with the width, so
every resolution sees the same scene), noise, ``textured`` (a random albedo pattern),
``curve`` (a dark ellipse drawn on the surface, like the scenarios' curve), and a
principal-point offset of the right camera. Every random choice takes ``seed``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.reflectance import oren_nayar

KINDS = ('bumps', 'ridges', 'saddle', 'sphere', 'vase')

# (X, Y) [m] -> (h, dh/dX, dh/dY), each of their shape
HeightFunction = Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray, FloatArray]]
# (X, Y) [m] -> boolean mask of the points on the surface
DomainFunction = Callable[[FloatArray, FloatArray], npt.NDArray[np.bool_]]


class StereoScene(NamedTuple):
    """One rendered rectified pair: uint8 images, ground-truth depth along the left optical
    axis, both intrinsics, the baseline and the shading parameters used."""

    left: npt.NDArray[np.uint8]  # (H, W)
    right: npt.NDArray[np.uint8]  # (H, W)
    depth: FloatArray  # (H, W) [m] along the left optical axis, NaN off the surface
    K_left: FloatArray  # (3, 3)
    K_right: FloatArray  # (3, 3): K_left but cx moved by -cx_offset
    baseline: float  # [m]
    light: FloatArray  # (3,) unit, surface -> light, left optical frame
    albedo: float
    ambient: float
    roughness: float


def _height_function(
    kind: str, rng: np.random.Generator, half: float
) -> tuple[HeightFunction, DomainFunction | None]:
    """h(X, Y) [m] toward the camera and its gradient, over |X|, |Y| <= ``half``, and where
    the surface is within that square (None: all of it)."""
    if kind == 'bumps':
        n = int(rng.integers(3, 7))
        centres = rng.uniform(-0.7, 0.7, (n, 2)) * half
        sigmas = rng.uniform(0.2, 0.45, n) * half
        amps = rng.uniform(0.3, 0.7, n) * half * 0.35 * rng.choice([-1, 1], n)

        def h(X: FloatArray, Y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
            value, gx, gy = np.zeros_like(X), np.zeros_like(X), np.zeros_like(X)
            for (cx, cy), s, a in zip(centres, sigmas, amps):
                g = a * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * s**2))
                value += g
                gx -= g * (X - cx) / s**2
                gy -= g * (Y - cy) / s**2
            return value, gx, gy

        return h, None
    if kind == 'ridges':
        angle = rng.uniform(0, np.pi)
        k = 2 * np.pi / (rng.uniform(0.6, 1.2) * half)
        a = rng.uniform(0.05, 0.09) * half
        c, s = np.cos(angle), np.sin(angle)

        def h(X: FloatArray, Y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
            phase = k * (c * X + s * Y)
            return a * np.cos(phase), -a * k * c * np.sin(phase), -a * k * s * np.sin(phase)

        return h, None
    if kind == 'saddle':
        a = rng.uniform(0.2, 0.35) / half

        def h(X: FloatArray, Y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
            return a * (X**2 - Y**2), 2 * a * X, -2 * a * Y

        return h, None
    if kind == 'sphere':  # a hemisphere of radius ``half``, its rim hidden (< 0.95 r)
        radius = half

        def h(X: FloatArray, Y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
            r2 = np.minimum(X**2 + Y**2, 0.9 * radius**2)
            cap = np.sqrt(radius**2 - r2)
            return cap, -X / cap, -Y / cap

        return h, lambda X, Y: X**2 + Y**2 <= 0.9 * radius**2
    if kind == 'vase':
        # Zhang et al.: sqrt(f(y)^2 - x^2), y in [0, 1] down the image
        def h(X: FloatArray, Y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
            x, y = X / (2 * half), Y / (2 * half) + 0.5
            f = 0.15 - 0.1 * y * (6 * y + 1) ** 2 * (y - 1) ** 2 * (3 * y - 2)
            df = -0.1 * (
                (6 * y + 1) ** 2 * (y - 1) ** 2 * (3 * y - 2)
                + y * 12 * (6 * y + 1) * (y - 1) ** 2 * (3 * y - 2)
                + y * (6 * y + 1) ** 2 * 2 * (y - 1) * (3 * y - 2)
                + y * (6 * y + 1) ** 2 * (y - 1) ** 2 * 3
            )
            inside = np.maximum(f**2 - x**2, 1e-4)
            value = np.sqrt(inside)
            # d/dX = d/dx / (2 half), and h = 2 half sqrt(.): the factors cancel
            return 2 * half * value, -x / value, f * df / value

        return h, lambda X, Y: (
            (np.abs(Y) <= half)
            & (
                np.abs(X)
                < 2
                * half
                * np.abs(
                    0.15
                    - 0.1
                    * (Y / (2 * half) + 0.5)
                    * (6 * (Y / (2 * half) + 0.5) + 1) ** 2
                    * (Y / (2 * half) - 0.5) ** 2
                    * (3 * (Y / (2 * half) + 0.5) - 2)
                )
                * 0.97
            )
        )
    raise InvalidInput(f'kind must be one of {KINDS}, got {kind!r}', key='kind')


def draw_scene(
    kind: str = 'bumps',
    seed: int = 0,
    size: tuple[int, int] = (320, 240),
    noise: float = 1.0,
    light: npt.ArrayLike = (-0.3, -0.3, -0.9),
    textured: bool = False,
    curve: bool = True,
    distance: float = 0.8,
    baseline: float = 0.08,
    cx_offset: float = 0.0,
    albedo: float = 0.8,
    ambient: float = 0.08,
    roughness: float = 0.3,
) -> StereoScene:
    """One ``StereoScene``: the surface Z = distance - h(X, Y) over a square seen by
    ~60 % of the image width, the rest background (black + noise)."""
    width, height = (int(v) for v in size)
    rng = np.random.default_rng(seed)
    focal = 1.0 * width
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    K_right = K.copy()
    K_right[0, 2] -= cx_offset
    half = 0.3 * distance * height / focal  # the square spans 60 % of the image height
    h, domain = _height_function(kind, rng, half)
    light_unit = np.asarray(light, dtype=float) / np.linalg.norm(light)
    pattern_k = rng.uniform(
        2 * np.pi / (0.3 * half), 2 * np.pi / (0.1 * half), (6, 2)
    ) * rng.choice([-1, 1], (6, 2))
    pattern_phase = rng.uniform(0, 2 * np.pi, 6)
    ellipse = rng.uniform(0.45, 0.75, 2) * half
    grey_noise_rng = np.random.default_rng([seed, 1])

    def view(centre_x: float, K_view: FloatArray) -> tuple[npt.NDArray[np.uint8], FloatArray]:
        v, u = np.mgrid[:height, :width].astype(float)
        xn, yn = (u - K_view[0, 2]) / K_view[0, 0], (v - K_view[1, 2]) / K_view[1, 1]
        Z = np.full(u.shape, distance)
        for _ in range(12):  # Newton on g(Z) = Z - distance + h(X(Z), Y(Z))
            X, Y = centre_x + Z * xn, Z * yn
            value, gx, gy = h(X, Y)
            Z = Z - (Z - distance + value) / (1 + gx * xn + gy * yn)
        X, Y = centre_x + Z * xn, Z * yn
        value, gx, gy = h(X, Y)
        on_surface = domain or (lambda X, Y: (np.abs(X) <= half) & (np.abs(Y) <= half))
        with np.errstate(invalid='ignore'):
            on = on_surface(X, Y) & (np.abs(Z - distance + value) < 1e-7) & (Z > 0)
        normals = -np.stack([gx, gy, np.ones_like(gx)], axis=-1)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        views = -np.stack([xn, yn, np.ones_like(xn)], axis=-1)
        views /= np.linalg.norm(views, axis=-1, keepdims=True)
        shade = oren_nayar(normals, light_unit, views, roughness)
        a = np.full(u.shape, albedo)
        if textured:
            pattern = np.mean(
                [np.sin(kx * X + ky * Y + p) for (kx, ky), p in zip(pattern_k, pattern_phase)],
                axis=0,
            )
            a = a * (1 + 0.6 * pattern)
        if curve:  # a dark line ~4 mm wide on the surface
            radius = np.hypot(X / ellipse[0], Y / ellipse[1])
            a = np.where(np.abs(radius - 1) * min(ellipse) < 0.002, 0.15 * albedo, a)
        grey = np.clip(255.0 * a * (shade + ambient), 0, 255)
        grey = np.where(on, grey, 0.0)
        grey = grey + grey_noise_rng.normal(0, noise, grey.shape)
        return np.clip(np.rint(grey), 0, 255).astype(np.uint8), np.where(on, Z, np.nan)

    left, depth = view(0.0, K)
    right, _ = view(baseline, K_right)
    return StereoScene(
        left, right, depth, K, K_right, baseline, light_unit, albedo, ambient, roughness
    )
