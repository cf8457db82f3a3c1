"""Generated curve/rig draws for curve_recon_node's bench and tests: curve
families in any orientation, seen by generated three-camera rigs, drawn with generated
line widths, contrasts and noise. Seeded: ``generate_case(family, seed)`` is the same
draw every time.

Families (each ``FAMILIES[name](rng, size)`` returns (points (N, 3) in a local frame
centred near 0 [m], closed)):

- planar conics: ``ellipse``, ``parabola``, ``hyperbola`` (one branch);
- planar cubics: ``planar_cubic`` (y = a x^3 + b x^2 + c x, with an inflection);
- space curves: ``helix``, ``twisted_cubic`` (t, t^2, t^3), ``torus_knot`` (2, 3),
  ``sphere_loop`` (a wavy closed loop on a sphere), ``saddle_loop`` (a closed loop on
  z = k (x^2 - y^2)), ``inflection`` (a planar S with an out-of-plane sway),
  ``near_straight`` (two straight stretches joined by a bend), ``self_approaching`` (a
  closed loop with a narrow waist, where the curve passes near itself);
- ``surface_loop``: a loop drawn *on* the default scene's S3 surface (every other family
  floats in front of a plane backdrop, off any surface).

The rig (``generate_rig``): left and right cameras with focal lengths 400-1400 px,
plumb_bob k1 in [-0.4, 0.1], a baseline of 0.04-0.3 m (at most half the viewing
distance), toed in on the curve; the aux camera oblique, 20-45 deg off the left view and
off the baseline's line. Every curve point is inside every image with a margin.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from sensor_sim.curves import curve_polylines
from sensor_sim.scenario import (
    Curve,
    CurveParameter,
    Noise,
    Scenario,
    Surface,
    load_scenario,
    resolve_scenario_path,
)
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray, look_at_rotation, make_transform

WIDTH, HEIGHT = 640, 480
IMAGE_MARGIN_PX = 25  # every curve point at least this far inside every image
SAMPLES = 4000  # points of the true curve (the renderer subdivides further)

# A family: (rng, size [m]) -> (points (N, 3) [m] in a local frame, closed)
Family = Callable[[np.random.Generator, float], tuple[FloatArray, bool]]


def _ellipse(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    t = np.linspace(0, 2 * np.pi, SAMPLES, endpoint=False)
    a, b = 0.5 * size, 0.5 * size * rng.uniform(0.45, 0.95)
    return np.column_stack([a * np.cos(t), b * np.sin(t), 0 * t]), True


def _parabola(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    x = np.linspace(-0.5, 0.5, SAMPLES) * size
    k = rng.uniform(1.0, 3.0) / size
    return np.column_stack([x, k * x**2 - k * size**2 / 12, 0 * x]), False


def _hyperbola(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    t = np.linspace(-1.0, 1.0, SAMPLES) * rng.uniform(1.0, 1.6)
    a = 0.25 * size * rng.uniform(0.5, 1.0)
    b = 0.5 * size / np.sinh(np.abs(t).max())
    points = np.column_stack([a * np.cosh(t), b * np.sinh(t), 0 * t])
    return points - points.mean(axis=0), False


def _planar_cubic(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    x = np.linspace(-1, 1, SAMPLES)
    a, b = rng.uniform(0.6, 1.2) * rng.choice([-1, 1]), rng.uniform(-0.4, 0.4)
    y = a * x**3 + b * x**2 - 0.6 * a * x
    y = y / max(np.ptp(y), 1e-9) * 0.5
    return np.column_stack([0.5 * x, y, 0 * x]) * size, False


def _helix(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    turns = rng.uniform(0.6, 1.0)  # more turns cross themselves in every view
    t = np.linspace(0, 2 * np.pi * turns, SAMPLES)
    r, pitch = 0.3 * size, size / (2 * np.pi * turns)
    z = pitch * t
    return np.column_stack([r * np.cos(t), r * np.sin(t), z - z.mean()]), False


def _twisted_cubic(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    t = np.linspace(-1, 1, SAMPLES)
    c = rng.uniform(0.6, 1.0, 3)
    points = np.column_stack([c[0] * t, c[1] * t**2, c[2] * t**3]) * 0.5 * size
    return points - points.mean(axis=0), False


def _torus_knot(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    t = np.linspace(0, 2 * np.pi, SAMPLES, endpoint=False)
    p, q = 2, 3
    R, r = 0.3 * size, 0.12 * size * rng.uniform(0.8, 1.2)
    rho = R + r * np.cos(q * t)
    return np.column_stack([rho * np.cos(p * t), rho * np.sin(p * t), r * np.sin(q * t)]), True


def _sphere_loop(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    t = np.linspace(0, 2 * np.pi, SAMPLES, endpoint=False)
    radius = 0.5 * size
    lobes = int(rng.integers(2, 4))
    latitude = rng.uniform(0.25, 0.5) * np.sin(lobes * t) + rng.uniform(-0.2, 0.2)
    points = radius * np.column_stack(
        [np.cos(latitude) * np.cos(t), np.cos(latitude) * np.sin(t), np.sin(latitude)]
    )
    return points - points.mean(axis=0), True


def _saddle_loop(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    t = np.linspace(0, 2 * np.pi, SAMPLES, endpoint=False)
    r = 0.45 * size
    k = rng.uniform(0.8, 1.6) / size
    x, y = r * np.cos(t), r * rng.uniform(0.6, 1.0) * np.sin(t)
    return np.column_stack([x, y, k * (x**2 - y**2)]), True


def _inflection(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    s = np.linspace(-1, 1, SAMPLES)
    sway = rng.uniform(0.1, 0.25)
    return np.column_stack([0.5 * s, 0.2 * np.sin(np.pi * s), sway * (s**2 - 1 / 3)]) * size, False


def _near_straight(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    """Straight, a bend of a quarter to half a turn, straight again."""
    bend = rng.uniform(0.5, 1.5)  # [rad]
    radius = 0.15 * size
    straight = 0.35 * size
    n = SAMPLES // 3
    first = np.column_stack([np.linspace(-straight, 0, n, endpoint=False), np.zeros(n)])
    a = np.linspace(0, bend, n, endpoint=False)
    arc = np.column_stack([radius * np.sin(a), radius * (1 - np.cos(a))])
    end = arc[-1] if len(arc) else np.zeros(2)
    direction = np.array([np.cos(bend), np.sin(bend)])
    last = end + np.linspace(0, straight, SAMPLES - 2 * n)[:, None] * direction
    xy = np.vstack([first, arc, last])
    lift = rng.uniform(-0.1, 0.1) * size * np.linspace(0, 1, len(xy)) ** 2
    points = np.column_stack([xy, lift])
    return points - points.mean(axis=0), False


def _self_approaching(rng: np.random.Generator, size: float) -> tuple[FloatArray, bool]:
    """A closed loop pinched at the middle: its two halves pass within ~a fifth of the
    size of each other."""
    t = np.linspace(0, 2 * np.pi, SAMPLES, endpoint=False)
    waist = rng.uniform(0.15, 0.25)
    r = 0.5 * size * (waist + (1 - waist) * np.cos(t) ** 2)
    points = np.column_stack([r * np.cos(t) * 1.4, r * np.sin(t), 0.08 * size * np.sin(2 * t)])
    return points, True


FAMILIES: dict[str, Family | None] = {
    'ellipse': _ellipse,
    'parabola': _parabola,
    'hyperbola': _hyperbola,
    'planar_cubic': _planar_cubic,
    'helix': _helix,
    'twisted_cubic': _twisted_cubic,
    'torus_knot': _torus_knot,
    'sphere_loop': _sphere_loop,
    'saddle_loop': _saddle_loop,
    'inflection': _inflection,
    'near_straight': _near_straight,
    'self_approaching': _self_approaching,
    'surface_loop': None,
}
PLANAR = ('ellipse', 'parabola', 'hyperbola', 'planar_cubic')
# the implicit degree the node is told, as a user would set `degree`
DEGREE = {'ellipse': 2, 'parabola': 2, 'hyperbola': 2, 'planar_cubic': 3}


@dataclass(frozen=True)
class CurveCase:
    """One generated draw: ``scenario`` (cameras, curve, backdrop, noise) renders with
    ``sensor_sim.render.SceneRenderer``; ``truth_base`` (N, 3) [m] is the true curve
    (closed curves not repeated), ``closed``; ``degree`` is the node's `degree`
    parameter for it; ``line_width_px``, ``contrast_grey`` and ``noise_grey`` as drawn."""

    family: str
    seed: int
    scenario: Scenario
    truth_base: FloatArray
    closed: bool
    degree: int
    line_width_px: float
    contrast_grey: float
    noise_grey: float
    size_m: float


def random_rotation(rng: np.random.Generator) -> FloatArray:
    """A uniformly random rotation matrix (3, 3)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _camera(
    rng: np.random.Generator, position: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike
) -> PinholeCamera:
    f = rng.uniform(400.0, 1400.0)
    K = np.array(
        [
            [f, 0, WIDTH / 2 + rng.uniform(-8, 8)],
            [0, f * rng.uniform(0.995, 1.005), HEIGHT / 2 + rng.uniform(-8, 8)],
            [0, 0, 1],
        ]
    )
    k1 = rng.uniform(-0.4, 0.1)
    D = np.array([k1, -0.2 * k1 * rng.uniform(0, 1), 0.0, 0.0, 0.0])
    T = make_transform(look_at_rotation(position, target, up), position)
    return PinholeCamera(WIDTH, HEIGHT, K, D, T)


def generate_rig(
    rng: np.random.Generator,
    points_base: FloatArray,
    closed: bool,
    min_gap_px: float | None = None,
    fill: tuple[float, float] = (0.45, 0.7),
    tries: int = 300,
) -> dict[str, PinholeCamera]:
    """Three cameras {'left', 'right', 'aux'} seeing ``points_base`` (N, 3) from above,
    each filling ``fill`` of its image's width with the curve, every point inside every
    image by IMAGE_MARGIN_PX, and, given ``min_gap_px``, the curve's image nowhere
    nearer than that to another part of itself (no crossing: a knot has crossings in
    every view, so it is drawn without). Drawn again until so; raises InvalidInput after
    ``tries``.
    """
    centre = 0.5 * (points_base.min(axis=0) + points_base.max(axis=0))
    size = float(np.linalg.norm(np.ptp(points_base, axis=0)))
    for _ in range(tries):
        elevation = rng.uniform(np.radians(45), np.radians(80))
        azimuth = rng.uniform(-np.pi, np.pi)
        view = np.array(
            [
                np.cos(elevation) * np.cos(azimuth),
                np.cos(elevation) * np.sin(azimuth),
                np.sin(elevation),
            ]
        )
        left_probe = _camera(rng, centre + view, centre, (0, 0, 1))
        f_left = left_probe.K[0, 0]
        distance = f_left * size / (rng.uniform(*fill) * WIDTH)
        left_position = centre + distance * view
        x_left = left_probe.T_base_camera[:3, 0]
        baseline = rng.uniform(0.04, min(0.3, 0.5 * distance)) if distance > 0.08 else 0.04
        aim = centre + rng.normal(scale=0.03 * size, size=3)
        left = replace(
            left_probe,
            T_base_camera=make_transform(
                look_at_rotation(left_position, aim, (0, 0, 1)), left_position
            ),
        )
        right_position = left_position + baseline * x_left
        right = _camera(rng, right_position, aim, (0, 0, 1))
        right = replace(right, K=_scaled_focal(right.K, f_left * rng.uniform(0.9, 1.1)))
        # aux: 20-45 deg off the left view, turned away from the baseline's line
        off = np.radians(rng.uniform(20, 45))
        y_left = left_probe.T_base_camera[:3, 1]
        side = np.cos(rng.uniform(-0.6, 0.6)) * y_left * rng.choice([-1, 1]) + 0.3 * x_left
        side /= np.linalg.norm(side)
        aux_view = np.cos(off) * view + np.sin(off) * side
        aux_view /= np.linalg.norm(aux_view)
        aux_probe = _camera(rng, centre + aux_view, centre, (0, 0, 1))
        aux_distance = aux_probe.K[0, 0] * size / (rng.uniform(*fill) * WIDTH)
        aux = replace(
            aux_probe,
            T_base_camera=make_transform(
                look_at_rotation(centre + aux_distance * aux_view, centre, (0, 0, 1)),
                centre + aux_distance * aux_view,
            ),
        )
        cameras = {'left': left, 'right': right, 'aux': aux}
        if all(_inside(camera, points_base) for camera in cameras.values()) and (
            min_gap_px is None
            or all(
                _simple_in_image(camera, points_base, closed, min_gap_px)
                for camera in cameras.values()
            )
        ):
            return cameras
    raise InvalidInput(f'no rig within {tries} draws sees the whole curve', key='rig')


def _scaled_focal(K: npt.ArrayLike, f: float) -> FloatArray:
    K = np.array(K, dtype=float)
    ratio = K[1, 1] / K[0, 0]
    K[0, 0], K[1, 1] = f, f * ratio
    return K


def _inside(camera: PinholeCamera, points_base: FloatArray) -> bool:
    pixels, depth = camera.project(points_base)
    if not np.all(depth > 0) or not np.all(np.isfinite(pixels)):
        return False
    m = IMAGE_MARGIN_PX
    return bool(
        np.all(
            (pixels[:, 0] > m)
            & (pixels[:, 0] < camera.width - m)
            & (pixels[:, 1] > m)
            & (pixels[:, 1] < camera.height - m)
        )
    )


def _simple_in_image(
    camera: PinholeCamera, points_base: FloatArray, closed: bool, min_gap_px: float
) -> bool:
    """True unless two parts of the projected curve more than 4 ``min_gap_px`` apart
    along it come within ``min_gap_px`` of each other."""
    pixels, _ = camera.project(points_base)
    steps = np.linalg.norm(np.diff(pixels, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    keep = np.searchsorted(arc, np.arange(0.0, arc[-1], 0.5 * min_gap_px))
    pixels, arc = pixels[keep], arc[keep]
    pairs = cKDTree(pixels).query_pairs(min_gap_px, output_type='ndarray')
    if not len(pairs):
        return True
    along = np.abs(arc[pairs[:, 0]] - arc[pairs[:, 1]])
    if closed:
        along = np.minimum(along, arc[-1] - along)
    return not np.any(along > 4 * min_gap_px)


def generate_case(
    family: str,
    seed: int,
    noise_grey: float | None = None,
    line_width_px: float | None = None,
    contrast_grey: float | None = None,
) -> CurveCase:
    """The draw ``seed`` of ``family`` (see FAMILIES): curve, rig, backdrop, line width
    (1.5-5 px), contrast (10-80 grey levels) and image noise (0-4 grey levels); give
    ``noise_grey`` / ``line_width_px`` / ``contrast_grey`` to fix one."""
    if family not in FAMILIES:
        raise InvalidInput(
            f'family: expected one of {", ".join(FAMILIES)}, got {family!r}',
            key='family',
            value=family,
        )
    rng = np.random.default_rng([seed, sorted(FAMILIES).index(family)])
    base = load_scenario(resolve_scenario_path('default'))
    # always drawn, so fixing one leaves the rest of the draw as it is
    width, contrast, noise = (
        rng.uniform(1.5, 5.0),
        rng.uniform(10.0, 80.0),
        rng.uniform(0.0, 4.0),
    )
    width = width if line_width_px is None else float(line_width_px)
    contrast = contrast if contrast_grey is None else float(contrast_grey)
    noise = noise if noise_grey is None else float(noise_grey)
    surface: Surface | None  # None: a backdrop, placed once the rig is drawn
    draw = FAMILIES[family]
    if draw is None:  # 'surface_loop'
        params: dict[str, CurveParameter] = {
            'center': rng.uniform(-0.08, 0.08, 2),
            'radii': np.array([rng.uniform(0.2, 0.34), rng.uniform(0.12, 0.22)]),
            'angle': rng.uniform(-np.pi, np.pi),
        }
        curve = Curve('surface_loop', width, 1.0, SAMPLES, params)
        truth = curve_polylines(curve, base.surface)[0][:-1]
        surface, closed = base.surface, True
    else:
        size = rng.uniform(0.1, 0.25)  # [m] across
        local, closed = draw(rng, size)
        centre = np.array([0.6, 0.0, 0.3]) + rng.uniform(-0.05, 0.05, 3)
        truth = centre + local @ random_rotation(rng).T
        curve = Curve('points', width, 1.0, len(truth), {'points': truth, 'closed': closed})
        surface = None
    # the gap the image curve keeps to itself: two line widths and the blur around them
    min_gap = None if family == 'torus_knot' else 2 * width + 4
    cameras = generate_rig(rng, truth, closed, min_gap)
    if surface is None:
        surface = _backdrop(truth, cameras['left'], rng)
    albedo = surface.albedo
    # contrast as a fraction of the local brightness, from the grey levels asked for
    # (the surface reads about 255 albedo (0.6 + ambient) where the curve is)
    fraction = float(np.clip(contrast / (255.0 * albedo * 0.65), 0.02, 0.95))
    curve = replace(curve, line_width_px=width, contrast=fraction)
    scenario = replace(
        base,
        name=f'{family}_{seed}',
        curve=curve,
        cameras=cameras,
        surface=surface,
        noise=Noise(noise, base.noise.pressure_sigma),
        seed=int(seed),
        calibration=None,
    )
    size_m = float(np.linalg.norm(np.ptp(truth, axis=0)))
    return CurveCase(
        family,
        int(seed),
        scenario,
        truth,
        closed,
        DEGREE.get(family, 3 if family != 'surface_loop' else 2),
        width,
        contrast,
        noise,
        size_m,
    )


def _backdrop(points_base: FloatArray, camera: PinholeCamera, rng: np.random.Generator) -> Surface:
    """A plane behind the curve, facing the camera, wide enough for every view."""
    centre = points_base.mean(axis=0)
    toward_camera = camera.centre_base - centre
    distance = np.linalg.norm(toward_camera)
    normal = toward_camera / distance
    reach = np.max(np.linalg.norm(points_base - centre, axis=1))
    origin = centre - (reach + 0.03) * normal
    # the plane's z axis is its normal; tilt it a little so shading varies
    tilt = random_rotation(rng)
    z = normal + 0.2 * tilt[:, 0]
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    scale = 1.0
    half = 4 * distance + 1.0
    return Surface(
        'plane',
        make_transform(R, origin),
        scale,
        ((-half, half), (-half, half)),
        albedo=rng.uniform(0.55, 0.9),
        roughness=rng.uniform(0.0, 0.3),
    )
