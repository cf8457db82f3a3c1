"""Generated rectified stereo scenes with known disparity, seeded: a textured slanted
plane with fronto-parallel blobs in front (for tests and the bench)."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from stereo_coding_node.views import synthesise_right
from vgm_common.geometry import FloatArray


def generated_scene(
    shape: tuple[int, int], seed: int, max_disparity_px: float | None = None
) -> tuple[npt.NDArray[np.uint8], np.ndarray, FloatArray]:
    """(left (H, W) uint8, right (H, W) uint8, disparity [px] (H, W) float64) for a
    random scene; disparities up to about ``max_disparity_px`` (default W / 10)."""
    H, W = shape
    rng = np.random.default_rng(seed)
    top = max_disparity_px or W / 10.0
    # Texture: noise at several scales, then shading, as a natural image has.
    texture = np.zeros(shape)
    for scale in (1.5, 4.0, 12.0, 30.0):
        texture += cv2.GaussianBlur(rng.normal(0, 1, shape), (0, 0), scale) * scale**0.7
    texture = (texture - texture.min()) / np.ptp(texture)
    rows, cols = np.indices(shape)
    a, b = rng.uniform(-0.3, 0.3, 2)
    disparity = top * (0.35 + 0.15 * (a * cols / W + b * rows / H))
    for _ in range(int(rng.integers(2, 5))):
        cy, cx = rng.uniform(0.2, 0.8) * H, rng.uniform(0.2, 0.8) * W
        ry, rx = rng.uniform(0.08, 0.25) * H, rng.uniform(0.08, 0.25) * W
        inside = ((rows - cy) / ry) ** 2 + ((cols - cx) / rx) ** 2 < 1
        disparity = np.where(inside, np.maximum(disparity, top * rng.uniform(0.6, 1.0)), disparity)
    shading = 0.6 + 0.4 * np.cos(rng.uniform(0, np.pi) + cols / W * rng.uniform(1, 3))
    left = np.clip(np.rint(255 * (0.1 + 0.8 * texture * shading)), 0, 255).astype(np.uint8)
    right = synthesise_right(left, disparity)
    return left, right, disparity
