"""The right view synthesised from the left image and its disparity (left reference, a
left pixel at column x appears at x - d in the right image)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def synthesise_right(left: npt.ArrayLike, disparity_px: npt.ArrayLike) -> np.ndarray:
    """Forward-warp ``left`` (H, W) uint8 by ``disparity_px`` (H, W) [px], NaN unknown.

    Where several left pixels land on one right pixel the nearer (larger disparity)
    wins; holes (occlusions, unknown disparity) take the nearest filled pixel on their
    right along the row (the background the occluder uncovers). Returns (H, W) uint8."""
    left = np.asarray(left)
    H, W = left.shape
    d = np.asarray(disparity_px, dtype=float)
    rows, cols = np.indices((H, W))
    ok = np.isfinite(d)
    target = np.rint(cols - np.where(ok, d, 0.0)).astype(int)
    ok &= (target >= 0) & (target < W)
    order = np.argsort(d[ok], kind='stable')  # far first, so the near ones overwrite
    right = np.zeros((H, W), dtype=left.dtype)
    filled = np.zeros((H, W), dtype=bool)
    r, t, v = rows[ok][order], target[ok][order], left[ok][order]
    right[r, t] = v
    filled[r, t] = True
    # Nearest filled column at or right of each pixel, else the nearest on its left.
    index = np.where(filled, cols, W)
    from_right = np.minimum.accumulate(index[:, ::-1], axis=1)[:, ::-1]
    index_left = np.where(filled, cols, -1)
    from_left = np.maximum.accumulate(index_left, axis=1)
    source = np.where(from_right < W, from_right, from_left)
    has = source >= 0
    out = np.where(has, right[rows, np.clip(source, 0, W - 1)], left)
    return out.astype(left.dtype)
