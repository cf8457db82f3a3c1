"""From reconstructed 3D curve points to tool waypoints (step 4): smoothing along
the curve, even resampling, orientation (x along the tangent, z into the surface), and
surface normals from a depth image.

Points arrive ordered along the curve (by the view-1 chain point they came from).
"""

from __future__ import annotations

from typing import cast

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

BoolArray = npt.NDArray[np.bool_]


def _as_points(points: npt.ArrayLike) -> FloatArray:
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInput(
            f'points: expected shape (N, 3), got {points.shape}', key='points', value=points.shape
        )
    return points


def arc_length(points: npt.ArrayLike, closed: bool) -> tuple[FloatArray, float]:
    """Cumulative arc length (N,) [m] of an ordered polyline, and its total length (with
    the closing segment if ``closed``)."""
    points = _as_points(points)
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(steps)])
    total = s[-1] + (np.linalg.norm(points[0] - points[-1]) if closed else 0.0)
    return s, total


END_POINTS_LEFT_OUT = 3  # at each open end, judged by the fit without them
JUMP_FACTOR = 3.0  # a step this many times its neighbours' median is a jump along the curve


def robust_arc_parameter(
    points: npt.ArrayLike, closed: bool, median_steps: int = 9
) -> tuple[FloatArray, float]:
    """Arc length (N,) [m] along ordered points that a lone outlier does not stretch, and
    the period [m] (the length around the loop if ``closed``, else the total).

    Each step from point i to i + 1 counts as the shortest of |p(i+1) - p(i)|,
    |p(i+1) - p(i-1)| and |p(i+2) - p(i)|: a lone point off the curve makes both its
    steps long but the chord over it short, while a true jump along the curve (a stretch
    that view 1 sees end-on, so that one chain step covers millimetres) stays long in all
    three. The steps then count at the running median over ``median_steps`` of them
    (the points' scatter across the curve would make the parameter jitter and bias the
    smoothing), except where one is over ``JUMP_FACTOR`` times that median: a true jump, kept
    (not at an open curve's ends, where nothing beyond confirms it).
    Steps are at least 1 % of the median step, so the parameter increases."""
    points = _as_points(points)
    n = len(points)
    if n < 3:
        t, total = arc_length(points, closed)
        return t, max(total, 1e-12)
    index = np.arange(n)
    if closed:
        nxt, after, before = (index + 1) % n, (index + 2) % n, (index - 1) % n
        count = n
    else:
        nxt, after, before = (
            index[1:],
            np.minimum(index[1:] + 1, n - 1),
            np.maximum(index[:-1] - 1, 0),
        )
        count = n - 1
    start = index[:count]
    step = np.minimum.reduce(
        [
            np.linalg.norm(points[nxt[:count]] - points[start], axis=1),
            np.linalg.norm(points[nxt[:count]] - points[before[:count]], axis=1),
            np.linalg.norm(points[after[:count]] - points[start], axis=1),
        ]
    )
    half = min(median_steps // 2, (count - 1) // 2)
    window = np.arange(-half, half + 1)
    around = start[:, None] + window[None, :]
    around = around % count if closed else np.clip(around, 0, count - 1)
    local = np.median(step[around], axis=1)
    jump = step > JUMP_FACTOR * local
    if not closed:  # a jump to an end point has no point beyond to confirm it
        jump[[0, -1]] = False
    step = np.where(jump, step, local)
    step = np.maximum(step, 0.01 * max(float(np.median(step)), 1e-12))
    t = np.concatenate([[0.0], np.cumsum(step[: n - 1])])
    return t, float(np.sum(step))


def open_at_largest_gap(
    points: npt.ArrayLike, closed: bool, max_gap_m: float, parameter: npt.ArrayLike | None = None
) -> tuple[FloatArray, bool, FloatArray]:
    """A closed sequence with a gap wider than ``max_gap_m`` [m] cannot be trusted as a
    loop: roll it to start after its widest gap and open it. Returns (points, closed,
    parameter) with ``parameter`` (N,) (default: the index) rolled alike and made
    increasing."""
    points = _as_points(points)
    parameter = (
        np.arange(len(points), dtype=float)
        if parameter is None
        else np.asarray(parameter, dtype=float)
    )
    if not closed or len(points) < 3:
        return points, closed, parameter
    gaps = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    widest = int(np.argmax(gaps))
    if gaps[widest] <= max_gap_m:
        return points, True, parameter
    period = parameter[-1] - parameter[0] + 1.0
    rolled = np.roll(parameter, -(widest + 1))
    rolled[rolled < rolled[0]] += period
    return np.roll(points, -(widest + 1), axis=0), False, rolled


def stranded_runs(
    points: npt.ArrayLike, closed: bool, max_gap_m: float, min_points: int = 5
) -> BoolArray:
    """Mask (N,) of the points in runs of fewer than ``min_points`` cut off on both sides
    by steps longer than ``max_gap_m`` [m] (around the loop if ``closed``): a few points
    on their own are no evidence of the curve (a wrong root the outlier test could not
    judge, its neighbours gone), and kept they open a loop or split a curve at their
    two jumps. Nothing is stranded when all points form one run."""
    points = _as_points(points)
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    if closed:
        steps = np.append(steps, np.linalg.norm(points[0] - points[-1]))
    cuts = np.nonzero(steps > max_gap_m)[0] + 1  # a run starts at each cut
    stranded = np.zeros(len(points), dtype=bool)
    if len(cuts) < 2:
        return stranded  # one run (a closed loop with one gap is one run too)
    starts = cuts % len(points) if closed else np.concatenate([[0], cuts])
    ends = np.roll(starts, -1) if closed else np.append(cuts, len(points))
    for start, end in zip(starts, ends):
        run = np.arange(start, end if end > start else end + len(points)) % len(points)
        if len(run) < min_points:
            stranded[run] = True
    if stranded.all():
        return np.zeros(len(points), dtype=bool)  # all runs short: leave the judgement
    return stranded


def without_reversals(points: npt.ArrayLike, closed: bool) -> FloatArray:
    """The ordered points without those where the path turns back (the steps before and
    after point i point more than 90 degrees apart): a local fit in a sparse stretch of
    the curve can overshoot and return, and resampled through, that hairpin gives two
    waypoints far closer than the spacing. Returns (K, 3)."""
    points = _as_points(points)
    while len(points) > 3:
        loop = np.vstack([points[-1:], points, points[:1]]) if closed else points
        steps = np.diff(loop, axis=0)
        turns = np.sum(steps[1:] * steps[:-1], axis=1)  # at points 1..n-2 (open)
        backwards = np.flatnonzero(turns < 0)
        if not len(backwards):
            break
        points = np.delete(points, backwards[0] + (0 if closed else 1), axis=0)
    return points


def split_at_gaps(points: npt.ArrayLike, max_gap_m: float) -> list[npt.NDArray[np.intp]]:
    """Index arrays of the runs of an ordered open sequence between steps longer than
    ``max_gap_m`` [m]."""
    points = _as_points(points)
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cuts = np.nonzero(steps > max_gap_m)[0] + 1
    return np.split(np.arange(len(points)), cuts)


def smooth_along_curve(
    points: npt.ArrayLike,
    closed: bool,
    window_m: float,
    parameter: npt.ArrayLike | None = None,
    period: float | None = None,
    reject_sigma: float = 4.0,
    passes: int = 2,
) -> tuple[FloatArray, BoolArray]:
    """Local quadratic regression of each coordinate against a curve parameter (tricube
    weights over a window of about ``window_m`` [m]); points whose residual exceeds
    ``reject_sigma`` robust standard deviations (and 0.5 mm) are dropped between passes.

    Args:
        parameter: (N,) increasing curve parameter, e.g. the view-1 chain index the points
            came from (noise-free, unlike the noisy points' own arc length); default: the
            points' arc length.
        period: the parameter's period for a closed curve (default: its total range).

    Returns (smoothed points (K, 3), kept mask (N,)).
    """
    points = _as_points(points)
    if parameter is None:
        parameter, total = arc_length(points, closed)
        period = total if period is None else period
    parameter = np.asarray(parameter, dtype=float)
    if closed and period is None:
        step = np.median(np.diff(parameter)) if len(parameter) > 1 else 1.0
        period = parameter[-1] - parameter[0] + step
    period_if_closed = period if closed else None  # never None for a closed curve here
    kept = np.ones(len(points), dtype=bool)
    smoothed = points.copy()
    for p in range(passes):
        current, t = points[kept], parameter[kept]
        if len(current) < 5:
            return current, kept
        # window in parameter units: window_m over the mean length per parameter unit
        _, length = arc_length(current, closed)
        span = t[-1] - t[0] if period_if_closed is None else period_if_closed
        half = 0.5 * float(window_m) * span / max(length, 1e-12)
        fitted = _local_quadratic(current, t, half, period_if_closed)
        smoothed = fitted
        if p == passes - 1:
            break
        if not closed:
            # an open curve's end points are judged by their neighbours' fit without
            # them: with no points beyond, their own fit follows them (a last point 1.7
            # mm off kept a 0.29 mm residual)
            ends = np.zeros(len(current), dtype=bool)
            ends[:END_POINTS_LEFT_OUT] = ends[-END_POINTS_LEFT_OUT:] = True
            fitted = _local_quadratic(current, t, half, None, leave_out=ends)
        residual = np.linalg.norm(current - fitted, axis=1)
        mad = 1.4826 * np.median(residual)
        outlier = residual > max(reject_sigma * mad, 5e-4)
        if not outlier.any():
            break
        index = np.nonzero(kept)[0]
        kept[index[outlier]] = False
    return smoothed, kept


def _local_quadratic(
    values: FloatArray,
    t: FloatArray,
    half: float,
    period: float | None,
    leave_out: npt.NDArray[np.bool_] | None = None,
) -> FloatArray:
    """Value at each t of the tricube-weighted quadratic fit of ``values`` (N, C) over
    |dt| < ``half``; ``period`` for a periodic parameter (else None); where ``leave_out``
    (N,) is set, the fit without the point itself. Points are sorted by t, so each window
    is a band of neighbours: all fits at once from weighted moments."""
    n = len(t)
    # the band: the most neighbours any point has within half on either side (half over
    # the smallest step overshoots it many times where the steps vary, as arc lengths do)
    extended = np.concatenate([t - period, t, t + period]) if period is not None else t
    position = (n if period is not None else 0) + np.arange(n)
    reach = np.maximum(
        np.searchsorted(extended, t + half, side='right') - 1 - position,
        position - np.searchsorted(extended, t - half, side='left'),
    )
    k = int(min(n // 2, max(int(reach.max()), 1)))
    offsets = np.arange(-k, k + 1)
    index = np.arange(n)[:, None] + offsets[None, :]
    if period is not None:
        wrapped = index % n
        dt = t[wrapped] - t[:, None]
        dt = (dt + 0.5 * period) % period - 0.5 * period
        valid = np.ones_like(dt, dtype=bool)
        index = wrapped
    else:
        valid = (index >= 0) & (index < n)
        index = np.clip(index, 0, n - 1)
        dt = t[index] - t[:, None]
    w = np.where(valid, np.clip(1 - (np.abs(dt) / half) ** 3, 0.0, None) ** 3, 0.0)
    if leave_out is not None:
        w[leave_out, k] = 0.0
    weighted_powers = [w]  # w dt^p, p = 0..4, by repeated products
    for _ in range(4):
        weighted_powers.append(weighted_powers[-1] * dt)
    moments = np.stack([wp.sum(axis=1) for wp in weighted_powers], axis=1)  # (N, 5)
    normal = np.stack([moments[:, r : r + 3] for r in range(3)], axis=1)
    normal += 1e-12 * np.trace(normal, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    # only the fit's value at dt = 0 is wanted, e0^T normal^-1 rhs: by Cramer's rule the
    # first row of the inverse is (column 1 x column 2) / det, so each neighbour's weight
    # in it is that row applied to its (w, w dt, w dt^2)
    first_row = np.cross(normal[:, :, 1], normal[:, :, 2])
    determinant = np.sum(normal[:, :, 0] * first_row, axis=1)
    # (the cast: a sum of arrays is an array; its start, 0, only adds to them)
    weight = cast(FloatArray, sum(first_row[:, p, None] * weighted_powers[p] for p in range(3)))
    with np.errstate(divide='ignore', invalid='ignore'):
        fitted = (weight[:, None, :] @ values[index])[:, 0, :] / determinant[:, None]
    enough = (w > 0).sum(axis=1) >= 4
    return np.where(enough[:, None], fitted, values)


TANGENT_STEPS = 2


def bridge_gaps(points: npt.ArrayLike, closed: bool, min_gap_m: float) -> FloatArray:
    """The polyline with every step longer than ``min_gap_m`` [m] (around the loop too
    if ``closed``) filled by a cubic Hermite arc: from the point before the hole to the
    one after, leaving and arriving along the curve's own direction there (one-sided
    differences over TANGENT_STEPS steps outside the hole; the chord's direction at an
    open end or next to another hole) with speed the hole's chord. A chord
    would cut a bend: its error grows with the hole's length squared over the radius,
    the arc's with the fourth power. Returns (M, 3), the given points among them."""
    points = _as_points(points)
    n = len(points)
    if n < 6:
        return points
    steps = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    is_hole = steps > min_gap_m  # the step from point k to k + 1
    if not closed:
        is_hole[-1] = False
    holes = np.nonzero(is_hole)[0]
    pieces, start = [], 0
    for i in map(int, holes):
        a, b = points[i], points[(i + 1) % n]
        # the directions just outside the hole; the chord's where that stretch is an
        # open end or crosses another hole (a stray point between two holes)
        before = np.arange(i - TANGENT_STEPS, i)
        after = np.arange(i + 1, i + 1 + TANGENT_STEPS)
        leaving, arriving = b - a, b - a
        if (closed or before[0] >= 0) and not is_hole[before % n].any():
            leaving = a - points[before[0] % n]
        if (closed or after[-1] + 1 < n) and not is_hole[after % n].any():
            arriving = points[(after[-1] + 1) % n] - b
        chord = float(np.linalg.norm(b - a))
        m0 = chord * leaving / max(float(np.linalg.norm(leaving)), 1e-12)
        m1 = chord * arriving / max(float(np.linalg.norm(arriving)), 1e-12)
        t = np.linspace(0.0, 1.0, int(np.ceil(4 * chord / min_gap_m)) + 1)[1:-1, None]
        arc = (
            (2 * t**3 - 3 * t**2 + 1) * a
            + (t**3 - 2 * t**2 + t) * m0
            + (-2 * t**3 + 3 * t**2) * b
            + (t**3 - t**2) * m1
        )
        pieces += [points[start : i + 1], arc]
        start = i + 1
    pieces.append(points[start:])
    return np.vstack(pieces)


def resample(points: npt.ArrayLike, closed: bool, spacing_m: float) -> FloatArray:
    """Evenly spaced points along the polyline: L / round(L / spacing) apart [m], so the
    spacing is within half a step's share of ``spacing_m``; a closed curve's first point
    is not repeated. Returns (M, 3)."""
    points = _as_points(points)
    if spacing_m <= 0:
        raise InvalidInput(
            f'spacing: must be > 0, got {spacing_m}', key='spacing', value=spacing_m
        )
    if closed:
        points = np.vstack([points, points[:1]])
    s, total = arc_length(points, False)
    # at least two waypoints on an open curve and three on a loop (so each has a
    # tangent), however coarse the spacing against the curve's length
    segments = max(3 if closed else 1, int(round(total / spacing_m)))
    targets = np.linspace(0.0, total, segments + 1)
    if closed:
        targets = targets[:-1]
    return np.column_stack([np.interp(targets, s, points[:, k]) for k in range(3)])


def tangents(points: npt.ArrayLike, closed: bool) -> FloatArray:
    """Unit tangents (N, 3) by central differences (one-sided at open ends). Where the
    difference vanishes (repeated points, a loop of two points) the nearest non-zero
    tangent along the curve is taken; raises InvalidInput if all points coincide."""
    points = _as_points(points)
    if len(points) < 2:
        raise InvalidInput(
            f'tangents: need at least 2 points, got {len(points)}', key='points', value=len(points)
        )
    if closed:
        t = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    else:
        t = np.gradient(points, axis=0)
    norm = np.linalg.norm(t, axis=1)
    scale = max(float(np.ptp(points, axis=0).max()), 1e-300)
    zero = ~(norm > 1e-9 * scale)
    if zero.all():
        raise InvalidInput('tangents: all points coincide', key='points', value=points[0].tolist())
    if zero.any():
        nonzero = np.nonzero(~zero)[0]
        nearest = nonzero[np.abs(np.arange(len(t))[:, None] - nonzero[None]).argmin(axis=1)]
        t, norm = t[nearest], norm[nearest]
    return t / norm[:, None]


def waypoint_frames(
    points: npt.ArrayLike, closed: bool, approach_base: npt.ArrayLike | None = None
) -> FloatArray:
    """Poses (N, 4, 4) in base: origin at the point, x along the tangent, z the approach
    direction made orthogonal to x, y = z x x.

    Args:
        approach_base: (N, 3) desired approach directions (into the surface), NaN rows or
            None for the default, the base's -z.
    """
    points = _as_points(points)
    x = tangents(points, closed)
    z = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    if approach_base is not None:
        approach_base = np.asarray(approach_base, dtype=float)
        known = np.all(np.isfinite(approach_base), axis=1)
        z[known] = approach_base[known]
    z = z - np.sum(z * x, axis=1, keepdims=True) * x
    norm = np.linalg.norm(z, axis=1, keepdims=True)
    degenerate = norm[:, 0] < 1e-6  # approach along the tangent: fall back to -z of base
    if degenerate.any():
        fallback = np.array([0.0, 0.0, -1.0]) - x[degenerate, 2:3] * x[degenerate]
        fallback_norm = np.linalg.norm(fallback, axis=1, keepdims=True)
        fallback = np.where(fallback_norm > 1e-6, fallback, np.cross(x[degenerate], [0, 1, 0]))
        z[degenerate] = fallback
        norm = np.linalg.norm(z, axis=1, keepdims=True)
    z /= norm
    y = np.cross(z, x)
    T = np.tile(np.eye(4), (len(points), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, y, z, points
    return T


def depth_points_rect(depth_m: npt.ArrayLike, K_rect: npt.ArrayLike) -> FloatArray:
    """Back-project a depth image (H, W) [m, z along the rectified optical axis; NaN where
    unknown] with the rectified intrinsics K (3, 3): (H, W, 3) points in the rectified
    frame [m]."""
    depth_m = np.asarray(depth_m, dtype=float)
    if depth_m.ndim != 2:
        raise InvalidInput(
            f'depth: expected (H, W), got {depth_m.shape}', key='depth', value=depth_m.shape
        )
    K = np.asarray(K_rect, dtype=float)
    v, u = np.mgrid[0 : depth_m.shape[0], 0 : depth_m.shape[1]]
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x * depth_m, y * depth_m, depth_m], axis=2)


DEPTH_RANGE_M = (1e-3, 100.0)  # [m] depths outside are not a surface seen by a camera


def usable_depth(
    depth_m: npt.ArrayLike, depth_range: tuple[float, float] = DEPTH_RANGE_M
) -> tuple[FloatArray, dict[str, int]]:
    """The depth image (H, W) with every value that cannot be a seen surface set to NaN
    (NaN stays unknown, REP 118), and the counts of what was removed: {'not_positive':
    zero or negative, 'too_far': beyond ``depth_range[1]`` [m] or infinite, 'too_near':
    positive but nearer than ``depth_range[0]``}."""
    depth_m = np.array(depth_m, dtype=float)
    with np.errstate(invalid='ignore'):
        not_positive = depth_m <= 0
        too_far = depth_m > depth_range[1]
        too_near = (depth_m > 0) & (depth_m < depth_range[0])
    depth_m[not_positive | too_far | too_near] = np.nan
    return depth_m, {
        'not_positive': int(not_positive.sum()),
        'too_far': int(too_far.sum()),
        'too_near': int(too_near.sum()),
    }


def check_depth_intrinsics(K_rect: npt.ArrayLike, width: int, height: int) -> None:
    """InvalidInput unless K (3, 3) is a plausible pinhole matrix for a ``width`` x
    ``height`` image: finite, positive focal lengths under 1e6 px, the principal point
    within an image size of the image, zero bottom row but K[2, 2] = 1."""
    K = np.asarray(K_rect, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InvalidInput('depth intrinsics: K must be a finite 3x3 matrix', key='K')
    limit = 1e6  # [px] no lens has a focal length of a million pixels
    if not (0 < K[0, 0] < limit and 0 < K[1, 1] < limit):
        raise InvalidInput(
            f'depth intrinsics: focal lengths {K[0, 0]:g}, {K[1, 1]:g} px '
            f'must be in (0, {limit:g})',
            key='K',
            value=K.tolist(),
        )
    if not (
        abs(K[0, 1]) < limit
        and -width <= K[0, 2] <= 2 * width
        and -height <= K[1, 2] <= 2 * height
    ):
        raise InvalidInput(
            f'depth intrinsics: principal point ({K[0, 2]:g}, {K[1, 2]:g}) '
            f'or skew {K[0, 1]:g} implausible for {width}x{height}',
            key='K',
            value=K.tolist(),
        )
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise InvalidInput(
            'depth intrinsics: K must be upper triangular with K[2, 2] = 1',
            key='K',
            value=K.tolist(),
        )


def normals_from_depth(
    points_base: npt.ArrayLike,
    depth_m: npt.ArrayLike,
    K_rect: npt.ArrayLike,
    T_base_rect: npt.ArrayLike,
    window_px: int = 9,
    min_valid: int = 12,
    max_depth_mismatch: float = 0.1,
) -> FloatArray:
    """Surface normals (N, 3) in base at ``points_base`` from a depth image.

    Each point is projected into the rectified frame (pose ``T_base_rect`` (4, 4), the
    rectified left optical frame in base), and a plane is fitted by SVD to the depth
    image's 3D points in the ``window_px`` x ``window_px`` window around it. The normal is
    oriented toward the camera (out of the surface). Rows are NaN where the point is
    outside the image, fewer than ``min_valid`` depths are usable (see ``usable_depth``),
    or the depth there disagrees with the point's own depth by more than
    ``max_depth_mismatch`` of it (plus 1 cm): that depth shows some other surface.
    Raises InvalidInput for implausible intrinsics (``check_depth_intrinsics``).
    """
    points_base = _as_points(points_base)
    depth_m = np.asarray(depth_m, dtype=float)
    if depth_m.ndim != 2:
        raise InvalidInput(
            f'depth: expected (H, W), got {depth_m.shape}', key='depth', value=depth_m.shape
        )
    H, W = depth_m.shape
    check_depth_intrinsics(K_rect, W, H)
    depth_m, _ = usable_depth(depth_m)
    cloud = depth_points_rect(depth_m, K_rect)
    T = np.asarray(T_base_rect, dtype=float)
    R_base_rect, centre_base = T[:3, :3], T[:3, 3]
    p_rect = (points_base - centre_base) @ R_base_rect
    K = np.asarray(K_rect, dtype=float)
    normals = np.full((len(points_base), 3), np.nan)
    half = int(window_px) // 2
    for i, p in enumerate(p_rect):
        if not p[2] > 0:
            continue
        u = K[0, 0] * p[0] / p[2] + K[0, 1] * p[1] / p[2] + K[0, 2]
        v = K[1, 1] * p[1] / p[2] + K[1, 2]
        if not (half <= u < W - half - 0.5 and half <= v < H - half - 0.5):
            continue  # also false for NaN
        ui, vi = int(round(u)), int(round(v))
        patch = cloud[vi - half : vi + half + 1, ui - half : ui + half + 1].reshape(-1, 3)
        patch = patch[np.all(np.isfinite(patch), axis=1)]
        if len(patch) < min_valid:
            continue
        if abs(np.median(patch[:, 2]) - p[2]) > max_depth_mismatch * p[2] + 0.01:
            continue
        centred = patch - patch.mean(axis=0)
        n = np.linalg.svd(centred, full_matrices=False)[2][-1]
        if n @ p > 0:  # point from the camera toward the surface: flip to face the camera
            n = -n
        normals[i] = R_base_rect @ n
    return normals
