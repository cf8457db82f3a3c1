"""One capture to one curve: extraction in each view, piecewise fits, cone intersection,
third-view selection, refinement, smoothing and resampling. Plain numpy, no ROS: the node
converts messages and calls ``reconstruct_capture``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from curve_recon_node.curve_extraction import extract_chains
from curve_recon_node.piecewise import (
    CandidateInfo,
    PiecewiseCurve,
    View,
    reconstruct_ray_roots,
    refine_points,
)
from curve_recon_node.thesis import reconstruct_cone_lsq
from curve_recon_node.waypoints import (
    arc_length,
    bridge_gaps,
    open_at_largest_gap,
    resample,
    robust_arc_parameter,
    smooth_along_curve,
    split_at_gaps,
    stranded_runs,
    tangents,
    without_reversals,
)
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.settings import setting

METHODS = ('ray_roots', 'cone_lsq')
REFINED_RESIDUAL_PX = 1.0  # [px] a refined point must come this near every view's curve
END_ON_GAP_SPACINGS = 2.0  # a step of more waypoint spacings between samples' points is a hole
END_ON_ARC_CHORD = 2.0  # a hole's stretch of view 2's chain is at most this x its chord
STRANDED_FRACTION = 0.02  # a run between two gaps with fewer of the points is dropped


class NoCurve(InvalidInput):
    """The capture holds no usable curve (none seen, seen in too few views, or its views
    do not agree)."""


@dataclass(frozen=True)
class ReconstructionSettings:
    """What shapes a reconstruction: the one source of curve_recon_node's parameters of
    these names (min_fraction, depth_range and seeds are constants, no parameters)."""

    degree: int = setting(
        2,
        'Degree n of the implicit image curves (2 conics incl. ellipses, parabolas, line '
        'pairs; 3 cubics; any n >= 1).',
        range=(1, 6),
    )
    method: str = setting(
        'ray_roots',
        'Cone intersection: ray_roots (ours: exact real roots of the view-2 cone along each '
        'view-1 ray) or cone_lsq (the thesis: minimise S1^2 + S2^2 from seeds).',
        choices=METHODS,
    )
    third_view_tolerance: float = setting(
        2.0,
        "Largest Sampson distance of a candidate's projection to the third view's fitted "
        'curve, in pixels of the third view.',
        unit='px',
        range=(1e-3, 100.0),
    )
    spacing: float = setting(
        0.005, 'Waypoint spacing along the curve.', unit='m', range=(1e-4, 1.0)
    )
    line_width_px: float = setting(
        3.0,
        "Width of the drawn line (sets the ridge detector's scale and the end trim).",
        unit='px',
        range=(1.0, 30.0),
    )
    min_contrast: float = setting(
        8.0,
        'Faintest line taken as the curve (darker than its surroundings by this).',
        unit='grey levels',
        range=(0.5, 255.0),
    )
    min_curve_pixels: float = setting(
        60.0, 'Shortest image chain taken as the curve.', unit='px', range=(5.0, 1e5)
    )
    fit_tolerance_px: float = setting(
        0.1,
        'A chain whose degree-n fit has a larger RMS Sampson residual is split into '
        'overlapping pieces.',
        unit='px',
        range=(1e-3, 100.0),
    )
    min_piece_points: int = setting(
        30, 'Pieces are not split below 2x this many chain points.', range=(8, 100000)
    )
    refine: bool = setting(
        True, "Move each point to minimise its pixel distances to all views' curves."
    )
    smoothing_window: float = setting(
        0.02,
        'Local-quadratic smoothing window along the curve before resampling.',
        unit='m',
        range=(0.0, 1.0),
    )
    min_fraction: float = 0.5  # of view-1 samples that must be reconstructed
    depth_range: tuple[float, float] = (0.005, 5.0)  # [m] where the curve may be (view-1 depth)
    seeds: int = 12  # cone_lsq seeds per view-1 ray, log-spaced over depth_range


@dataclass
class Reconstruction:
    """Result: ``waypoints_base`` (M, 3) evenly spaced along the curve, ``closed``,
    ``points_base`` (K, 3) the points that passed the third-view test and the smoothing's
    outlier test (refined, not smoothed), in curve order, and ``stats`` for diagnostics."""

    waypoints_base: np.ndarray
    closed: bool
    points_base: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)  # diagnostic values of mixed types


class StageClock:
    """Wall time [ms] spent in each named stage of a reconstruction (summed over calls)."""

    def __init__(self) -> None:
        self.stage_ms: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        """Charge the time since the previous lap (or the start) to ``stage``."""
        now = time.perf_counter()
        self.stage_ms[stage] = self.stage_ms.get(stage, 0.0) + 1e3 * (now - self._last)
        self._last = now


def view_curve(
    image: npt.ArrayLike,
    camera: PinholeCamera,
    settings: ReconstructionSettings,
    clock: StageClock | None = None,
) -> tuple[View | None, int]:
    """The longest curve chain of one image as a ``View`` (undistorted with the camera),
    or None if there is none. ``clock`` (a ``StageClock``) gets the stages' times."""
    clock = StageClock() if clock is None else clock
    chains = extract_chains(
        image, settings.line_width_px, settings.min_contrast, settings.min_curve_pixels
    )
    clock.lap('extraction')
    if not chains:
        return None, 0
    chain = chains[0]
    xy = camera.undistort_pixels(chain.pixels)
    focal = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
    clock.lap('undistortion')
    curve = PiecewiseCurve(
        xy,
        chain.closed,
        settings.degree,
        focal,
        settings.fit_tolerance_px,
        settings.min_piece_points,
        measured=chain.measured,
    )
    clock.lap('piecewise fits')
    return View(curve, camera), len(chains)


def _second_pair(
    views: Sequence[View],
    points: FloatArray,
    info: CandidateInfo,
    tol3_px: float,
    settings: ReconstructionSettings,
) -> tuple[FloatArray, CandidateInfo]:
    """Samples that views 1 and 2 left unreconstructed (where the curve runs along
    their epipolar lines the two cones meet at a grazing angle, so the root is off and
    view 3 rejects it) get a second chance from views 1 and 3, checked by view 2: with
    the oblique third camera that pair is well conditioned there. Returns the merged
    (points, info), in view-1 order; the counts of the first pass stay as they were
    and ``n_second_pair`` counts the samples recovered."""
    missing = np.setdiff1d(np.nonzero(views[0].curve.measured)[0], info['sample_index'])
    if len(missing) < 3:
        return points, info
    # view 2 is the checker here, and view 3's piece the cone: a root on that piece's
    # continuation, 2-2.6 px off view 3's chain, met view 2's curve 0.01 px closer than
    # the true root of the same ray and won (sphere_loop seed 1 at noise 2: three such
    # points 4.4-5.8 mm off, smoothed into a 4.5 mm excursion); those rank last now.
    # (In the first pass the same ranking by view 2's chain moved picks where view 2's
    # chain is pixels off near a knot's crossings: torus_knot seed 3 at noise 4, max
    # 5.9 -> 6.7 mm; self_approaching seed 3 at noise 4, 1.50 -> 1.83 mm.)
    more, more_info = reconstruct_ray_roots(
        views[0],
        views[2],
        views[1],
        samples=missing,
        tol3_px=tol3_px,
        max_depth=settings.depth_range[1],
        off_chain_last=True,
    )
    if not len(more):
        return points, info
    points, merged = _merge(points, info, more, more_info, more_info['sample_index'])
    merged['n_candidates'] = info['n_candidates'] + more_info['n_candidates']
    merged['n_second_pair'] = len(more)
    return points, merged


def _merge(
    points: FloatArray,
    info: CandidateInfo,
    more: FloatArray,
    more_info: CandidateInfo,
    more_index: np.ndarray,
) -> tuple[FloatArray, CandidateInfo]:
    """``points`` and ``more`` (at view-1 sample positions ``more_index``) in view-1 order,
    with their third-view distances and out-of-order counts."""
    index = np.concatenate([info['sample_index'], more_index])
    order = np.argsort(index, kind='stable')
    merged: CandidateInfo = {
        **info,
        'sample_index': index[order],
        'third_view_px': np.concatenate([info['third_view_px'], more_info['third_view_px']])[
            order
        ],
        'n_out_of_order': info['n_out_of_order'] + more_info['n_out_of_order'],
    }
    return np.vstack([points, more])[order], merged


def _end_on_holes(points: FloatArray, closed: bool, spacing: float) -> list[tuple[int, int]]:
    """The holes (i, j) between points i and j (j may be len(points): the first point of
    a loop) that ``_fill_end_on_stretches`` fills: a step longer than
    END_ON_GAP_SPACINGS spacings (j = i + 1), or a run of such steps whose two outer
    points are that far apart too (view 1 sees the stretch end-on and its samples there
    land at either end of it, out of order: twisted_cubic seed 3 at noise 4). A run whose
    outer points are near each other goes out to a lone wrong root and back: no hole."""
    ends = np.vstack([points, points[:1]]) if closed else points
    steps = np.linalg.norm(np.diff(ends, axis=0), axis=1)
    long_step = steps > END_ON_GAP_SPACINGS * spacing
    holes = []
    k = 0
    while k < len(long_step):
        if not long_step[k]:
            k += 1
            continue
        m = k
        while m + 1 < len(long_step) and long_step[m + 1]:
            m += 1
        wraps = closed and long_step[0] and long_step[-1] and (k == 0 or m == len(long_step) - 1)
        if not wraps and (
            m == k or np.linalg.norm(ends[m + 1] - ends[k]) > END_ON_GAP_SPACINGS * spacing
        ):
            holes.append((k, m + 1))
        k = m + 1
    return holes


def _fill_end_on_stretches(
    views: Sequence[View],
    points: FloatArray,
    info: CandidateInfo,
    tol3_px: float,
    settings: ReconstructionSettings,
) -> tuple[FloatArray, CandidateInfo]:
    """Where view 1 sees a stretch of the curve end-on, one step along its chain covers
    millimetres of curve (a helix: 40 mm in 4 samples), and the hole between the two
    samples' points was bridged or cut. Views 2 and 3 see that stretch: the view-2 chain
    points between the projections of the hole's two ends are intersected with view 3's
    cone, checked by view 1, and the points inserted between the ends in view-2 chain
    order (``_end_on_holes``; points of view 1's samples inside a hole, out of order at
    its ends, are replaced). ``sample_index`` becomes fractional there (between the
    ends' indices); ``n_end_on`` counts the points added."""
    index = info['sample_index'].astype(float)
    closed = views[0].curve.closed
    holes = _end_on_holes(points, closed, settings.spacing)
    if not holes:
        return points, info
    ends = np.vstack([points, points[:1]]) if closed else points
    curve2 = views[1].curve
    n2 = len(curve2.xy)
    chain2 = views[1].chain_index(ends)
    samples2: list[np.ndarray] = []
    positions: list[np.ndarray] = []
    replaced: list[int] = []
    for hole, after in holes:
        first, last = chain2[hole], chain2[after]
        if first < 0 or last < 0:
            continue
        step = last - first
        if curve2.closed and abs(step) > n2 / 2:
            step -= int(np.sign(step)) * n2
        # chain points are about a pixel apart: a stretch much longer along view 2's
        # chain than straight across is no hole in one curve but a jump between two
        # stretches (an end is a wrong root): left to the outlier tests
        chord_px = curve2.focal_px * np.linalg.norm(curve2.xy[last] - curve2.xy[first])
        if abs(step) > END_ON_ARC_CHORD * chord_px + END_ON_ARC_CHORD:
            continue
        inside = np.arange(hole + 1, after)
        # the points inside must project onto that stretch of view 2's chain
        offset = chain2[inside] - first
        if curve2.closed:
            offset = (offset + n2 // 2) % n2 - n2 // 2
        if np.any(
            (chain2[inside] < 0) | (offset * np.sign(step) < 0) | (np.abs(offset) > abs(step))
        ):
            continue
        between = first + np.sign(step) * np.arange(1, abs(step))
        between = between % n2 if curve2.closed else between
        measured = curve2.measured[between]
        if not measured.any():
            continue
        samples2.append(between[measured])
        replaced.extend(inside.tolist())
        start = index[hole]
        stop = index[after] if after < len(index) else index[0] + len(views[0].curve.xy)
        positions.append(start + (stop - start) * (np.arange(1, abs(step)) / abs(step))[measured])
    if not samples2:
        return points, info
    order2 = np.concatenate(samples2)
    more, more_info = reconstruct_ray_roots(
        views[1],
        views[2],
        views[0],
        samples=order2,
        tol3_px=tol3_px,
        max_depth=settings.depth_range[1],
    )
    if not len(more):
        return points, info
    if replaced:
        kept = np.ones(len(points), dtype=bool)
        kept[replaced] = False
        points = points[kept]
        info = {
            **info,
            'sample_index': info['sample_index'][kept],
            'third_view_px': info['third_view_px'][kept],
        }
    position_of = dict(zip(order2.tolist(), np.concatenate(positions).tolist()))
    added = np.array([position_of[int(i)] for i in more_info['sample_index']])
    points, merged = _merge(points, info, more, more_info, added % len(views[0].curve.xy))
    merged['n_end_on'] = len(more)
    return points, merged


def reconstruct_capture(
    images: Mapping[str, npt.ArrayLike],
    cameras: Mapping[str, PinholeCamera],
    settings: ReconstructionSettings,
    names: Sequence[str] = ('left', 'right', 'aux'),
) -> Reconstruction:
    """Reconstruct the curve seen in ``images`` {name: (H, W) grey} by ``cameras`` {name:
    PinholeCamera with pose}; ``names`` are the views used, view 1 first (2 or 3).

    Raises ``NoCurve`` when a view has no curve or too little of it is reconstructed.
    """
    started = time.perf_counter()
    clock = StageClock()
    if settings.method not in METHODS:
        raise InvalidInput(
            f'method: expected one of {METHODS}, got {settings.method!r}',
            key='method',
            value=settings.method,
        )
    views = _curve_views(images, cameras, settings, names, clock)
    points, info = _intersection(views, settings)
    clock.lap(settings.method)
    stats = _intersection_stats(views, info)
    fraction = len(points) / max(info['n_samples'], 1)
    # two views: reconstruct where the intersection is unique and report the rest as
    # ambiguous (stats), so only the three-view case needs most samples to succeed
    if (len(views) > 2 and fraction < settings.min_fraction) or len(points) < 10:
        raise NoCurve(
            f'only {len(points)} of {info["n_samples"]} curve samples were '
            f'reconstructed ({info["n_rejected_view3"]} rejected by the third '
            f'view, {info["n_ambiguous"]} ambiguous): the views do not show one '
            'curve',
            key='no curve',
            value=stats,
        )
    points, sample_index = _refined_points(
        points, info['sample_index'], views, settings, clock, stats
    )
    ordered, closed = _longest_run(points, sample_index, views[0].curve.closed, settings, stats)
    if len(ordered) < 5:
        raise NoCurve(
            f'the longest gap-free piece of the curve has only {len(ordered)} points',
            key='no curve',
            value=stats,
        )
    waypoints, points = _smoothed_waypoints(ordered, closed, settings, stats)
    clock.lap('ordering, smoothing, resampling')
    stats.update(
        {
            'points': len(points),
            'closed': closed,
            'waypoints': len(waypoints),
            'length_m': _polyline_length(waypoints, closed),
            'time_ms': 1e3 * (time.perf_counter() - started),
            'stage_ms': clock.stage_ms,
        }
    )
    return Reconstruction(waypoints, closed, points, stats)


def _curve_views(
    images: Mapping[str, npt.ArrayLike],
    cameras: Mapping[str, PinholeCamera],
    settings: ReconstructionSettings,
    names: Sequence[str],
    clock: StageClock,
) -> list[View]:
    """The ``View`` of the curve in each named image, in ``names`` order. Raises
    ``NoCurve`` at the first image without one, naming the views that had one."""
    views: list[View] = []
    chain_counts: dict[str, int] = {}
    for name in names:
        view, count = view_curve(images[name], cameras[name], settings, clock)
        chain_counts[name] = count
        if view is None:
            seen = [n for n in names if chain_counts.get(n)]
            raise NoCurve(
                f'no curve in the {name} image (curve found in: {", ".join(seen) or "no view"})',
                key='no curve',
                value=name,
            )
        views.append(view)
    return views


def _intersection(
    views: Sequence[View], settings: ReconstructionSettings
) -> tuple[FloatArray, CandidateInfo]:
    """The points (K, 3) where the cones of views 1 and 2 meet, checked by view 3 if
    there is one, by ``settings.method``, in view-1 order, and their ``CandidateInfo``."""
    view3 = views[2] if len(views) > 2 else None
    tol3 = settings.third_view_tolerance
    if settings.method == 'ray_roots':
        points, info = reconstruct_ray_roots(
            views[0], views[1], view3, tol3_px=tol3, max_depth=settings.depth_range[1]
        )
        if view3 is not None:
            points, info = _second_pair(views, points, info, tol3, settings)
            points, info = _fill_end_on_stretches(views, points, info, tol3, settings)
        return points, info
    # the thesis's "suitable initial roots": log-spaced depths on each view-1 ray
    seeds = np.geomspace(*settings.depth_range, settings.seeds)
    return reconstruct_cone_lsq(
        views[0],
        views[1],
        view3,
        tol3_px=tol3,
        seed_depths=seeds,
        max_depth=settings.depth_range[1],
    )


def _intersection_stats(views: Sequence[View], info: CandidateInfo) -> dict[str, Any]:
    """The first entries of ``Reconstruction.stats``: the views' pieces and fit
    residuals and the counts of the intersection's samples and candidates."""
    return {
        'views': len(views),
        'pieces': '/'.join(str(len(v.curve.pieces)) for v in views),
        'samples': info['n_samples'],
        'candidates': info['n_candidates'],
        'rejected_by_third_view': info['n_rejected_view3'],
        'out_of_order': info['n_out_of_order'],
        'ambiguous': info['n_ambiguous'],
        'from_views_1_3': info.get('n_second_pair', 0),
        'from_views_2_3': info.get('n_end_on', 0),
        'without_candidates': info['n_without_candidates'],
        'fit_rms_px': '/'.join(f'{v.curve.rms_px:.3f}' for v in views),
    }


def _refined_points(
    points: FloatArray,
    sample_index: np.ndarray,
    views: Sequence[View],
    settings: ReconstructionSettings,
    clock: StageClock,
    stats: dict[str, Any],
) -> tuple[FloatArray, np.ndarray]:
    """(points, sample_index) with the points moved onto every view's curve when
    ``settings.refine``, less those that stay off it; adds the residuals before and after
    and the count dropped to ``stats``."""
    if settings.refine:
        closed = views[0].curve.closed
        rough, _ = smooth_along_curve(
            points,
            closed,
            settings.smoothing_window,
            sample_index,
            len(views[0].curve.xy) if closed else None,
            passes=1,
        )
        refined, residuals, before = refine_points(points, views, tangents(rough, closed))
        # a refined point that cannot come within REFINED_RESIDUAL_PX of every view's
        # curve (or several times the typical residual) lies on no common curve: a root
        # of a grazing intersection or a wrong branch. Left in, it is an outlier the
        # smoothing may follow, and a cluster of them splits the curve into runs.
        worst = np.max(np.abs(residuals), axis=1)
        finite = np.isfinite(worst)
        limit = max(
            REFINED_RESIDUAL_PX, 5 * float(np.median(worst[finite])) if finite.any() else 0.0
        )
        good = finite & (worst <= limit)
        stats_rejected_refined = int((finite & ~good).sum())
        points, sample_index = refined[good], sample_index[good]
        # then steps without the direction the views determine least (the tangent as
        # they see it): the full 3D steps above, their tangent part removed, keep
        # drifting where that direction's singular value passes rcond (three more of
        # them: torus_knot seed 0 7.5 -> 7.9 mm max, parabola seed 2 at noise 4 0.14
        # -> 0.88 mm), but they are what moves a wrong root off every curve for the
        # test above (steps within the rough tangent's normal plane alone, or with
        # rcond 0.05, kept one 12 mm off in sphere_loop seed 0)
        points, residuals, _ = refine_points(points, views, max_rank=2)
        clock.lap('refinement')
    else:
        before = residuals = np.column_stack([v.distance_px(points) for v in views])
        stats_rejected_refined = 0
    stats['off_curve_after_refinement'] = stats_rejected_refined
    stats['rms_residual_px_before'] = float(np.sqrt(np.mean(before**2)))
    stats['rms_residual_px'] = '/'.join(f'{r:.3f}' for r in np.sqrt(np.mean(residuals**2, axis=0)))
    return points, sample_index


def _longest_run(
    points: FloatArray,
    sample_index: np.ndarray,
    closed: bool,
    settings: ReconstructionSettings,
    stats: dict[str, Any],
) -> tuple[FloatArray, bool]:
    """(ordered points, closed) of the longest gap-free run of the points (in the order
    of ``sample_index``) once the outliers are out, the loop opened at its largest gap if
    that is too wide; adds the outlier and segment counts to ``stats``."""
    max_gap = 4 * settings.spacing + settings.smoothing_window  # [m]
    # outliers first (isolated points where three cones happen to meet off the curve):
    # each would otherwise open the loop or split the curve at its two jumps. Along the
    # curve's length, not view 1's chain index: where view 1 sees the curve end-on one
    # chain step covers millimetres, no quadratic in the index follows, and good points
    # there were dropped as outliers (inflection seed 3: 17 points, a 26 mm hole)
    parameter, period = robust_arc_parameter(points, closed)
    _, inlier = smooth_along_curve(
        points, closed, settings.smoothing_window, parameter, period=period if closed else None
    )
    points, sample_index = points[inlier], sample_index[inlier]
    # a cluster of wrong roots (on a self-approaching loop, a dozen samples whose true
    # stretch view 3 does not show, matched to the other strand 90 mm away) is no
    # smooth-curve outlier along the arc length, but it is a short run between jumps
    alone = stranded_runs(points, closed, max_gap, max(5, int(STRANDED_FRACTION * len(points))))
    stats['outliers'] = int((~inlier).sum() + alone.sum())
    points, sample_index = points[~alone], sample_index[~alone]
    ordered, closed, _ = open_at_largest_gap(points, closed, max_gap, sample_index)
    # never bridge a gap with a straight line: keep the longest gap-free run (two views
    # leave gaps where the intersection is ambiguous)
    runs = split_at_gaps(ordered, max_gap) if not closed else [np.arange(len(ordered))]
    longest = max(runs, key=lambda run: arc_length(ordered[run], False)[1])
    stats['segments'] = len(runs)
    stats['points_in_other_segments'] = len(ordered) - len(longest)
    return ordered[longest], closed


def _smoothed_waypoints(
    ordered: FloatArray,
    closed: bool,
    settings: ReconstructionSettings,
    stats: dict[str, Any],
) -> tuple[FloatArray, FloatArray]:
    """(waypoints evenly spaced along the smoothed run, the run's points the smoothing
    kept); adds the points it dropped to the outliers of ``stats``."""
    parameter, period = robust_arc_parameter(ordered, closed)  # see _longest_run
    smoothed, kept = smooth_along_curve(
        ordered, closed, settings.smoothing_window, parameter, period=period if closed else None
    )
    # holes the third view or refinement left (shorter than _longest_run's max_gap)
    polyline = bridge_gaps(without_reversals(smoothed, closed), closed, 2 * settings.spacing)
    waypoints = resample(polyline, closed, settings.spacing)
    stats['outliers'] += int((~kept).sum())
    # the published raw points: those that passed the third view and the outlier test
    return waypoints, ordered[kept]


def _polyline_length(waypoints: FloatArray, closed: bool) -> float:
    """Length [m] of the polyline through ``waypoints``, back to the first if ``closed``."""
    return float(
        np.sum(
            np.linalg.norm(
                np.diff(np.vstack([waypoints, waypoints[:1]]) if closed else waypoints, axis=0),
                axis=1,
            )
        )
    )
