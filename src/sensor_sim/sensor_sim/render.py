"""Rendering of the scenario's three camera images, depth maps and calibration-chart views.

Pure numpy/OpenCV (no ROS). ``SceneRenderer(scenario)`` ray-casts every pixel centre of
each true camera (distortion undone through ``PinholeCamera``) against the surface, once,
and caches per camera:

- the depth map: float32 (H, W) [m] along the optical axis (REP 118), NaN where the ray
  misses the surface;
- the clean scene image: float64 (H, W) grey levels in [0, 255].

Grey levels: ``255 * albedo * (intensity * R + ambient)`` clipped to [0, 255], where R is
the Oren-Nayar reflectance factor ``cos(theta_i) (A + B max(0, cos(phi_r - phi_i))
sin(alpha) tan(beta))`` (ALGORITHMS.md §4.3; ``variant='thesis'`` uses the thesis's
``sin(beta)`` instead of ``tan(beta)``, A5.1), which is Lambert's ``cos(theta_i)`` when the
roughness is 0. Radiance's 1/pi is folded into the camera gain, so a white Lambertian
surface lit head-on with intensity 1 reads 255. The light is distant (direction from the
surface toward the light); the viewer direction is per pixel, toward the camera centre.
Both faces of the surface sheet reflect alike; the face the camera sees is shaded. Where
no surface is hit the image is ``BACKGROUND_GREY``.

The curve is drawn as a dark line of full width ``curve.line_width_px``: its polylines are
sampled densely enough that projected segments are at most ``MAX_SEGMENT_PX`` long,
projected with ``PinholeCamera.project`` (so distortion is exactly the camera's), and each
pixel is darkened by the factor ``1 - contrast * coverage``, where coverage =
clip(width / 2 + 0.5 - distance, 0, 1) is a one-pixel linear ramp of the pixel centre's
distance to the projected polyline. A curve sample is visible unless the surface is nearer
than it by more than ``DEPTH_TOLERANCE`` (checked against the largest depth in the 3x3
pixels around it); a segment is drawn when both its ends are visible.

``add_noise`` turns a clean image into the published uint8 image; randomness comes only
from the generator the caller passes.
"""
from dataclasses import dataclass

import cv2
import numpy as np

from sensor_sim import chart, curves, surfaces
from vgm_common.errors import InvalidInput

BACKGROUND_GREY = 20.0
CHART_BACK_ALBEDO = 0.3  # the unprinted back of the chart plate
MAX_SEGMENT_PX = 0.5  # longest projected curve segment drawn as a straight piece [px]
MAX_CURVE_SAMPLES = 400_000
DEPTH_TOLERANCE = (1e-3, 1e-3)  # (absolute [m], relative) slack of the curve depth test
ON_VARIANTS = ('oren_nayar', 'thesis')
_STENCIL_ELEMENTS = 2_000_000  # pixel candidates handled at once when drawing the curve


def oren_nayar(normals, light, views, roughness, variant='oren_nayar'):
    """Oren-Nayar reflectance factor without albedo (N,).

    Args:
        normals: (N, 3) unit surface normals.
        light: (3,) unit vector from the surface toward the distant light.
        views: (N, 3) unit vectors from the surface point toward the viewer.
        roughness: Oren-Nayar sigma [rad]; 0 gives Lambert's cos(theta_i).
        variant: ``'oren_nayar'`` (sin(alpha) tan(beta), the published model) or
            ``'thesis'`` (sin(alpha) sin(beta), as the thesis prints it; A5.1).

    Returns:
        cos(theta_i) * (A + B * max(0, cos(phi_r - phi_i)) * sin(alpha) * f(beta)),
        0 where the light or the viewer is behind the surface (cos theta <= 0).
    """
    if variant not in ON_VARIANTS:
        raise InvalidInput(f'oren_nayar: variant must be one of {ON_VARIANTS}, got '
                           f'{variant!r}', key='variant', value=variant)
    normals = np.asarray(normals, dtype=float).reshape(-1, 3)
    views = np.asarray(views, dtype=float).reshape(-1, 3)
    light = np.asarray(light, dtype=float).reshape(3)
    cos_i = normals @ light
    cos_r = np.sum(normals * views, axis=1)
    sigma2 = roughness ** 2
    A = 1 - 0.5 * sigma2 / (sigma2 + 0.33)
    B = 0.45 * sigma2 / (sigma2 + 0.09)
    theta_i = np.arccos(np.clip(cos_i, -1.0, 1.0))
    theta_r = np.arccos(np.clip(cos_r, -1.0, 1.0))
    alpha, beta = np.maximum(theta_i, theta_r), np.minimum(theta_i, theta_r)
    # cos(phi_r - phi_i): angle between light and view projected on the tangent plane.
    light_tangent = light - cos_i[:, None] * normals
    view_tangent = views - cos_r[:, None] * normals
    norms = np.linalg.norm(light_tangent, axis=1) * np.linalg.norm(view_tangent, axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        cos_phi = np.where(norms > 1e-12,
                           np.sum(light_tangent * view_tangent, axis=1) / norms, 0.0)
    lit = (cos_i > 0) & (cos_r > 0)
    with np.errstate(invalid='ignore'):  # tan(beta) of unlit points is discarded below
        beta_term = np.tan(beta) if variant == 'oren_nayar' else np.sin(beta)
    factor = cos_i * (A + B * np.maximum(0.0, cos_phi) * np.sin(alpha) * beta_term)
    return np.where(lit, factor, 0.0)


def add_noise(clean, sigma, rng):
    """Camera image from a clean render: clean + N(0, sigma^2), rounded, clipped.

    Args:
        clean: (H, W) float grey levels.
        sigma: noise standard deviation [grey levels] (0 gives the rounded clean image).
        rng: ``numpy.random.Generator``; the only source of randomness.

    Returns:
        (H, W) uint8.
    """
    noisy = np.asarray(clean, dtype=float) + rng.normal(0.0, sigma, np.shape(clean))
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class _View:
    """What is cached per camera. Arrays are read-only."""

    normalized: np.ndarray  # (H + 2, W + 2, 2) undistorted x/z, y/z at pixel centres -1..W
    hit_base: np.ndarray  # (H, W, 3) [m], NaN where the ray misses
    depth: np.ndarray  # (H, W) float32 [m]
    image: np.ndarray  # (H, W) float64 grey levels, curve drawn


class SceneRenderer:
    """Renders a scenario's cameras; see the module docstring for the model.

    Args:
        scenario: a ``vgm_common.scenario.Scenario``.
        variant: Oren-Nayar form, ``'oren_nayar'`` (default) or ``'thesis'``.
        supersample: chart images average supersample x supersample rays per pixel.

    Each camera is rendered on first use and cached; chart images are cached per
    (camera, pose). Returned arrays are read-only. The caches are not locked: use one
    renderer from one thread.
    """

    def __init__(self, scenario, variant='oren_nayar', supersample=4):
        if variant not in ON_VARIANTS:
            raise InvalidInput(f'variant must be one of {ON_VARIANTS}, got {variant!r}',
                               key='variant', value=variant)
        if int(supersample) < 1:
            raise InvalidInput(f'supersample must be >= 1, got {supersample!r}',
                               key='supersample', value=supersample)
        self.scenario = scenario
        self.variant = variant
        self.supersample = int(supersample)
        self._views = {}
        self._charts = {}
        self._curve_pieces = None

    @property
    def camera_names(self):
        return tuple(self.scenario.cameras)

    def scene_image(self, name):
        """Clean image of camera ``name``: (H, W) float64 grey levels in [0, 255]."""
        return self._view(name).image

    def depth(self, name):
        """Depth map of camera ``name``: (H, W) float32 [m] along its optical axis, NaN
        where the pixel's ray misses the surface."""
        return self._view(name).depth

    def hit_points_base(self, name):
        """Surface point seen at each pixel centre of camera ``name``: (H, W, 3) base_link
        [m], NaN where the ray misses."""
        return self._view(name).hit_base

    def curve_polylines_base(self):
        """The curve's pieces as drawn: list of (N_i, 3) base_link polylines [m] (closed
        pieces end with their first point), dense enough for every camera."""
        if self._curve_pieces is None:
            self._curve_pieces = _dense_curve(self.scenario)
        return self._curve_pieces

    def chart_image(self, name, pose_index):
        """Clean image of camera ``name`` with the calibration chart at stage pose
        ``pose_index`` in front of the scene: (H, W) float64 grey levels.

        The pose is ``scenario.calibration.T_base_chart[pose_index]`` (the chart frame of
        ``sensor_sim.chart`` in base_link). The plate is drawn where its ray hit is nearer
        than the surface, each pixel the mean of supersample^2 rays. Printed face: chart
        albedo times (intensity * max(0, n . light) + ambient); the unprinted back:
        ``CHART_BACK_ALBEDO`` likewise. ``depth(name)`` stays the surface's.

        Raises:
            InvalidInput: the scenario has no calibration, or ``pose_index`` is out of range.
        """
        calibration = self.scenario.calibration
        if calibration is None:
            raise InvalidInput('the scenario has no calibration section', key='calibration')
        if not 0 <= pose_index < len(calibration.T_base_chart):
            raise InvalidInput(f'chart pose index {pose_index} out of range '
                               f'0..{len(calibration.T_base_chart) - 1}',
                               key='pose_index', value=pose_index)
        key = (name, pose_index)
        if key not in self._charts:
            image = _render_chart(self.scenario, self._camera(name), self._view(name),
                                  calibration.T_base_chart[pose_index], self.supersample)
            self._charts[key] = _read_only(image)
        return self._charts[key]

    def _camera(self, name):
        if name not in self.scenario.cameras:
            raise InvalidInput(f'unknown camera {name!r}; expected one of '
                               f'{self.camera_names}', key='camera', value=name)
        return self.scenario.cameras[name]

    def _view(self, name):
        camera = self._camera(name)
        if name not in self._views:
            self._views[name] = _render_view(self.scenario, camera,
                                             self.curve_polylines_base(), self.variant)
        return self._views[name]


def _read_only(array):
    array.setflags(write=False)
    return array


def _render_view(scenario, camera, curve_pieces, variant):
    height, width = camera.height, camera.width
    # Undistorted normalised coordinates at pixel centres -1..W, -1..H: the inner part
    # gives the pixel rays, the border lets chart supersamples interpolate at the edges.
    u, v = np.meshgrid(np.arange(-1.0, width + 1), np.arange(-1.0, height + 1))
    normalized = camera.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]))
    normalized = normalized.reshape(height + 2, width + 2, 2)
    rays_camera = np.concatenate([normalized[1:-1, 1:-1].reshape(-1, 2),
                                  np.ones((height * width, 1))], axis=1)
    # With rays of unit optical-axis component, the ray parameter t is the depth.
    directions_base = rays_camera @ camera.T_base_camera[:3, :3].T
    origin = camera.centre_base
    depth = surfaces.intersect_rays(scenario.surface, origin, directions_base)
    hit_base = origin + depth[:, None] * directions_base
    image = np.full(height * width, BACKGROUND_GREY)
    hit = np.isfinite(depth)
    image[hit] = _shade_surface(scenario, hit_base[hit], origin, variant)
    image = image.reshape(height, width)
    depth = depth.reshape(height, width).astype(np.float32)
    _draw_curve(image, depth, camera, curve_pieces, scenario.curve)
    return _View(normalized=_read_only(normalized),
                 hit_base=_read_only(hit_base.reshape(height, width, 3)),
                 depth=_read_only(depth), image=_read_only(image))


def _shade_surface(scenario, points_base, camera_centre, variant):
    """Grey levels (N,) of surface points seen from ``camera_centre``."""
    surface, lighting = scenario.surface, scenario.lighting
    views = camera_centre - points_base
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    normals = surfaces.normal_base(surface, points_base)
    normals *= np.where(np.sum(normals * views, axis=1) < 0, -1.0, 1.0)[:, None]
    reflectance = oren_nayar(normals, lighting.direction_base, views, surface.roughness,
                             variant)
    grey = 255.0 * surface.albedo * (lighting.intensity * reflectance + lighting.ambient)
    return np.clip(grey, 0.0, 255.0)


def _dense_curve(scenario):
    """Curve pieces sampled so that no projected segment exceeds MAX_SEGMENT_PX in any
    camera; analytic curves are re-sampled exactly, ``points`` curves are subdivided
    linearly (their polyline is the curve)."""
    curve, surface = scenario.curve, scenario.surface
    pieces = curves.curve_polylines(curve, surface)
    longest = max(_longest_projected_segment(camera, piece)
                  for camera in scenario.cameras.values() for piece in pieces)
    if curve.kind != 'points' and longest > MAX_SEGMENT_PX:
        samples = min(int(np.ceil(curve.samples * 1.2 * longest / MAX_SEGMENT_PX)),
                      MAX_CURVE_SAMPLES)
        pieces = curves.curve_polylines(curve, surface, samples=samples)
    for camera in scenario.cameras.values():
        pieces = [_subdivide(camera, piece) for piece in pieces]
    return [_read_only(piece) for piece in pieces]


def _longest_projected_segment(camera, points_base):
    pixels, _ = camera.project(points_base)
    lengths = np.linalg.norm(np.diff(pixels, axis=0), axis=1)
    lengths = lengths[np.isfinite(lengths)]
    return lengths.max() if len(lengths) else 0.0


def _subdivide(camera, points_base):
    """Split segments whose projection is longer than MAX_SEGMENT_PX, linearly in 3D."""
    pixels, _ = camera.project(points_base)
    lengths = np.linalg.norm(np.diff(pixels, axis=0), axis=1)
    parts = np.where(np.isfinite(lengths),
                     np.ceil(np.nan_to_num(lengths) / MAX_SEGMENT_PX), 1).astype(int)
    parts = np.clip(parts, 1, MAX_CURVE_SAMPLES // len(points_base) + 1)
    if np.all(parts == 1):
        return points_base
    segment = np.repeat(np.arange(len(parts)), parts)
    # Fraction along each segment: 0, 1/k, ..., (k-1)/k.
    fraction = (np.arange(len(segment)) - np.repeat(np.cumsum(parts) - parts, parts)) \
        / np.repeat(parts, parts)
    start, end = points_base[segment], points_base[segment + 1]
    return np.vstack([start + fraction[:, None] * (end - start), points_base[-1:]])


def _draw_curve(image, depth, camera, pieces, curve):
    """Darken ``image`` (H, W) in place along the visible curve."""
    height, width = image.shape
    # Nothing in front where the ray missed: treat as infinitely far.
    far_depth = np.where(np.isfinite(depth), depth, np.inf)
    padded = np.pad(far_depth, 1, mode='edge')
    neighbourhood_max = np.max([padded[dv:dv + height, du:du + width]
                                for dv in range(3) for du in range(3)], axis=0)
    starts, ends = [], []
    for piece in pieces:
        pixels, point_depth = camera.project(piece)
        visible = np.isfinite(pixels).all(axis=1) & (point_depth > 0)
        col = np.clip(np.rint(np.nan_to_num(pixels[:, 0])), 0, width - 1).astype(int)
        row = np.clip(np.rint(np.nan_to_num(pixels[:, 1])), 0, height - 1).astype(int)
        in_image = ((pixels[:, 0] > -0.5) & (pixels[:, 0] < width - 0.5)
                    & (pixels[:, 1] > -0.5) & (pixels[:, 1] < height - 0.5))
        surface_depth = np.where(in_image, neighbourhood_max[row, col], np.inf)
        absolute, relative = DEPTH_TOLERANCE
        visible &= point_depth <= surface_depth + absolute + relative * point_depth
        # Segments still long after subdivision run off toward the camera plane (their
        # subdivision was capped); they are not drawn rather than drawn as straight lines.
        short = np.linalg.norm(np.diff(pixels, axis=0), axis=1) <= 4 * MAX_SEGMENT_PX
        drawn = visible[:-1] & visible[1:] & short
        starts.append(pixels[:-1][drawn])
        ends.append(pixels[1:][drawn])
    starts, ends = np.concatenate(starts), np.concatenate(ends)
    if not len(starts):
        return
    half_width = curve.line_width_px / 2
    # Every pixel within reach of the line lies in a square stencil around its segment's
    # midpoint, as segments are short.
    longest = np.max(np.linalg.norm(ends - starts, axis=1))
    reach = int(np.ceil(half_width + 0.5 + longest / 2)) + 1
    offsets = np.arange(-reach, reach + 1)
    du, dv = np.meshgrid(offsets, offsets)
    nearest = np.full(height * width, np.inf)
    # Chunks bound the memory of the (segments x stencil) arrays.
    chunk = max(1, _STENCIL_ELEMENTS // du.size)
    for first in range(0, len(starts), chunk):
        chunk_starts, chunk_ends = starts[first:first + chunk], ends[first:first + chunk]
        midpoints = np.rint((chunk_starts + chunk_ends) / 2).astype(int)
        cols = midpoints[:, :1] + du.ravel()
        rows = midpoints[:, 1:] + dv.ravel()
        distance = _point_segment_distance(cols, rows, chunk_starts, chunk_ends)
        inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
        np.minimum.at(nearest, (rows * width + cols)[inside], distance[inside])
    coverage = np.clip(half_width + 0.5 - nearest, 0.0, 1.0).reshape(height, width)
    image *= 1.0 - curve.contrast * coverage


def _point_segment_distance(cols, rows, starts, ends):
    """Distance [px] of pixel centres (M, K) to the M segments starts -> ends (M, 2)."""
    direction = ends - starts
    length2 = np.sum(direction * direction, axis=1)
    px, py = cols - starts[:, :1], rows - starts[:, 1:]
    with np.errstate(divide='ignore', invalid='ignore'):
        s = (px * direction[:, :1] + py * direction[:, 1:]) / length2[:, None]
    s = np.clip(np.nan_to_num(s), 0.0, 1.0)  # a zero-length segment is its start point
    return np.hypot(px - s * direction[:, :1], py - s * direction[:, 1:])


def _render_chart(scenario, camera, view, T_base_chart, supersample):
    """Chart-over-scene image; see ``SceneRenderer.chart_image``."""
    calibration, lighting = scenario.calibration, scenario.lighting
    rows, cols, spacing = calibration.rows, calibration.cols, calibration.spacing
    image = view.image.copy()
    box = _chart_pixel_box(camera, T_base_chart, rows, cols, spacing)
    if box is None:
        return image
    (u0, u1), (v0, v1) = box
    T_camera_chart = camera.T_camera_base @ T_base_chart
    R, origin = T_camera_chart[:3, :3], T_camera_chart[:3, 3]
    x, y = _supersample_normalized(view.normalized, box, supersample)
    # Plate plane n . p = n . origin; with rays (x, y, 1) the ray parameter is the depth.
    normal = R[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        chart_depth = (normal @ origin) / (normal[0] * x + normal[1] * y + normal[2])
    # Chart-frame coordinates of the hit: R^T (depth * ray - origin).
    chart_x = chart_depth * (R[0, 0] * x + R[1, 0] * y + R[2, 0]) - R[:, 0] @ origin
    chart_y = chart_depth * (R[0, 1] * x + R[1, 1] * y + R[2, 1]) - R[:, 1] @ origin
    albedo = chart.chart_albedo(np.column_stack([chart_x.ravel(), chart_y.ravel()]),
                                rows, cols, spacing).reshape(x.shape)
    printed = normal @ origin > 0  # the camera is on the chart's -z side
    face_normal_base = T_base_chart[:3, 2] * (-1.0 if printed else 1.0)
    irradiance = (lighting.intensity * max(0.0, face_normal_base @ lighting.direction_base)
                  + lighting.ambient)
    if not printed:
        albedo = np.where(np.isfinite(albedo), CHART_BACK_ALBEDO, np.nan)
    chart_grey = np.clip(255.0 * albedo * irradiance, 0.0, 255.0)
    # Per pixel of the box, the scene's depth and grey level, repeated for its samples.
    scene_depth = view.depth[v0:v1, u0:u1].astype(float)
    scene_depth = np.where(np.isfinite(scene_depth), scene_depth, np.inf)
    scene_depth = np.repeat(np.repeat(scene_depth, supersample, 0), supersample, 1)
    scene_grey = np.repeat(np.repeat(image[v0:v1, u0:u1], supersample, 0), supersample, 1)
    on_chart = np.isfinite(albedo) & (chart_depth > 0) & (chart_depth < scene_depth)
    samples = np.where(on_chart, chart_grey, scene_grey)
    image[v0:v1, u0:u1] = samples.reshape(v1 - v0, supersample, u1 - u0,
                                          supersample).mean(axis=(1, 3))
    return image


def _chart_pixel_box(camera, T_base_chart, rows, cols, spacing):
    """((u0, u1), (v0, v1)) pixel index ranges holding the plate's image, the whole image
    if the plate reaches behind the camera, None if it is entirely behind or outside."""
    (x0, x1), (y0, y1) = chart.chart_plate_extent(rows, cols, spacing)
    s = np.linspace(0.0, 1.0, 65)
    outline = np.concatenate([
        np.column_stack([x0 + s * (x1 - x0), np.full_like(s, y0)]),
        np.column_stack([x0 + s * (x1 - x0), np.full_like(s, y1)]),
        np.column_stack([np.full_like(s, x0), y0 + s * (y1 - y0)]),
        np.column_stack([np.full_like(s, x1), y0 + s * (y1 - y0)])])
    outline_base = (np.column_stack([outline, np.zeros(len(outline))])
                    @ T_base_chart[:3, :3].T + T_base_chart[:3, 3])
    pixels, depth = camera.project(outline_base)
    if np.all(depth <= 0):
        return None
    if np.any(depth <= 0):
        return (0, camera.width), (0, camera.height)
    # Distortion bends the edges between outline samples by far less than the margin.
    margin = 3
    u0 = int(max(np.floor(pixels[:, 0].min()) - margin, 0))
    u1 = int(min(np.ceil(pixels[:, 0].max()) + margin + 1, camera.width))
    v0 = int(max(np.floor(pixels[:, 1].min()) - margin, 0))
    v1 = int(min(np.ceil(pixels[:, 1].max()) + margin + 1, camera.height))
    if u0 >= u1 or v0 >= v1:
        return None
    return (u0, u1), (v0, v1)


def _supersample_normalized(normalized, box, supersample):
    """Undistorted coordinates (x, y), each (S * rows, S * cols), of S x S rays per pixel
    of ``box``, at offsets (k + 0.5) / S - 0.5 from each pixel centre.

    Bilinear interpolation of the pixel-centre map (cv2.resize samples exactly those
    offsets). The map is smooth, so the error is about 0.1 * |k1| * r / fx pixels (~1e-4 px
    for modest distortion), far below what the chart's antialiasing resolves.
    """
    (u0, u1), (v0, v1) = box
    # The map starts at pixel -1; take one pixel of border on each side, then crop it.
    region = normalized[v0:v1 + 2, u0:u1 + 2]
    size = (region.shape[1] * supersample, region.shape[0] * supersample)
    fine = cv2.resize(region, size, interpolation=cv2.INTER_LINEAR)
    fine = fine[supersample:-supersample, supersample:-supersample]
    return fine[..., 0], fine[..., 1]
