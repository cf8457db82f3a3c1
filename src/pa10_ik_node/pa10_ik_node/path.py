"""A waypoint path by arc length: interpolation, nearest point, closed-loop handling. No ROS.

Waypoints are (N, 4, 4) poses in base_link (INTERFACES.md /curve/waypoints): origin on the
surface, x along the tangent, z the approach direction into the surface. A path whose
ends meet (closer than ``closed_tolerance``) is a loop and is followed once around, back
to its start.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

# A step between waypoints closer than ~18 deg to their approach axis does not lie on a
# surface (INTERFACES.md: x along the tangent, z into the surface): no tool frame.
CURVATURE_WINDOW_M = 0.005  # [m] chords over which WaypointPath.curvature is measured
MAX_APPROACH_COSINE = 0.95


def validate_waypoints(waypoints: npt.ArrayLike, min_spacing: float = 1e-6) -> FloatArray:
    """The waypoints as a finite (N, 4, 4) float array with orthonormal rotations.

    Consecutive duplicates (closer than ``min_spacing`` [m]) are dropped.

    Raises:
        InvalidInput: empty, non-finite, wrong shape, fewer than 2 distinct points, or a
            rotation that is not orthonormal.
    """
    T = np.array(waypoints, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise InvalidInput(
            f'waypoints must be a non-empty (N, 4, 4) array, got shape {T.shape}',
            'waypoints',
            T.shape,
        )
    if not np.all(np.isfinite(T)):
        raise InvalidInput('waypoints must be finite', 'waypoints')
    R = T[:, :3, :3]
    if np.max(np.abs(R @ np.transpose(R, (0, 2, 1)) - np.eye(3))) > 1e-4:
        raise InvalidInput('waypoint rotations must be orthonormal', 'waypoints')
    keep = np.concatenate(
        [[True], np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) > min_spacing]
    )
    T = T[keep]
    if len(T) < 2:
        raise InvalidInput('the path needs at least 2 distinct waypoints', 'waypoints')
    steps = np.diff(T[:, :3, 3], axis=0)
    steps /= np.linalg.norm(steps, axis=1, keepdims=True)
    along = np.abs(np.einsum('ij,ij->i', steps, T[:-1, :3, 2]))
    worst = int(np.argmax(along))
    if along[worst] > MAX_APPROACH_COSINE:
        raise InvalidInput(
            f'the path runs along its approach axis at waypoint {worst} ('
            f'{np.degrees(np.arccos(min(along[worst], 1.0))):.1f} deg from it): waypoints '
            'must lie on the surface, z the approach into it',
            'waypoints',
            worst,
        )
    return T


class WaypointPath:
    """Piecewise-linear path through the waypoints with interpolated approach axes.

    Args:
        waypoints: (N, 4, 4) poses in base_link (validated by ``validate_waypoints``).
        closed_tolerance: [m] ends closer than this make a loop; the first point is then
            appended so that the path returns to its start.

    Attributes:
        points (M, 3) [m], approach (M, 3) unit z axes, arc (M,) cumulative length [m],
        length [m], closed (bool), curvature (M,) [1/m] across the approach axis (see
        ``lateral_curvature``).
    """

    def __init__(self, waypoints: npt.ArrayLike, closed_tolerance: float = 0.01) -> None:
        T = validate_waypoints(waypoints)
        points, approach = T[:, :3, 3], T[:, :3, 2]
        gap = np.linalg.norm(points[-1] - points[0])
        spacing = np.median(np.linalg.norm(np.diff(points, axis=0), axis=1))
        self.closed = bool(len(points) > 3 and gap < max(closed_tolerance, 1.5 * spacing))
        if self.closed and gap > 1e-9:
            points = np.vstack([points, points[:1]])
            approach = np.vstack([approach, approach[:1]])
        self.points = points
        self.approach = approach / np.linalg.norm(approach, axis=1, keepdims=True)
        steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(steps)])
        self.length = float(self.arc[-1])
        self.T = T
        self.curvature = self.lateral_curvature()

    def _points_at(self, s: FloatArray) -> FloatArray:
        """(K, 3) points [m] at arc lengths ``s`` (K,) [m] (wrapped on a loop, clamped
        else)."""
        s = np.mod(s, self.length) if self.closed else np.clip(s, 0.0, self.length)
        return np.column_stack([np.interp(s, self.arc, self.points[:, k]) for k in range(3)])

    def lateral_curvature(self, window: float = CURVATURE_WINDOW_M) -> FloatArray:
        """(M,) curvature [1/m] of the path at each point across its approach axis: the
        turn between the chords ``window`` [m] behind and ahead over ``window`` (a mean
        over 2 ``window``, so 1 mm waypoint noise does not read as a sharp bend)."""
        if self.length <= 0:
            return np.zeros(len(self.arc))
        here = self.points
        behind = here - self._points_at(self.arc - window)
        ahead = self._points_at(self.arc + window) - here
        z = self.approach
        behind -= z * np.einsum('ij,ij->i', behind, z)[:, None]
        ahead -= z * np.einsum('ij,ij->i', ahead, z)[:, None]
        norms = np.linalg.norm(behind, axis=1) * np.linalg.norm(ahead, axis=1)
        cos = np.einsum('ij,ij->i', behind, ahead) / np.maximum(norms, 1e-18)
        turn = np.where(norms > 1e-18, np.arccos(np.clip(cos, -1.0, 1.0)), 0.0)
        return turn / window

    def nominal_duration(self, max_speed: float, max_lateral_acceleration: float) -> float:
        """[s] The time to travel the path at ``max_speed`` [m/s], slowed to
        sqrt(``max_lateral_acceleration`` [m/s^2] / curvature) where it bends."""
        speeds = np.full(len(self.arc), float(max_speed))
        bent = self.curvature > 0
        speeds[bent] = np.minimum(
            speeds[bent], np.sqrt(max_lateral_acceleration / self.curvature[bent])
        )
        steps = np.diff(self.arc)
        return float(np.sum(steps / np.minimum(speeds[:-1], speeds[1:])))

    def largest_curvature(self, start: float, end: float) -> float:
        """Largest ``curvature`` [1/m] of the points with arc length in [start, end] [m]
        (wrapped on a loop), or at the point nearest ``start``."""
        if self.closed and end - start >= self.length:
            return float(np.max(self.curvature))
        a, b = (
            (np.mod(start, self.length), np.mod(end, self.length))
            if self.closed
            else (
                start,
                end,
            )
        )
        if a <= b:
            inside = (self.arc >= a) & (self.arc <= b)
        else:  # the window passes the loop's start
            inside = (self.arc >= a) | (self.arc <= b)
        if not inside.any():
            return float(self.curvature[int(np.argmin(np.abs(self.arc - a)))])
        return float(np.max(self.curvature[inside]))

    def sample(self, s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(point (3,), approach (3,) unit, tangent (3,) unit) at arc length ``s`` [m]
        (clamped to the path)."""
        # min/max, not np.clip: the same numbers at a tenth of the time on scalars
        s = min(max(float(s), 0.0), self.length)
        i = min(max(int(np.searchsorted(self.arc, s, side='right')) - 1, 0), len(self.arc) - 2)
        h = self.arc[i + 1] - self.arc[i]
        t = (s - self.arc[i]) / h if h > 0 else 0.0
        point = self.points[i] + t * (self.points[i + 1] - self.points[i])
        approach = self.approach[i] + t * (self.approach[i + 1] - self.approach[i])
        approach /= np.linalg.norm(approach)
        tangent = (self.points[i + 1] - self.points[i]) / h if h > 0 else np.array([1.0, 0.0, 0.0])
        return point, approach, tangent

    def nearest(
        self, point: FloatArray, around: float | None = None, window: float | None = None
    ) -> tuple[float, float]:
        """Arc length [m] of the path point nearest to ``point`` (3,) and its distance [m].

        With ``around`` and ``window`` [m], only segments within ``window`` of arc length
        ``around`` are searched (a loop passes near itself at its start and end).
        """
        a, b = self.points[:-1], self.points[1:]
        ab = b - a
        lengths2 = np.maximum(np.sum(ab * ab, axis=1), 1e-18)
        t = np.clip(np.einsum('ij,ij->i', point - a, ab) / lengths2, 0.0, 1.0)
        distances = np.linalg.norm(a + t[:, None] * ab - point, axis=1)
        s = self.arc[:-1] + t * np.sqrt(lengths2)
        if around is not None and window is not None:
            distances = np.where(np.abs(s - around) <= window, distances, np.inf)
            if not np.isfinite(distances).any():
                return self.nearest(point)
        i = int(np.argmin(distances))
        return float(s[i]), float(distances[i])

    def lateral_distance(self, point: FloatArray, s: float) -> float:
        """Distance [m] from ``point`` to the path at ``s`` across the approach axis:
        the in-surface tracking error, leaving out the indentation along the approach."""
        p, z, _ = self.sample(s)
        d = point - p
        return float(np.linalg.norm(d - z * np.dot(z, d)))
