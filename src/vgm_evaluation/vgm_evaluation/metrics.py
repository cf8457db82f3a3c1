"""Measures of an estimate against its ground truth, written once for the tests, the
benches and the demo."""

from __future__ import annotations

from collections.abc import Sequence
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


class CurveAgreement(NamedTuple):
    """Points reconstructed along a curve against the true curve, all in [m]: each point's
    distance to the true curve and their RMS and max; the other direction as both the
    share of the true curve's length within the coverage radius of the points' polyline
    and the largest distance of a true-curve point to that polyline (Hausdorff)."""

    distance_m: npt.NDArray[np.float64]  # (N,) each point to the nearest true segment
    rms_m: float  # NaN without points
    max_m: float  # NaN without points
    coverage: float  # share of the true length within the radius; 0 without 2 points
    farthest_uncovered_m: float  # inf without 2 points


def _distance_to_segments(
    points: npt.NDArray[np.float64],
    starts: npt.NDArray[np.float64],
    ends: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """Distance (N,) of each point (N, 3) to the nearest of the segments (S, 3)-(S, 3)."""
    best = np.full(len(points), np.inf)
    if len(starts) == 0:
        return best
    along = ends - starts
    length2 = np.maximum(np.einsum('sk,sk->s', along, along), 1e-300)  # zero-length: a point
    rows = max(1, 2**21 // len(starts))  # bounded memory: about 2M point-segment pairs a chunk
    for first in range(0, len(points), rows):
        to_point = points[first : first + rows, None, :] - starts
        t = np.clip(np.einsum('nsk,sk->ns', to_point, along) / length2, 0.0, 1.0)
        offset = to_point - t[..., None] * along
        best[first : first + rows] = np.sqrt(np.einsum('nsk,nsk->ns', offset, offset).min(axis=1))
    return best


def _segments(
    polylines: Sequence[npt.NDArray[np.float64]],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    starts = [p[:-1] if len(p) > 1 else p for p in polylines]
    ends = [p[1:] if len(p) > 1 else p for p in polylines]  # a lone point: a zero segment
    return np.concatenate(starts), np.concatenate(ends)


def distance_to_polylines(
    points: npt.ArrayLike, polylines: Sequence[npt.NDArray[np.float64]]
) -> npt.NDArray[np.float64]:
    """Distance (N,) [m] of each point (N, 3) to the nearest segment of the polylines
    (each (K, 3) [m], not joined to each other)."""
    return _distance_to_segments(
        np.atleast_2d(np.asarray(points, dtype=float)), *_segments(polylines)
    )


def _closed(polyline: npt.NDArray[np.float64], closed: bool) -> npt.NDArray[np.float64]:
    return np.vstack([polyline, polyline[:1]]) if closed and len(polyline) > 2 else polyline


def curve_agreement(
    points: npt.ArrayLike,
    truth: npt.NDArray[np.float64] | Sequence[npt.NDArray[np.float64]],
    closed: bool = False,
    truth_closed: bool = False,
    coverage_radius_m: float = 3e-3,
    truth_step_m: float = 1e-4,
) -> CurveAgreement:
    """How well ``points`` (N, 3) [m], in order along a polyline (``closed``: back to the
    first), follow the true curve ``truth``: one polyline (M, 3) [m] or a list of them
    (pieces not joined), ``truth_closed`` closing each. Distances are exact to the
    segments. The coverage is measured at points every ``truth_step_m`` along the truth.

    Raises:
        ValueError: a point array or a truth polyline not of shape (K, 3).
    """
    pts = np.asarray(points, dtype=float)
    pts = pts.reshape(0, 3) if pts.size == 0 else pts
    pieces = [truth] if isinstance(truth, np.ndarray) and truth.ndim == 2 else list(truth)
    truth_polylines = [_closed(np.asarray(p, dtype=float), truth_closed) for p in pieces]
    for array in (pts, *truth_polylines):
        if array.ndim != 2 or array.shape[1] != 3:
            raise ValueError(f'expected points of shape (K, 3), got {array.shape}')
    distance = _distance_to_segments(pts, *_segments(truth_polylines))
    if len(pts) == 0:
        return CurveAgreement(distance, float('nan'), float('nan'), 0.0, float('inf'))
    rms, worst = float(np.sqrt(np.mean(distance**2))), float(distance.max())
    if len(pts) < 2:
        return CurveAgreement(distance, rms, worst, 0.0, float('inf'))
    truth_samples = np.vstack([_resampled(p, truth_step_m) for p in truth_polylines])
    uncovered = _distance_to_segments(truth_samples, *_segments([_closed(pts, closed)]))
    return CurveAgreement(
        distance,
        rms,
        worst,
        float(np.mean(uncovered <= coverage_radius_m)),
        float(uncovered.max()),
    )


def _resampled(polyline: npt.NDArray[np.float64], step_m: float) -> npt.NDArray[np.float64]:
    """Points at most ``step_m`` apart along the polyline, its vertices among them."""
    if len(polyline) < 2:
        return polyline
    along = np.diff(polyline, axis=0)
    counts = np.maximum(np.ceil(np.linalg.norm(along, axis=1) / step_m).astype(int), 1)
    segment = np.repeat(np.arange(len(along)), counts)
    fraction = (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)) / counts[
        segment
    ]
    return np.vstack([polyline[segment] + fraction[:, None] * along[segment], polyline[-1:]])
