"""Height-field surfaces z = h(x, y) of a scenario, with analytic gradients and ray casting.

Units and frames: ``h`` is evaluated in *surface units* in the surface frame. A surface
point (x, y, h(x, y)) is placed in base_link as

    p_base = T_base_surface @ (scale * (x, y, h(x, y)))

so one surface unit is ``scale`` metres. The surface exists only over its domain: the
scenario's ``extent`` box intersected with the kind's own domain (the sphere's disc, the
vase's unit box, the height map's grid); outside it every function here returns NaN.

Kinds (ALGORITHMS.md §6.6 for S1-S3):

- ``plane``: h = 0;
- ``S1``: h = -(x + y^3);
- ``S2``: h = x^2 y sin(x/3) + cos(y^2);
- ``S3``: h = xy + 0.5x - 0.6;
- ``sphere``: the upper hemisphere h = sqrt(r^2 - x^2 - y^2) on the disc x^2 + y^2 <= r^2;
- ``paraboloid``: the dome h = -(x^2 + y^2) / (2 r) (apex radius of curvature r =
  ``Surface.radius``; used in-process by the task generator, not a scenario type);
- ``vase``: Zhang et al. 1999's synthetic vase, h = sqrt(max(f(y)^2 - x^2, 0)) with
  f(y) = 0.15 - 0.1 y (6y+1)^2 (y-1)^2 (3y-2), on x in [-0.5, 0.5], y in [0, 1];
- ``heightmap``: bilinear interpolation of ``Surface.heights`` (rows along y, grid spacing
  ``cell``, node (row 0, col 0) at the extent's minimum corner).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt
from numpy.polynomial import Polynomial

from sensor_sim.scenario import Surface
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

Box = tuple[tuple[float, float], tuple[float, float]]  # ((x_min, x_max), (y_min, y_max))
BoolArray = npt.NDArray[np.bool_]

# Vase profile f(y) = 0.15 - 0.1 y (6y+1)^2 (y-1)^2 (3y-2) as a polynomial, so that its
# derivative is exact.
_VASE_PROFILE = 0.15 - 0.1 * (
    Polynomial([0, 1]) * Polynomial([1, 6]) ** 2 * Polynomial([-1, 1]) ** 2 * Polynomial([-2, 3])
)
_VASE_PROFILE_DERIVATIVE = _VASE_PROFILE.deriv()

# Ray marching: tiles per axis with their own slope bounds, samples per axis of the grid
# that measures them (a multiple of the tiles, plus one), the smallest march step as a
# fraction of the surface's size (features thinner than this along a ray may be skipped),
# and iteration caps.
_BOUND_TILES = 64
_BOUND_GRID_SAMPLES = _BOUND_TILES * 8 + 1
_MIN_STEP_FRACTION = 1.0 / 4000
_MAX_MARCH_STEPS = 20000
_MAX_REFINE_STEPS = 100
_DOMAIN_SLACK = 1e-12


def domain_box(surface: Surface) -> Box:
    """The surface's domain bounding box ((x_min, x_max), (y_min, y_max)) [surface units]:
    the extent intersected with the kind's own domain."""
    (x0, x1), (y0, y1) = surface.extent
    if surface.kind == 'sphere':
        r = surface.radius
        x0, x1, y0, y1 = max(x0, -r), min(x1, r), max(y0, -r), min(y1, r)
    elif surface.kind == 'vase':
        x0, x1, y0, y1 = max(x0, -0.5), min(x1, 0.5), max(y0, 0.0), min(y1, 1.0)
    elif surface.kind == 'heightmap':
        rows, cols = _height_grid(surface).shape
        x1 = min(x1, x0 + (cols - 1) * surface.cell)
        y1 = min(y1, y0 + (rows - 1) * surface.cell)
    if not (x0 < x1 and y0 < y1):
        raise InvalidInput(
            f'surface {surface.kind}: the extent {surface.extent} does not '
            "overlap the surface's own domain",
            key='surface.extent',
            value=surface.extent,
        )
    return (x0, x1), (y0, y1)


def in_domain(surface: Surface, xy_units: npt.ArrayLike) -> BoolArray:
    """Boolean (N,): which (N, 2) surface-unit points lie on the surface's domain.

    The boundary is widened by ``_DOMAIN_SLACK`` of the domain's size, so that points on
    its edge survive a round trip through base_link.
    """
    xy = np.asarray(xy_units, dtype=float).reshape(-1, 2)
    (x0, x1), (y0, y1) = domain_box(surface)
    slack = _DOMAIN_SLACK * max(x1 - x0, y1 - y0)
    x, y = xy[:, 0], xy[:, 1]
    inside = (x >= x0 - slack) & (x <= x1 + slack) & (y >= y0 - slack) & (y <= y1 + slack)
    if surface.kind == 'sphere':
        inside &= np.hypot(x, y) <= surface.radius + slack
    return inside


def height(surface: Surface, xy_units: npt.ArrayLike) -> FloatArray:
    """h(x, y) [surface units] at (N, 2) surface-unit points; NaN outside the domain."""
    return height_and_gradient(surface, xy_units)[0]


def gradient(surface: Surface, xy_units: npt.ArrayLike) -> FloatArray:
    """(dh/dx, dh/dy) (N, 2) at (N, 2) surface-unit points; NaN outside the domain."""
    return height_and_gradient(surface, xy_units)[1]


def height_and_gradient(
    surface: Surface, xy_units: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """h (N,) and its gradient (N, 2) at (N, 2) surface-unit points; NaN outside."""
    xy = np.asarray(xy_units, dtype=float).reshape(-1, 2)
    inside = in_domain(surface, xy)
    h = np.full(len(xy), np.nan)
    grad = np.full((len(xy), 2), np.nan)
    x, y = xy[inside, 0], xy[inside, 1]
    h[inside] = _heights(surface, x, y)
    grad[inside] = _gradients(surface, x, y, h[inside])
    return h, grad


def _heights(surface: Surface, x: FloatArray, y: FloatArray) -> FloatArray:
    """h (N,) of ``surface.kind`` at points known to be in the domain."""
    kind = surface.kind
    if kind == 'plane':
        return np.zeros_like(x)
    if kind == 'S1':
        return -(x + y**3)
    if kind == 'S2':
        return x * x * y * np.sin(x / 3) + np.cos(y * y)
    if kind == 'S3':
        return x * y + 0.5 * x - 0.6
    if kind == 'sphere':
        return np.sqrt(np.maximum(surface.radius**2 - x * x - y * y, 0.0))
    if kind == 'paraboloid':
        return -(x * x + y * y) / (2.0 * surface.radius)
    if kind == 'vase':
        f = _VASE_PROFILE(y)
        return np.sqrt(np.maximum(f * f - x * x, 0.0))
    if kind == 'heightmap':
        return _bilinear(surface, x, y)[0]
    raise InvalidInput(f'unknown surface kind {kind!r}', key='surface.type', value=kind)


def _gradients(surface: Surface, x: FloatArray, y: FloatArray, h: FloatArray) -> FloatArray:
    """(dh/dx, dh/dy) (N, 2) of ``surface.kind`` at points in the domain, heights h."""
    kind = surface.kind
    if kind == 'plane':
        return np.zeros((len(x), 2))
    if kind == 'S1':
        return np.column_stack([-np.ones_like(x), -3 * y**2])
    if kind == 'S2':
        s, c = np.sin(x / 3), np.cos(x / 3)
        return np.column_stack(
            [2 * x * y * s + x * x * y * c / 3, x * x * s - 2 * y * np.sin(y * y)]
        )
    if kind == 'S3':
        return np.column_stack([y + 0.5, x])
    if kind == 'sphere':
        return _divide_or_zero(np.column_stack([-x, -y]), h)
    if kind == 'paraboloid':
        return np.column_stack([-x, -y]) / surface.radius
    if kind == 'vase':
        # Where the vase is clamped to the base plane (h = 0) the surface is flat.
        f = _VASE_PROFILE(y)
        return _divide_or_zero(np.column_stack([-x, f * _VASE_PROFILE_DERIVATIVE(y)]), h)
    if kind == 'heightmap':
        return _bilinear(surface, x, y)[1]
    raise InvalidInput(f'unknown surface kind {kind!r}', key='surface.type', value=kind)


def _divide_or_zero(numerator: FloatArray, h: FloatArray) -> FloatArray:
    """numerator (N, 2) / h (N,), 0 where h == 0 (the rim of a sphere or vase)."""
    with np.errstate(divide='ignore', invalid='ignore'):
        out = numerator / h[:, None]
    out[h == 0] = 0.0
    return out


def _height_grid(surface: Surface) -> FloatArray:
    """``surface.heights`` of a heightmap (the scenario parser always sets it)."""
    if surface.heights is None:
        raise InvalidInput(f'surface {surface.kind}: no heights grid', key='surface.heights')
    return surface.heights


def _bilinear(surface: Surface, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
    heights = _height_grid(surface)
    rows, cols = heights.shape
    (x0, _), (y0, _) = surface.extent
    gx, gy = (x - x0) / surface.cell, (y - y0) / surface.cell
    i = np.clip(np.floor(gx).astype(int), 0, cols - 2)
    j = np.clip(np.floor(gy).astype(int), 0, rows - 2)
    fx, fy = gx - i, gy - j
    h00, h10 = heights[j, i], heights[j, i + 1]
    h01, h11 = heights[j + 1, i], heights[j + 1, i + 1]
    h = (1 - fy) * ((1 - fx) * h00 + fx * h10) + fy * ((1 - fx) * h01 + fx * h11)
    dh_dx = ((1 - fy) * (h10 - h00) + fy * (h11 - h01)) / surface.cell
    dh_dy = ((1 - fx) * (h01 - h00) + fx * (h11 - h10)) / surface.cell
    return h, np.column_stack([dh_dx, dh_dy])


def to_surface_units(surface: Surface, points_base: npt.ArrayLike) -> FloatArray:
    """(N, 3) base_link points [m] -> (N, 3) surface-frame points [surface units]."""
    points = np.asarray(points_base, dtype=float).reshape(-1, 3)
    R, t = surface.T_base_surface[:3, :3], surface.T_base_surface[:3, 3]
    return (points - t) @ R / surface.scale


def surface_points_base(surface: Surface, xy_units: npt.ArrayLike) -> FloatArray:
    """Lift (N, 2) surface-unit points onto the surface: (N, 3) base_link points [m],
    NaN outside the domain."""
    xy = np.asarray(xy_units, dtype=float).reshape(-1, 2)
    local = np.column_stack([xy, height(surface, xy)]) * surface.scale
    return local @ surface.T_base_surface[:3, :3].T + surface.T_base_surface[:3, 3]


def normal_base(surface: Surface, points_base: npt.ArrayLike) -> FloatArray:
    """Unit surface normals (N, 3) in base_link under (N, 3) base_link points.

    The normal is that of the surface at the point's (x, y) in the surface frame (the
    point need not lie on the surface) and points to the surface frame's +z side. NaN
    outside the domain.
    """
    local = to_surface_units(surface, points_base)
    grad = gradient(surface, local[:, :2])
    normal_surface = np.column_stack([-grad, np.ones(len(grad))])
    normal_surface /= np.linalg.norm(normal_surface, axis=1, keepdims=True)
    return normal_surface @ surface.T_base_surface[:3, :3].T


def signed_height_base(surface: Surface, points_base: npt.ArrayLike) -> FloatArray:
    """Approximate signed distance [m] (N,) of (N, 3) base_link points above the surface.

    First order: (z - h(x, y)) * scale / sqrt(1 + |grad h|^2) in the surface frame, exact
    for planes and good while the point is close to the surface compared with its radius
    of curvature. Positive on the +z side, NaN outside the domain.
    """
    local = to_surface_units(surface, points_base)
    h, grad = height_and_gradient(surface, local[:, :2])
    return (local[:, 2] - h) * surface.scale / np.sqrt(1 + np.sum(grad * grad, axis=1))


def intersect_rays(
    surface: Surface, origin_base: npt.ArrayLike, directions_base: npt.ArrayLike
) -> FloatArray:
    """First intersection of rays from one origin with the surface.

    Args:
        surface: a ``Scenario.surface``.
        origin_base: (3,) ray origin in base_link [m] (a camera centre).
        directions_base: (N, 3) ray directions in base_link (any non-zero length).

    Returns:
        t (N,) with hit = origin + t * direction, the first hit at t > 0; with unit
        directions t is the distance [m]. NaN where a ray misses the surface.

    Plane and sphere are solved in closed form. Other kinds are ray-marched, all rays at
    once, with steps that cannot jump over the surface: |z - h| divided by the fastest
    rate at which z - h can change along the ray, given bounds on grad h (measured on a
    fine grid, with a safety factor) over the whole domain, or over the current one of
    64 x 64 tiles if that allows a longer step within the tile; never shorter than 1/4000
    of the surface's size. A sign change of z - h is then refined by the Illinois method
    to ~1e-13 relative.
    """
    origin = np.asarray(origin_base, dtype=float).reshape(3)
    directions = np.asarray(directions_base, dtype=float).reshape(-1, 3)
    lengths = np.linalg.norm(directions, axis=1)
    if not np.all(lengths > 0):
        raise InvalidInput('intersect_rays: zero-length direction', key='directions_base')
    origin_units = to_surface_units(surface, origin[None, :])[0]
    R = surface.T_base_surface[:3, :3]
    directions_units = (directions / lengths[:, None]) @ R
    if surface.kind == 'plane':
        t_units = _intersect_plane(surface, origin_units, directions_units)
    elif surface.kind == 'sphere':
        t_units = _intersect_sphere(surface, origin_units, directions_units)
    else:
        t_units = _march(surface, origin_units, directions_units)
    return t_units * surface.scale / lengths


def _intersect_plane(surface: Surface, o: FloatArray, d: FloatArray) -> FloatArray:
    with np.errstate(divide='ignore', invalid='ignore'):
        t = -o[2] / d[:, 2]
    t[~(t > 0)] = np.nan
    hit = o[:2] + t[:, None] * d[:, :2]
    t[~in_domain(surface, hit)] = np.nan
    return t


def _intersect_sphere(surface: Surface, o: FloatArray, d: FloatArray) -> FloatArray:
    # |o + t d|^2 = r^2 with unit d: t = -b -+ sqrt(b^2 - c).
    b = d @ o
    c = o @ o - surface.radius**2
    with np.errstate(invalid='ignore'):
        root = np.sqrt(b * b - c)
    t = np.full(len(d), np.nan)
    # The far root is the first hit only where the near one is invalid (behind the origin,
    # on the lower half, or outside the extent): the far root is tried first, then
    # overwritten by the near root where that one is valid.
    for t_candidate in (-b + root, -b - root):
        point = o + t_candidate[:, None] * d
        valid = (t_candidate > 0) & (point[:, 2] >= 0) & in_domain(surface, point[:, :2])
        t[valid] = t_candidate[valid]
    return t


def _march_bounds(surface: Surface) -> tuple[FloatArray, FloatArray, tuple[float, float]]:
    """Per-tile slope ranges and the height range of the surface, from a fine grid.

    The domain box is cut into ``_BOUND_TILES`` x ``_BOUND_TILES`` tiles. Returns
    (slope_x, slope_y, (z_lo, z_hi)): slope_x[j, i] = (lo, hi) of dh/dx over tile
    (row j along y, column i along x) and its eight neighbours, likewise slope_y. Slopes
    are secants between grid neighbours, which stay finite where the analytic gradient
    does not (the vase's silhouette); as extremes may fall between samples, each range is
    widened by a quarter of its width plus a tenth of its magnitude. The neighbours make a
    step that ends a little past its tile still safe.
    """
    (x0, x1), (y0, y1) = domain_box(surface)
    n = _BOUND_GRID_SAMPLES
    x, y = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    h = height(surface, np.column_stack([x.ravel(), y.ravel()])).reshape(n, n)
    dx, dy = (x1 - x0) / (n - 1), (y1 - y0) / (n - 1)
    starts = np.arange(_BOUND_TILES) * ((n - 1) // _BOUND_TILES)
    ranges = []
    for slope in (np.diff(h, axis=1) / dx, np.diff(h, axis=0) / dy):
        low = np.fmin.reduceat(np.fmin.reduceat(slope, starts, axis=0), starts, axis=1)
        high = np.fmax.reduceat(np.fmax.reduceat(slope, starts, axis=0), starts, axis=1)
        low, high = _with_neighbours(low, np.fmin), _with_neighbours(high, np.fmax)
        pad = 0.25 * (high - low) + 0.1 * np.maximum(np.abs(low), np.abs(high)) + 1e-6
        ranges.append(np.stack([low - pad, high + pad], axis=-1))
    # Between samples h can exceed the grid's values by at most slope * spacing.
    margin = max(np.max(np.abs(r)) for r in ranges) * max(dx, dy)
    return ranges[0], ranges[1], (np.nanmin(h) - margin, np.nanmax(h) + margin)


def _with_neighbours(tiles: FloatArray, reduce: np.ufunc) -> FloatArray:
    """Reduce each tile's value with its eight neighbours' (edges replicated)."""
    rows, cols = tiles.shape
    padded = np.pad(tiles, 1, mode='edge')
    out = tiles.copy()
    for dr in range(3):
        for dc in range(3):
            out = reduce(out, padded[dr : dr + rows, dc : dc + cols])
    return out


def _tile_and_exit(
    position: FloatArray, direction: FloatArray, tile_size: float
) -> tuple[npt.NDArray[np.int_], FloatArray]:
    """Along one axis: the tile (N,) a ray at ``position`` (N,) [from the domain's min]
    is moving through, and the ray length (N,) to that tile's far edge."""
    cell = position / tile_size
    index = np.clip(
        np.where(direction < 0, np.ceil(cell) - 1, np.floor(cell)), 0, _BOUND_TILES - 1
    )
    edge = (index + (direction > 0)) * tile_size
    with np.errstate(divide='ignore', invalid='ignore'):
        length = np.where(direction != 0, (edge - position) / direction, np.inf)
    return index.astype(int), np.maximum(length, 0.0)


def _slab(o: float, d: FloatArray, low: float, high: float) -> tuple[FloatArray, FloatArray]:
    """Ray parameters where o + t d lies within [low, high] along one axis (N,) each."""
    with np.errstate(divide='ignore', invalid='ignore'):
        t_a, t_b = (low - o) / d, (high - o) / d
    t_in, t_out = np.minimum(t_a, t_b), np.maximum(t_a, t_b)
    parallel = d == 0
    inside = (o >= low) & (o <= high)
    t_in[parallel] = np.where(inside, -np.inf, np.inf)
    t_out[parallel] = np.where(inside, np.inf, -np.inf)
    return t_in, t_out


def _march(surface: Surface, o: FloatArray, d: FloatArray) -> FloatArray:
    (x0, x1), (y0, y1) = domain_box(surface)
    slope_x, slope_y, (z_lo, z_hi) = _march_bounds(surface)
    tile_w, tile_h = (x1 - x0) / _BOUND_TILES, (y1 - y0) / _BOUND_TILES
    t_enter, t_exit = np.zeros(len(d)), np.full(len(d), np.inf)
    for axis, (low, high) in enumerate(((x0, x1), (y0, y1), (z_lo, z_hi))):
        t_in, t_out = _slab(o[axis], d[:, axis], low, high)
        t_enter, t_exit = np.maximum(t_enter, t_in), np.minimum(t_exit, t_out)
    min_step = _MIN_STEP_FRACTION * max(x1 - x0, y1 - y0, z_hi - z_lo)

    def closing_rate(
        direction: FloatArray, g: FloatArray, range_x: FloatArray, range_y: FloatArray
    ) -> FloatArray:
        """Fastest rate (N,) at which the gap g = z - h can close along unit rays.

        Along a ray z - h changes at d_z - h_x d_x - h_y d_y; over slope ranges (N, 2)
        this bounds the closing from above (g > 0) or below (g < 0).
        """
        x_a, x_b = direction[:, 0] * range_x[:, 0], direction[:, 0] * range_x[:, 1]
        y_a, y_b = direction[:, 1] * range_y[:, 0], direction[:, 1] * range_y[:, 1]
        rate = np.where(
            g > 0,
            -direction[:, 2] + np.maximum(x_a, x_b) + np.maximum(y_a, y_b),
            direction[:, 2] - np.minimum(x_a, x_b) - np.minimum(y_a, y_b),
        )
        return np.maximum(rate, 1e-12)

    whole_x = np.array([slope_x[..., 0].min(), slope_x[..., 1].max()])
    whole_y = np.array([slope_y[..., 0].min(), slope_y[..., 1].max()])

    def safe_step(t: FloatArray, g: FloatArray, index: npt.NDArray[np.intp]) -> FloatArray:
        """Longest step from t along rays ``index`` that cannot jump over the surface:
        the larger of the step safe under the whole domain's slope bounds and the step
        safe under the current tile's, which must stay in the tile."""
        direction = d[index]
        i, exit_x = _tile_and_exit(o[0] + t * direction[:, 0] - x0, direction[:, 0], tile_w)
        j, exit_y = _tile_and_exit(o[1] + t * direction[:, 1] - y0, direction[:, 1], tile_h)
        in_tile = np.minimum(
            np.abs(g) / closing_rate(direction, g, slope_x[j, i], slope_y[j, i]),
            np.minimum(exit_x, exit_y),
        )
        anywhere = np.abs(g) / closing_rate(direction, g, whole_x[None], whole_y[None])
        return np.maximum(in_tile, anywhere)

    def gap(t: FloatArray, index: npt.NDArray[np.intp]) -> FloatArray:
        """z - h along rays ``index`` at parameters t."""
        point = o + t[:, None] * d[index]
        # The marched kinds' domain is the whole box; clipping only undoes rounding at its
        # faces.
        return point[:, 2] - _heights(
            surface, np.clip(point[:, 0], x0, x1), np.clip(point[:, 1], y0, y1)
        )

    result = np.full(len(d), np.nan)
    active = np.flatnonzero(t_enter < t_exit)
    t = t_enter[active]
    g = gap(t, active)
    empty = np.zeros(0)
    lo, hi, g_lo, g_hi = [empty], [empty], [empty], [empty]
    bracketed = [np.zeros(0, dtype=int)]
    for _ in range(_MAX_MARCH_STEPS):
        if not len(active):
            break
        step = np.maximum(safe_step(t, g, active), min_step)
        t_next = np.minimum(t + step, t_exit[active])
        g_next = gap(t_next, active)
        crossed = (np.sign(g_next) != np.sign(g)) | (g == 0)
        lo.append(t[crossed])
        hi.append(t_next[crossed])
        g_lo.append(g[crossed])
        g_hi.append(g_next[crossed])
        bracketed.append(active[crossed])
        keep = ~crossed & (t_next < t_exit[active])
        active, t, g = active[keep], t_next[keep], g_next[keep]
    index = np.concatenate(bracketed)
    result[index] = _refine(
        gap,
        index,
        np.concatenate(lo),
        np.concatenate(hi),
        np.concatenate(g_lo),
        np.concatenate(g_hi),
    )
    return result


def _refine(
    gap: Callable[[FloatArray, npt.NDArray[np.intp]], FloatArray],
    index: npt.NDArray[np.intp],
    a: FloatArray,
    b: FloatArray,
    g_a: FloatArray,
    g_b: FloatArray,
) -> FloatArray:
    """Root of ``gap`` on brackets [a, b] (g_a, g_b of opposite signs or g_a == 0) by the
    Illinois variant of regula falsi, all rays at once."""
    root = np.where(g_a == 0, a, b)
    todo = np.flatnonzero(g_a != 0)
    for _ in range(_MAX_REFINE_STEPS):
        if not len(todo):
            break
        ia, ib, ga, gb = a[todo], b[todo], g_a[todo], g_b[todo]
        c = (ia * gb - ib * ga) / (gb - ga)
        gc = gap(c, index[todo])
        same_side = np.sign(gc) == np.sign(gb)
        # Illinois: the endpoint that stays has its value halved, so it cannot stall.
        a[todo] = np.where(same_side, ia, ib)
        g_a[todo] = np.where(same_side, ga / 2, gb)
        b[todo], g_b[todo] = c, gc
        root[todo] = c
        done = (gc == 0) | (np.abs(ib - c) <= 1e-13 * np.maximum(np.abs(c), 1.0))
        todo = todo[~done]
    return root
