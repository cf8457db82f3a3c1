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

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import cv2
import numpy as np
import numpy.typing as npt
from scipy.special import ndtri

from sensor_sim import chart, curves, surfaces
from sensor_sim.scenario import Calibration, Curve, Scenario
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.reflectance import VARIANTS as ON_VARIANTS
from vgm_common.reflectance import oren_nayar

BACKGROUND_GREY = 20.0
CHART_BACK_ALBEDO = 0.3  # the unprinted back of the chart plate
MAX_SEGMENT_PX = 0.5  # longest projected curve segment drawn as a straight piece [px]
MAX_CURVE_SAMPLES = 400_000
DEPTH_TOLERANCE = (1e-3, 1e-3)  # (absolute [m], relative) slack of the curve depth test
_STENCIL_ELEMENTS = 2_000_000  # pixel candidates handled at once when drawing the curve

# ((u0, u1), (v0, v1)): pixel index ranges, ends excluded
PixelBox = tuple[tuple[int, int], tuple[int, int]]
# (x, y) of optical-frame rays (x, y, 1), any shape S -> (grey, depth [m]), each of shape S
ChartSampler = Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray]]
_Array = TypeVar('_Array', bound=np.ndarray)


# Standard normal quantiles at 65536 equiprobable levels: indexing it with uniform 16-bit
# integers draws Gaussian noise ~4x faster than rng.normal, which keeps three 640x480
# cameras at 30 Hz within one core. Its std is 1 to 1e-5; tails stop at 4.3 sigma.
_NORMAL_QUANTILES = ndtri((np.arange(65536) + 0.5) / 65536).astype(np.float32)


def add_noise(
    clean: npt.ArrayLike, sigma: float, rng: np.random.Generator
) -> npt.NDArray[np.uint8]:
    """Camera image from a clean render: clean + N(0, sigma^2), rounded, clipped.

    Args:
        clean: (H, W) float grey levels.
        sigma: noise standard deviation [grey levels] (0 gives the rounded clean image).
        rng: ``numpy.random.Generator``; the only source of randomness.

    Returns:
        (H, W) uint8.
    """
    noisy = _NORMAL_QUANTILES[rng.integers(0, 65536, size=np.shape(clean), dtype=np.uint16)]
    noisy *= sigma
    noisy += clean
    np.rint(noisy, out=noisy)
    np.clip(noisy, 0, 255, out=noisy)
    return noisy.astype(np.uint8)


@dataclass(frozen=True)
class _View:
    """What is cached per camera. Arrays are read-only."""

    normalized: FloatArray  # (H + 2, W + 2, 2) undistorted x/z, y/z at pixel centres -1..W
    hit_base: FloatArray  # (H, W, 3) [m], NaN where the ray misses
    depth: npt.NDArray[np.float32]  # (H, W) [m]
    image: FloatArray  # (H, W) grey levels, curve drawn


class SceneRenderer:
    """Renders a scenario's cameras; see the module docstring for the model.

    Args:
        scenario: a ``sensor_sim.scenario.Scenario``.
        variant: Oren-Nayar form, ``'oren_nayar'`` (default) or ``'thesis'``.
        supersample: chart images average supersample x supersample rays per pixel.

    Each camera is rendered on first use and cached; chart images are cached per
    (camera, pose). Returned arrays are read-only. The caches are not locked: use one
    renderer from one thread.
    """

    def __init__(
        self, scenario: Scenario, variant: str = 'oren_nayar', supersample: int = 4
    ) -> None:
        if variant not in ON_VARIANTS:
            raise InvalidInput(
                f'variant must be one of {ON_VARIANTS}, got {variant!r}',
                key='variant',
                value=variant,
            )
        if int(supersample) < 1:
            raise InvalidInput(
                f'supersample must be >= 1, got {supersample!r}',
                key='supersample',
                value=supersample,
            )
        self.scenario = scenario
        self.variant = variant
        self.supersample = int(supersample)
        self._views: dict[str, _View] = {}
        self._charts: dict[tuple[str, int], FloatArray] = {}
        self._curve_pieces: list[FloatArray] | None = None

    @property
    def camera_names(self) -> tuple[str, ...]:
        """Names of the scenario's cameras (``'left'``, ``'right'``, ``'aux'``)."""
        return tuple(self.scenario.cameras)

    def scene_image(self, name: str) -> FloatArray:
        """Clean image of camera ``name``: (H, W) float64 grey levels in [0, 255]."""
        return self._view(name).image

    def depth(self, name: str) -> npt.NDArray[np.float32]:
        """Depth map of camera ``name``: (H, W) float32 [m] along its optical axis, NaN
        where the pixel's ray misses the surface."""
        return self._view(name).depth

    def hit_points_base(self, name: str) -> FloatArray:
        """Surface point seen at each pixel centre of camera ``name``: (H, W, 3) base_link
        [m], NaN where the ray misses."""
        return self._view(name).hit_base

    def curve_polylines_base(self) -> list[FloatArray]:
        """The curve's pieces as drawn: list of (N_i, 3) base_link polylines [m] (closed
        pieces end with their first point), dense enough for every camera."""
        if self._curve_pieces is None:
            self._curve_pieces = _dense_curve(self.scenario)
        return self._curve_pieces

    def chart_image(self, name: str, pose_index: int) -> FloatArray:
        """Clean image of camera ``name`` with the calibration chart at stage pose
        ``pose_index`` in front of the scene: (H, W) float64 grey levels.

        The pose is ``scenario.calibration.T_base_chart[pose_index]`` (the chart frame of
        ``sensor_sim.chart`` in base_link). The plate is drawn where its ray hit is nearer
        than the surface, each pixel the mean of supersample^2 rays (cast only where the
        pixel can be mixed; elsewhere all of them would agree). Printed face: chart
        albedo times (intensity * max(0, n . light) + ambient); the unprinted back:
        ``CHART_BACK_ALBEDO`` likewise. ``depth(name)`` stays the surface's.

        Raises:
            InvalidInput: the scenario has no calibration, or ``pose_index`` is out of range.
        """
        calibration = _calibration(self.scenario)
        if not 0 <= pose_index < len(calibration.T_base_chart):
            raise InvalidInput(
                f'chart pose index {pose_index} out of range '
                f'0..{len(calibration.T_base_chart) - 1}',
                key='pose_index',
                value=pose_index,
            )
        key = (name, pose_index)
        if key not in self._charts:
            image = _render_chart(
                self.scenario,
                self._camera(name),
                self._view(name),
                calibration.T_base_chart[pose_index],
                self.supersample,
            )
            self._charts[key] = _read_only(image)
        return self._charts[key]

    def _camera(self, name: str) -> PinholeCamera:
        if name not in self.scenario.cameras:
            raise InvalidInput(
                f'unknown camera {name!r}; expected one of {self.camera_names}',
                key='camera',
                value=name,
            )
        return self.scenario.cameras[name]

    def _view(self, name: str) -> _View:
        camera = self._camera(name)
        if name not in self._views:
            self._views[name] = _render_view(
                self.scenario, camera, self.curve_polylines_base(), self.variant
            )
        return self._views[name]


def _calibration(scenario: Scenario) -> Calibration:
    """The scenario's calibration section; raises InvalidInput if it has none."""
    if scenario.calibration is None:
        raise InvalidInput('the scenario has no calibration section', key='calibration')
    return scenario.calibration


def _read_only(array: _Array) -> _Array:
    array.setflags(write=False)
    return array


def _render_view(
    scenario: Scenario, camera: PinholeCamera, curve_pieces: Sequence[FloatArray], variant: str
) -> _View:
    height, width = camera.height, camera.width
    # Undistorted normalised coordinates at pixel centres -1..W, -1..H: the inner part
    # gives the pixel rays, the border lets chart supersamples interpolate at the edges.
    u, v = np.meshgrid(np.arange(-1.0, width + 1), np.arange(-1.0, height + 1))
    normalized = camera.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]))
    normalized = normalized.reshape(height + 2, width + 2, 2)
    rays_camera = np.concatenate(
        [normalized[1:-1, 1:-1].reshape(-1, 2), np.ones((height * width, 1))], axis=1
    )
    # With rays of unit optical-axis component, the ray parameter t is the depth.
    directions_base = rays_camera @ camera.T_base_camera[:3, :3].T
    origin = camera.centre_base
    ray_depth = surfaces.intersect_rays(scenario.surface, origin, directions_base)  # (H * W,)
    hit_base = origin + ray_depth[:, None] * directions_base
    image: FloatArray = np.full(height * width, BACKGROUND_GREY)
    hit = np.isfinite(ray_depth)
    image[hit] = _shade_surface(scenario, hit_base[hit], origin, variant)
    image = image.reshape(height, width)
    depth = ray_depth.reshape(height, width).astype(np.float32)
    _draw_curve(image, depth, camera, curve_pieces, scenario.curve)
    return _View(
        normalized=_read_only(normalized),
        hit_base=_read_only(hit_base.reshape(height, width, 3)),
        depth=_read_only(depth),
        image=_read_only(image),
    )


def _shade_surface(
    scenario: Scenario, points_base: FloatArray, camera_centre: FloatArray, variant: str
) -> FloatArray:
    """Grey levels (N,) of surface points seen from ``camera_centre``."""
    surface, lighting = scenario.surface, scenario.lighting
    views = camera_centre - points_base
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    normals = surfaces.normal_base(surface, points_base)
    normals *= np.where(np.sum(normals * views, axis=1) < 0, -1.0, 1.0)[:, None]
    reflectance = oren_nayar(normals, lighting.direction_base, views, surface.roughness, variant)
    grey = 255.0 * surface.albedo * (lighting.intensity * reflectance + lighting.ambient)
    return np.clip(grey, 0.0, 255.0)


def _dense_curve(scenario: Scenario) -> list[FloatArray]:
    """Curve pieces sampled so that no projected segment exceeds MAX_SEGMENT_PX in any
    camera; analytic curves are re-sampled exactly, ``points`` curves are subdivided
    linearly (their polyline is the curve)."""
    curve, surface = scenario.curve, scenario.surface
    pieces = curves.curve_polylines(curve, surface)
    longest = max(
        _longest_projected_segment(camera, piece)
        for camera in scenario.cameras.values()
        for piece in pieces
    )
    if curve.kind != 'points' and longest > MAX_SEGMENT_PX:
        samples = min(
            int(np.ceil(curve.samples * 1.2 * longest / MAX_SEGMENT_PX)), MAX_CURVE_SAMPLES
        )
        pieces = curves.curve_polylines(curve, surface, samples=samples)
    for camera in scenario.cameras.values():
        pieces = [_subdivide(camera, piece) for piece in pieces]
    return [_read_only(piece) for piece in pieces]


def _longest_projected_segment(camera: PinholeCamera, points_base: FloatArray) -> float:
    pixels, _ = camera.project(points_base)
    lengths = np.linalg.norm(np.diff(pixels, axis=0), axis=1)
    lengths = lengths[np.isfinite(lengths)]
    return lengths.max() if len(lengths) else 0.0


def _subdivide(camera: PinholeCamera, points_base: FloatArray) -> FloatArray:
    """Split segments whose projection is longer than MAX_SEGMENT_PX, linearly in 3D."""
    pixels, _ = camera.project(points_base)
    lengths = np.linalg.norm(np.diff(pixels, axis=0), axis=1)
    parts = np.where(
        np.isfinite(lengths), np.ceil(np.nan_to_num(lengths) / MAX_SEGMENT_PX), 1
    ).astype(int)
    parts = np.clip(parts, 1, MAX_CURVE_SAMPLES // len(points_base) + 1)
    if np.all(parts == 1):
        return points_base
    segment = np.repeat(np.arange(len(parts)), parts)
    # Fraction along each segment: 0, 1/k, ..., (k-1)/k.
    fraction = (np.arange(len(segment)) - np.repeat(np.cumsum(parts) - parts, parts)) / np.repeat(
        parts, parts
    )
    start, end = points_base[segment], points_base[segment + 1]
    return np.vstack([start + fraction[:, None] * (end - start), points_base[-1:]])


def _draw_curve(
    image: FloatArray,
    depth: npt.NDArray[np.float32],
    camera: PinholeCamera,
    pieces: Sequence[FloatArray],
    curve: Curve,
) -> None:
    """Darken ``image`` (H, W) in place along the visible curve."""
    height, width = image.shape
    # Nothing in front where the ray missed: treat as infinitely far.
    far_depth = np.where(np.isfinite(depth), depth, np.inf)
    padded = np.pad(far_depth, 1, mode='edge')
    neighbourhood_max = np.max(
        [padded[dv : dv + height, du : du + width] for dv in range(3) for du in range(3)], axis=0
    )
    piece_starts, piece_ends = [], []
    for piece in pieces:
        pixels, point_depth = camera.project(piece)
        visible = np.isfinite(pixels).all(axis=1) & (point_depth > 0)
        col = np.clip(np.rint(np.nan_to_num(pixels[:, 0])), 0, width - 1).astype(int)
        row = np.clip(np.rint(np.nan_to_num(pixels[:, 1])), 0, height - 1).astype(int)
        in_image = (
            (pixels[:, 0] > -0.5)
            & (pixels[:, 0] < width - 0.5)
            & (pixels[:, 1] > -0.5)
            & (pixels[:, 1] < height - 0.5)
        )
        surface_depth = np.where(in_image, neighbourhood_max[row, col], np.inf)
        absolute, relative = DEPTH_TOLERANCE
        visible &= point_depth <= surface_depth + absolute + relative * point_depth
        # Segments still long after subdivision run off toward the camera plane (their
        # subdivision was capped); they are not drawn rather than drawn as straight lines.
        short = np.linalg.norm(np.diff(pixels, axis=0), axis=1) <= 4 * MAX_SEGMENT_PX
        drawn = visible[:-1] & visible[1:] & short
        piece_starts.append(pixels[:-1][drawn])
        piece_ends.append(pixels[1:][drawn])
    starts, ends = np.concatenate(piece_starts), np.concatenate(piece_ends)
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
        chunk_starts, chunk_ends = starts[first : first + chunk], ends[first : first + chunk]
        midpoints = np.rint((chunk_starts + chunk_ends) / 2).astype(int)
        cols = midpoints[:, :1] + du.ravel()
        rows = midpoints[:, 1:] + dv.ravel()
        distance = _point_segment_distance(cols, rows, chunk_starts, chunk_ends)
        inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
        np.minimum.at(nearest, (rows * width + cols)[inside], distance[inside])
    coverage = np.clip(half_width + 0.5 - nearest, 0.0, 1.0).reshape(height, width)
    image *= 1.0 - curve.contrast * coverage


def _point_segment_distance(
    cols: npt.NDArray[np.int_], rows: npt.NDArray[np.int_], starts: FloatArray, ends: FloatArray
) -> FloatArray:
    """Distance [px] of pixel centres (M, K) to the M segments starts -> ends (M, 2)."""
    direction = ends - starts
    length2 = np.sum(direction * direction, axis=1)
    px, py = cols - starts[:, :1], rows - starts[:, 1:]
    with np.errstate(divide='ignore', invalid='ignore'):
        s = (px * direction[:, :1] + py * direction[:, 1:]) / length2[:, None]
    s = np.clip(np.nan_to_num(s), 0.0, 1.0)  # a zero-length segment is its start point
    return np.hypot(px - s * direction[:, :1], py - s * direction[:, 1:])


def _render_chart(
    scenario: Scenario,
    camera: PinholeCamera,
    view: _View,
    T_base_chart: FloatArray,
    supersample: int,
) -> FloatArray:
    """Chart-over-scene image; see ``SceneRenderer.chart_image``.

    Only pixels that can be mixed are supersampled: a pixel that no edge of the print
    crosses and whose four corners see the same thing (the same print colour in front of
    the surface, or no chart) is uniform.
    """
    calibration = _calibration(scenario)
    rows, cols, spacing = calibration.rows, calibration.cols, calibration.spacing
    image = view.image.copy()
    box = _chart_pixel_box(camera, T_base_chart, rows, cols, spacing)
    if box is None:
        return image
    (u0, u1), (v0, v1) = box
    sample = _chart_sampler(scenario, camera, T_base_chart)
    scene_depth = view.depth[v0:v1, u0:u1].astype(float)
    scene_depth = np.where(np.isfinite(scene_depth), scene_depth, np.inf)
    scene_grey = image[v0:v1, u0:u1]

    # Pixel corners: midpoints of four pixel centres of the undistortion map (from -1).
    centres = view.normalized[v0 : v1 + 2, u0 : u1 + 2]
    corners = 0.25 * (centres[:-1, :-1] + centres[1:, :-1] + centres[:-1, 1:] + centres[1:, 1:])
    corner_grey, corner_depth = sample(corners[..., 0], corners[..., 1])
    height, width = scene_grey.shape
    shifts = [(slice(dr, dr + height), slice(dc, dc + width)) for dr in (0, 1) for dc in (0, 1)]
    covered = [corner_depth[shift] < scene_depth for shift in shifts]
    greys = [corner_grey[shift] for shift in shifts]
    all_covered = covered[0] & covered[1] & covered[2] & covered[3]
    none_covered = ~(covered[0] | covered[1] | covered[2] | covered[3])
    same_grey = (greys[0] == greys[1]) & (greys[0] == greys[2]) & (greys[0] == greys[3])
    mixed = ~((all_covered & same_grey) | none_covered)
    mixed |= _pixels_on_print_edges(camera, T_base_chart, rows, cols, spacing, box)
    if calibration.pattern == 'charuco':
        # A marker's bit edge may pass between a pixel's corners without changing their
        # colour (the squares' edges are drawn above; the bits are not).
        mixed |= cv2.dilate(mixed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)

    block = np.where(all_covered, greys[0], scene_grey)
    r, c = np.nonzero(mixed)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = np.meshgrid(offsets, offsets)
    u = (u0 + c)[:, None] + du.ravel()
    v = (v0 + r)[:, None] + dv.ravel()
    x, y = _interpolate_normalized(view.normalized, u.ravel(), v.ravel())
    grey, depth = sample(x.reshape(u.shape), y.reshape(u.shape))
    in_front = depth < scene_depth[r, c][:, None]
    block[r, c] = np.where(in_front, grey, scene_grey[r, c][:, None]).mean(axis=1)
    image[v0:v1, u0:u1] = block
    return image


def _chart_sampler(
    scenario: Scenario, camera: PinholeCamera, T_base_chart: FloatArray
) -> ChartSampler:
    """A function (x, y) -> (grey, depth) for rays (x, y, 1) of ``camera``'s optical
    frame: the chart's grey level where the ray meets the plate, and the hit's depth [m]
    (+inf off the plate or behind the camera)."""
    calibration, lighting = _calibration(scenario), scenario.lighting
    print_albedo = chart.print_albedo(
        calibration.pattern,
        calibration.rows,
        calibration.cols,
        calibration.spacing,
        calibration.marker_size,
        calibration.dictionary,
    )
    T_camera_chart = camera.T_camera_base @ T_base_chart
    R, origin = T_camera_chart[:3, :3], T_camera_chart[:3, 3]
    normal = R[:, 2]
    printed = normal @ origin > 0  # the camera is on the chart's -z side
    face_normal_base = T_base_chart[:3, 2] * (-1.0 if printed else 1.0)
    irradiance = (
        lighting.intensity * max(0.0, face_normal_base @ lighting.direction_base)
        + lighting.ambient
    )

    def sample(x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        # Plate plane n . p = n . origin; with rays (x, y, 1) the ray parameter is depth.
        with np.errstate(divide='ignore', invalid='ignore'):
            depth = (normal @ origin) / (normal[0] * x + normal[1] * y + normal[2])
        # Chart-frame coordinates of the hit: R^T (depth * ray - origin).
        chart_x = depth * (R[0, 0] * x + R[1, 0] * y + R[2, 0]) - R[:, 0] @ origin
        chart_y = depth * (R[0, 1] * x + R[1, 1] * y + R[2, 1]) - R[:, 1] @ origin
        albedo = print_albedo(np.column_stack([chart_x.ravel(), chart_y.ravel()])).reshape(x.shape)
        on_plate = np.isfinite(albedo) & (depth > 0)
        if not printed:
            albedo = np.full(x.shape, CHART_BACK_ALBEDO)
        grey = np.where(on_plate, np.clip(255.0 * albedo * irradiance, 0.0, 255.0), 0.0)
        return grey, np.where(on_plate, depth, np.inf)

    return sample


def _pixels_on_print_edges(
    camera: PinholeCamera,
    T_base_chart: FloatArray,
    rows: int,
    cols: int,
    spacing: float,
    box: PixelBox,
) -> npt.NDArray[np.bool_]:
    """Boolean mask of ``box``: pixels within one pixel of the projection of an edge of the
    print (square sides, plate outline), sampled every half pixel."""
    (u0, u1), (v0, v1) = box
    (x0, x1), (y0, y1) = chart.chart_plate_extent(rows, cols, spacing)
    lines = (
        [((i * spacing, y0), (i * spacing, y1)) for i in range(-1, cols + 1)]
        + [((x0, j * spacing), (x1, j * spacing)) for j in range(-1, rows + 1)]
        + [((x0, y0), (x1, y0)), ((x0, y1), (x1, y1)), ((x0, y0), (x0, y1)), ((x1, y0), (x1, y1))]
    )
    mask = np.zeros((v1 - v0, u1 - u0), bool)
    for start, end in lines:
        ends_base = _chart_to_base(T_base_chart, np.array([start, end]))
        ends_px, _ = camera.project(ends_base)
        length = np.linalg.norm(ends_px[1] - ends_px[0])
        # A line reaching behind the camera has no finite length: sample it finely.
        count = int(np.ceil(length / 0.5)) + 2 if np.isfinite(length) else 4000
        s = np.linspace(0.0, 1.0, min(count, 20000))[:, None]
        pixels, depth = camera.project(
            _chart_to_base(T_base_chart, (1 - s) * np.array(start) + s * np.array(end))
        )
        pixels = pixels[depth > 0]
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                col = np.rint(pixels[:, 0]).astype(int) + dc - u0
                row = np.rint(pixels[:, 1]).astype(int) + dr - v0
                inside = (col >= 0) & (col < u1 - u0) & (row >= 0) & (row < v1 - v0)
                mask[row[inside], col[inside]] = True
    return mask


def _chart_to_base(T_base_chart: FloatArray, xy_chart: FloatArray) -> FloatArray:
    """(N, 2) points of the chart plane [m] -> (N, 3) base_link points."""
    return xy_chart @ T_base_chart[:3, :2].T + T_base_chart[:3, 3]


def _chart_pixel_box(
    camera: PinholeCamera, T_base_chart: FloatArray, rows: int, cols: int, spacing: float
) -> PixelBox | None:
    """((u0, u1), (v0, v1)) pixel index ranges holding the plate's image, the whole image
    if the plate reaches behind the camera, None if it is entirely behind or outside."""
    (x0, x1), (y0, y1) = chart.chart_plate_extent(rows, cols, spacing)
    s = np.linspace(0.0, 1.0, 65)
    outline = np.concatenate(
        [
            np.column_stack([x0 + s * (x1 - x0), np.full_like(s, y0)]),
            np.column_stack([x0 + s * (x1 - x0), np.full_like(s, y1)]),
            np.column_stack([np.full_like(s, x0), y0 + s * (y1 - y0)]),
            np.column_stack([np.full_like(s, x1), y0 + s * (y1 - y0)]),
        ]
    )
    pixels, depth = camera.project(_chart_to_base(T_base_chart, outline))
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


def _interpolate_normalized(
    normalized: FloatArray, u: FloatArray, v: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Undistorted coordinates (x (N,), y (N,)) at pixel positions (u, v) (N,), by
    bilinear interpolation of the map of pixel centres -1..W, -1..H.

    The map is smooth, so the error is about 0.1 * |k1| * r / fx pixels (~1e-4 px for
    modest distortion), far below what the chart's antialiasing resolves.
    """
    gu, gv = u + 1.0, v + 1.0
    rows, cols = normalized.shape[:2]
    i = np.clip(np.floor(gu).astype(int), 0, cols - 2)
    j = np.clip(np.floor(gv).astype(int), 0, rows - 2)
    fu, fv = gu - i, gv - j
    flat = j * cols + i

    def interpolate(channel: int) -> FloatArray:
        values = np.ascontiguousarray(normalized[..., channel]).ravel()
        top = values.take(flat) * (1 - fu) + values.take(flat + 1) * fu
        bottom = values.take(flat + cols) * (1 - fu) + values.take(flat + cols + 1) * fu
        return top * (1 - fv) + bottom * fv

    return interpolate(0), interpolate(1)
