"""The scenario's curve as samples in base_link [m].

A curve is one or more *pieces* (``line_pair`` has two, every other kind one), each open or
closed. ``curve_polylines`` returns the pieces separately, because pieces must never be
joined when drawn or tracked; ``curve_points_base`` returns all samples in one array.

Sampling: each analytic piece is sampled uniformly in arc length (its parameter is first
sampled 16 times more densely, the chord lengths give the arc length as a function of the
parameter, and the curve is then evaluated exactly at the parameters of evenly spaced arc
lengths, so every sample lies on the true curve). ``points`` curves are returned as given.

Kinds (see ``sensor_sim.scenario._parse_curve`` for the keys):

- ``parabola`` / ``cubic``: p(t) = sum_k c[:, k] t^k over ``t_range``, c of shape
  (3, degree + 1) in base_link metres; open.
- ``ellipse``: center + axis_a cos t + axis_b sin t, t in [0, 2 pi); closed.
- ``circle``: radius about center in the plane normal to ``normal``; closed.
- ``line_pair``: two straight segments, ``segments[i] = (start, end)``; two open pieces.
- ``surface_loop``: the ellipse center + Rot(angle) (radii[0] cos t, radii[1] sin t) in the
  surface's (x, y) [surface units], lifted onto the surface (z = h) and mapped to
  base_link; closed.
- ``points``: the file's points in base_link, in order; closed if ``closed``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import cast

import numpy as np

from sensor_sim import surfaces
from sensor_sim.scenario import Curve, CurveParameter, Surface
from vgm_common.errors import ScenarioError
from vgm_common.geometry import FloatArray

_DENSE_FACTOR = 16  # parameter samples per output sample when measuring arc length

CurveFunction = Callable[[FloatArray], FloatArray]  # parameters t (M,) -> points (M, 3) [m]
Piece = tuple[CurveFunction, float, float]  # (evaluate, t_start, t_end) of one piece


def curve_is_closed(curve: Curve) -> bool:
    """True if the curve's pieces are closed loops (``line_pair`` and polynomials are open)."""
    if curve.kind == 'points':
        return cast(bool, curve.params['closed'])  # the parser made it a bool
    return curve.kind in ('ellipse', 'circle', 'surface_loop')


def curve_polylines(
    curve: Curve, surface: Surface, samples: int | None = None
) -> list[FloatArray]:
    """The curve's pieces as polylines in base_link.

    Args:
        curve: a ``Scenario.curve``.
        surface: the ``Scenario.surface`` (used by ``surface_loop``).
        samples: total number of distinct samples over all pieces (default
            ``curve.samples``); ignored for ``points`` curves, which come as given. Split
            between pieces in proportion to their length, at least 2 each.

    Returns:
        A list with one (N_i, 3) array [m] per piece (two for ``line_pair``, in the
        order of ``segments``). A closed piece ends with a copy of its first point, so
        consecutive rows are always the segments to draw.

    Raises:
        ScenarioError: a ``surface_loop`` that leaves the surface's domain.
    """
    if curve.kind == 'points':
        points = np.array(curve.params['points'], dtype=float)
        return [np.vstack([points, points[:1]]) if curve.params['closed'] else points]
    samples = curve.samples if samples is None else int(samples)
    closed = curve_is_closed(curve)
    pieces = _pieces(curve, surface)
    lengths = [_arc_length(evaluate, t0, t1, 1000)[1][-1] for evaluate, t0, t1 in pieces]
    counts = _split(samples, lengths)
    return [
        _sample_uniform_arc_length(evaluate, t0, t1, n, closed)
        for (evaluate, t0, t1), n in zip(pieces, counts)
    ]


def curve_points_base(curve: Curve, surface: Surface) -> FloatArray:
    """All samples of the curve (N, 3) in base_link [m], pieces one after another.

    N = ``curve.samples`` (the file's row count for ``points``); closed pieces are not
    repeated at their end. For ``line_pair`` the first piece's samples come first; use
    ``curve_polylines`` to get the pieces apart.
    """
    closed = curve_is_closed(curve)
    return np.vstack(
        [piece[:-1] if closed else piece for piece in curve_polylines(curve, surface)]
    )


def _pieces(curve: Curve, surface: Surface) -> list[Piece]:
    """(evaluate(t (M,)) -> (M, 3) base_link points, t_start, t_end) for each piece."""
    params = curve.params
    kind = curve.kind
    if kind in ('parabola', 'cubic'):
        coefficients = np.asarray(params['coefficients'], dtype=float)
        t0, t1 = _array_param(params, 't_range')
        # coefficients[:, k] multiplies t^k.
        return [
            (
                lambda t: np.vander(t, coefficients.shape[1], increasing=True) @ coefficients.T,
                t0,
                t1,
            )
        ]
    if kind == 'ellipse':
        center, axis_a, axis_b = params['center'], params['axis_a'], params['axis_b']
        return [
            (
                lambda t: center + np.outer(np.cos(t), axis_a) + np.outer(np.sin(t), axis_b),
                0.0,
                2 * np.pi,
            )
        ]
    if kind == 'circle':
        center, radius = params['center'], params['radius']
        normal = params['normal'] / np.linalg.norm(params['normal'])
        helper = np.eye(3)[np.argmin(np.abs(normal))]
        u = np.cross(normal, helper)
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        return [
            (
                lambda t: center + radius * (np.outer(np.cos(t), u) + np.outer(np.sin(t), v)),
                0.0,
                2 * np.pi,
            )
        ]
    if kind == 'line_pair':
        return [
            (_segment(start, end), 0.0, 1.0) for start, end in _array_param(params, 'segments')
        ]
    if kind == 'surface_loop':
        return [(lambda t: _surface_loop(params, surface, t), 0.0, 2 * np.pi)]
    raise ScenarioError(f'curve.type: unknown curve kind {kind!r}', key='curve.type', value=kind)


def _segment(a: FloatArray, b: FloatArray) -> CurveFunction:
    """The straight segment a -> b, t in [0, 1]."""
    return lambda t: a + np.outer(t, b - a)


def _surface_loop(
    params: Mapping[str, CurveParameter], surface: Surface, t: FloatArray
) -> FloatArray:
    c, s = np.cos(params['angle']), np.sin(params['angle'])
    center, radii = _array_param(params, 'center'), _array_param(params, 'radii')
    local = np.column_stack([radii[0] * np.cos(t), radii[1] * np.sin(t)])
    xy = center + local @ np.array([[c, s], [-s, c]])
    points = surfaces.surface_points_base(surface, xy)
    if not np.all(np.isfinite(points)):
        raise ScenarioError(
            "curve: the surface_loop leaves the surface's domain "
            f'(center {center.tolist()}, radii '
            f'{radii.tolist()}, surface extent {surface.extent})',
            key='curve.radii',
            value=radii,
        )
    return points


def _array_param(params: Mapping[str, CurveParameter], key: str) -> FloatArray:
    """``params[key]`` of a curve kind whose parser made it an array (vectors, matrices)."""
    return cast(FloatArray, params[key])


def _arc_length(
    evaluate: CurveFunction, t0: float, t1: float, n: int
) -> tuple[FloatArray, FloatArray]:
    """Parameters (n,) from t0 to t1 and the cumulative chord length (n,) [m] at each."""
    t = np.linspace(t0, t1, n)
    points = evaluate(t)
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return t, np.concatenate([[0.0], np.cumsum(steps)])


def _split(samples: int, lengths: Sequence[float]) -> list[int]:
    """Split ``samples`` between pieces in proportion to length, at least 2 each."""
    lengths_m = np.asarray(lengths, dtype=float)
    if len(lengths_m) == 1:
        return [max(samples, 2)]
    share = lengths_m / lengths_m.sum() if lengths_m.sum() > 0 else np.full(len(lengths_m), 0.5)
    counts = np.maximum(np.round(share * samples).astype(int), 2)
    counts[-1] = max(samples - counts[:-1].sum(), 2)
    return counts.tolist()


def _sample_uniform_arc_length(
    evaluate: CurveFunction, t0: float, t1: float, n: int, closed: bool
) -> FloatArray:
    """n samples evenly spaced in arc length (a closed piece gets its first point appended)."""
    t_dense, s_dense = _arc_length(evaluate, t0, t1, _DENSE_FACTOR * n + 1)
    total = s_dense[-1]
    if total == 0:  # a degenerate piece: all samples coincide
        return evaluate(np.full(n + closed, t0))
    # A closed piece's end point is its start: spread n samples over [0, L) and close.
    s = np.linspace(0.0, total, n + 1)[:-1] if closed else np.linspace(0.0, total, n)
    points = evaluate(np.interp(s, s_dense, t_dense))
    return np.vstack([points, points[:1]]) if closed else points
