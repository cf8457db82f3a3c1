"""Measures of an estimate against its ground truth, written once for the tests, the
benches and the demo."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt


class DisparityAgreement(NamedTuple):
    """A decoded or estimated disparity against the true one, over the pixels known in
    both (NaN unknown): Pearson correlation, RMS [px] and the share more than 2 px off."""

    correlation: float  # 0 when nothing was decoded or fewer than 2 pixels are shared
    rms_px: float  # NaN when no pixel is shared
    beyond_2px: float  # NaN when no pixel is shared


def disparity_agreement(
    estimate: npt.ArrayLike | None, truth: npt.ArrayLike
) -> DisparityAgreement:
    """How well ``estimate`` (None: nothing decoded) matches ``truth``, both (H, W) [px]."""
    if estimate is None:
        return DisparityAgreement(0.0, float('nan'), float('nan'))
    a, b = np.asarray(estimate, float), np.asarray(truth, float)
    both = np.isfinite(a) & np.isfinite(b)
    if not both.any():
        return DisparityAgreement(0.0, float('nan'), float('nan'))
    error = a[both] - b[both]
    correlation = float(np.corrcoef(a[both], b[both])[0, 1]) if both.sum() >= 2 else 0.0
    return DisparityAgreement(
        correlation, float(np.sqrt(np.mean(error**2))), float(np.mean(np.abs(error) > 2.0))
    )
