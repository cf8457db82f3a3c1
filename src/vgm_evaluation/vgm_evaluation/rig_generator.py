"""Random camera rigs and chessboard images rendered through their true cameras, for the
bench and the tests: focal lengths, image sizes, radial distortion, baselines,
vergence, an oblique aux camera with its own lens, chart poses and image noise are drawn
from a seeded generator. No rclpy.

The chart is the one of INTERFACES.md ("The calibration chart", ``sensor_sim.chart``):
``rows`` x ``cols`` inner corners, a white margin, corner (0, 0) at the black end.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from calib_node.chart_detection import chart_points
from calib_node.uncertainty import GRID, image_grid, points_at_range
from vgm_common.camera_model import PinholeCamera, distort
from vgm_common.geometry import (
    FloatArray,
    invert_transform,
    look_at_rotation,
    make_transform,
    rot_x,
    rot_y,
    rot_z,
)

BACKGROUND_GREY = 70.0  # a dark wall behind the chart [grey level]
BLACK_GREY, WHITE_GREY = 15.0, 230.0  # the print under the light [grey level]
CHARTS = ((6, 9, 0.025), (5, 8, 0.03), (7, 10, 0.02), (6, 7, 0.035), (8, 11, 0.018))

GreyImage = npt.NDArray[np.uint8]
Lens = tuple[FloatArray, FloatArray, tuple[int, int]]  # K (3, 3), D, (width, height)
LENS_MODELS = ('plumb_bob', 'rational_polynomial', 'equidistant')
# vgm_common.calibration_io.stereo_rectification: (left, right) -> {name: (R, P)}
Rectification = Callable[
    [PinholeCamera, PinholeCamera], Mapping[str, tuple[np.ndarray, np.ndarray]]
]


class Rig(NamedTuple):
    """A drawn rig (:func:`draw_rig`): the true cameras, the chart pose of every view, the
    chart, the image noise and the drawn parameters."""

    cameras: dict[str, PinholeCamera]  # the truth, poses in base_link
    T_base_chart: list[FloatArray]  # (4, 4) chart frame in base_link, one per view
    rows: int
    cols: int
    spacing: float  # [m]
    noise: float  # image noise sigma [grey levels]
    params: dict[str, int | float | str]  # what was drawn (for the bench's tables)
    pattern: str = 'chessboard'  # or 'charuco' (DICT_5X5_100, markers 0.75 spacing)


def _lens(
    rng: np.random.Generator,
    width: int,
    focal_range: tuple[float, float] = (400.0, 1400.0),
    k1_range: tuple[float, float] = (-0.4, 0.1),
) -> Lens:
    """K and plumb_bob D of a lens: square pixels up to 0.5 % aspect, principal point
    within 4 % of the centre, k1 drawn, k2 of the opposite sign as real lenses have."""
    f = rng.uniform(*focal_range) * width / 1280 * rng.uniform(1.0, 1.4)
    f = float(np.clip(f, *focal_range))
    height = int(width * 3 / 4)
    K = np.array(
        [
            [f, 0, width / 2 + rng.uniform(-0.04, 0.04) * width],
            [0, f * rng.uniform(0.995, 1.005), height / 2 + rng.uniform(-0.04, 0.04) * height],
            [0, 0, 1.0],
        ]
    )
    k1 = rng.uniform(*k1_range)
    D = np.array([k1, -0.4 * k1 * rng.uniform(0.0, 1.0), 0.0, 0.0, 0.0])
    return K, D, (width, height)


def _wide_lens(rng: np.random.Generator, width: int, model: str) -> Lens:
    """K and D of a wide lens of ``model``, square pixels up to 0.5 %, principal point
    within 3 % of the centre. rational_polynomial: f 0.4..0.55 width (a 85-100 deg
    horizontal field), barrel k1 in [0.2, 1], k4 = k1 + 0.3..0.8 (the denominator wins
    at the edge, as OpenCV fits of such lenses have), k2, k5 in [0, 0.1], k3 = k6 = 0,
    decentred (p1, p2 in [-0.002, 0.002]; radially symmetric, such a lens is as well
    described by the four coefficients of an equidistant one over the image), drawn
    again until it maps the whole image one to one.
    equidistant: f 0.28..0.38 width (135-160 deg horizontally), k1 in [-0.05, 0.05],
    k2 in [-0.01, 0.01], k3 = k4 = 0 (cv2.fisheye's fits of real fisheyes)."""
    height = int(width * 3 / 4)
    share = (0.4, 0.55) if model == 'rational_polynomial' else (0.28, 0.38)
    f = rng.uniform(*share) * width
    K = np.array(
        [
            [f, 0, width / 2 + rng.uniform(-0.03, 0.03) * width],
            [0, f * rng.uniform(0.995, 1.005), height / 2 + rng.uniform(-0.03, 0.03) * height],
            [0, 0, 1.0],
        ]
    )
    if model == 'rational_polynomial':
        # Drawn again until the lens maps the whole image one to one: its radius grows
        # until it reaches the image corner, within 76 deg of the axis (r_u <= 4); some
        # draws fold first and would leave the image corners without a ray.
        corner = np.hypot(*(np.maximum(K[:2, 2], [width, height] - K[:2, 2]) / np.diag(K)[:2]))
        r_u = np.linspace(0.0, 4.0, 4001)
        while True:
            k1, k2 = rng.uniform(0.2, 1.0), rng.uniform(0.0, 0.1)
            p1, p2 = rng.uniform(-2e-3, 2e-3, 2)
            k4, k5 = k1 + rng.uniform(0.3, 0.8), rng.uniform(0.0, 0.1)
            D = np.array([k1, k2, p1, p2, 0, k4, k5, 0])
            r2 = r_u**2
            r_d = r_u * (1 + r2 * (k1 + r2 * k2)) / (1 + r2 * (k4 + r2 * k5))
            reached = np.flatnonzero(r_d >= corner)
            if len(reached) and np.all(np.diff(r_d[: reached[0] + 1]) > 0):
                break
    else:
        D = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.01, 0.01), 0.0, 0.0])
    return K, D, (width, height)


def board_in_view(
    camera: PinholeCamera,
    corners_base: FloatArray,
    margin_px: float = 8.0,
    max_angle_deg: float = 65.0,
    T_base_chart: FloatArray | None = None,
) -> bool:
    """Whether the whole board (corners padded by one square) is inside the image with
    ``margin_px``, in front of the camera, seen from the printed side at most
    ``max_angle_deg`` from its normal."""
    pixels, depth = camera.project(corners_base)
    if np.any(depth <= 0) or not np.all(np.isfinite(pixels)):
        return False
    inside = (
        (pixels[:, 0] > margin_px)
        & (pixels[:, 0] < camera.width - 1 - margin_px)
        & (pixels[:, 1] > margin_px)
        & (pixels[:, 1] < camera.height - 1 - margin_px)
    )
    if not np.all(inside):
        return False
    if T_base_chart is not None:
        to_chart = T_base_chart[:3, 3] - camera.centre_base
        cos = T_base_chart[:3, 2] @ to_chart / np.linalg.norm(to_chart)
        if cos < np.cos(np.radians(max_angle_deg)):  # chart z points away from the camera
            return False
    return True


def _outline_points(rows: int, cols: int, spacing: float) -> FloatArray:
    """The board's outer squares' corners (padded by one square) in the chart frame."""
    xs = np.array([-spacing, cols * spacing])
    ys = np.array([-spacing, rows * spacing])
    grid = np.array(
        [(x, y, 0.0) for x in np.linspace(xs[0], xs[1], 5) for y in np.linspace(ys[0], ys[1], 5)]
    )
    return grid


def draw_rig(
    seed: int,
    cameras: Sequence[str] = ('left', 'right', 'aux'),
    views: int | None = None,
    noise: float | None = None,
    lens_model: str = 'plumb_bob',
) -> Rig:
    """A random rig and chart poses (the ranges above), from an integer ``seed``.

    Left: width 640..1280 (4:3), f 400..1400 px, k1 in [-0.4, 0.1], k2 = -0.4 k1 * U(0, 1).
    Right: its own lens of the same size, baseline 0.04..0.3 m along left x, both toed in
    by half the vergence 0..10 deg. Aux (if asked): its own size and lens, looking at the
    fixation point from 0..45 deg off the pair's axis. The chart (one of ``CHARTS``)
    fills about half the narrowest view at the working distance; ``views`` (8..20) poses
    with the whole board inside every image, tilted up to 40 deg. The rig sits at a random
    pose in base_link. ``lens_model`` other than plumb_bob (``LENS_MODELS``): every lens
    a wide one of that model (:func:`_wide_lens`), the rest drawn alike.

    Returns:
        :class:`Rig`.
    """
    rng = np.random.default_rng(seed)
    rows, cols, spacing = CHARTS[rng.integers(len(CHARTS))]
    views = int(rng.integers(8, 21)) if views is None else int(views)
    noise = float(rng.uniform(0.0, 3.0)) if noise is None else float(noise)
    width = int(rng.choice([640, 800, 960, 1024, 1280]))
    baseline = float(rng.uniform(0.04, 0.3))
    vergence = float(np.radians(rng.uniform(0.0, 10.0)))
    if lens_model not in LENS_MODELS:
        raise ValueError(f'lens_model: expected one of {LENS_MODELS}, got {lens_model!r}')

    def lens(width: int) -> Lens:
        return (
            _lens(rng, width) if lens_model == 'plumb_bob' else _wide_lens(rng, width, lens_model)
        )

    lenses = {'left': lens(width), 'right': lens(width)}
    if 'aux' in cameras:
        lenses['aux'] = lens(int(rng.choice([640, 800, 960, 1024, 1280])))
    board = np.array([(cols + 1) * spacing, (rows + 1) * spacing])
    # Working distance: the board about half as wide as the narrowest field of view, far
    # enough that the pair's fields overlap there (vergence or not).
    fov = min(lens[2][0] / lens[0][0, 0] for lens in lenses.values())  # tan-width
    distance = max(board[0] / (0.5 * fov), 2.5 * baseline / fov)
    # Fixation point on the pair's bisector; toe-in turns each axis to it.
    fixation = np.array([baseline / 2, 0.0, distance])
    poses = {
        'left': make_transform(rot_y(vergence / 2), [0, 0, 0]),
        'right': make_transform(rot_y(-vergence / 2), [baseline, 0, 0]),
    }
    if 'aux' in cameras:
        oblique = np.radians(rng.uniform(0.0, 45.0))
        azimuth = rng.uniform(0, 2 * np.pi)
        aux_width = lenses['aux'][2][0]
        aux_distance = max(board[0] / (0.5 * aux_width / lenses['aux'][0][0, 0]), distance * 0.6)
        direction = np.array(
            [
                np.sin(oblique) * np.cos(azimuth),
                np.sin(oblique) * np.sin(azimuth),
                -np.cos(oblique),
            ]
        )
        centre = fixation + aux_distance * direction
        up = np.array([0.0, -1.0, 0.0])  # image up is -y of the left optical frame
        poses['aux'] = make_transform(look_at_rotation(centre, fixation, up), centre)
    T_base_rig = make_transform(
        rot_z(rng.uniform(-np.pi, np.pi)) @ rot_x(rng.uniform(-2.5, -1.5)),
        rng.uniform(-0.5, 0.5, 3) + [0, 0, 1.0],
    )
    truth = {}
    for name in cameras:
        K, D, size = lenses[name]
        truth[name] = PinholeCamera(size[0], size[1], K, D, T_base_rig @ poses[name], lens_model)
    outline = _outline_points(rows, cols, spacing)
    centre_chart = np.array([(cols - 1) * spacing / 2, (rows - 1) * spacing / 2, 0.0])
    charts: list[FloatArray] = []
    attempts = 0
    while len(charts) < views:
        attempts += 1
        if attempts > 20000:
            raise RuntimeError(f'draw_rig(seed={seed}): cannot place {views} chart poses')
        # Chart frame in the rig frame: z away from the cameras, tilted, turned in plane.
        spread = 0.25 if attempts < 5000 else 0.1
        centre = fixation + rng.uniform(-spread, spread, 3) * [board[0], board[1], distance]
        R = (
            rot_x(rng.uniform(-0.7, 0.7))
            @ rot_y(rng.uniform(-0.7, 0.7))
            @ rot_z(rng.uniform(-0.35, 0.35))
        )
        T_rig_chart = make_transform(R, centre - R @ centre_chart)
        T_base_chart = T_base_rig @ T_rig_chart
        outline_base = outline @ T_base_chart[:3, :3].T + T_base_chart[:3, 3]
        if all(
            board_in_view(camera, outline_base, T_base_chart=T_base_chart)
            for camera in truth.values()
        ):
            charts.append(T_base_chart)
    params: dict[str, int | float | str] = {
        'width': width,
        'baseline_m': baseline,
        'vergence_deg': float(np.degrees(vergence)),
        'views': views,
        'noise': noise,
        'chart': f'{rows}x{cols} @ {spacing * 1000:g} mm',
        'f_left': float(lenses['left'][0][0, 0]),
        'k1_left': float(lenses['left'][1][0]),
        'k1_right': float(lenses['right'][1][0]),
    }
    if 'aux' in cameras:
        params.update(
            aux_oblique_deg=float(np.degrees(oblique)),
            aux_width=int(lenses['aux'][2][0]),
            f_aux=float(lenses['aux'][0][0, 0]),
        )
    return Rig(truth, charts, int(rows), int(cols), float(spacing), noise, params)


def _undistortion_map(camera: PinholeCamera) -> FloatArray:
    """Normalised undistorted (x, y) at the pixel centres -1..W, -1..H: (H + 2, W + 2, 2)."""
    u, v = np.meshgrid(
        np.arange(-1, camera.width + 1, dtype=float), np.arange(-1, camera.height + 1, dtype=float)
    )
    xy = camera.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]))
    return xy.reshape(camera.height + 2, camera.width + 2, 2)


def _bilinear(grid: FloatArray, u: FloatArray, v: FloatArray) -> FloatArray:
    """Bilinear interpolation of a (H + 2, W + 2, 2) map of pixel centres -1.. at (u, v)."""
    gu, gv = u + 1.0, v + 1.0
    rows, cols = grid.shape[:2]
    i = np.clip(np.floor(gu).astype(int), 0, cols - 2)
    j = np.clip(np.floor(gv).astype(int), 0, rows - 2)
    fu, fv = (gu - i)[..., None], (gv - j)[..., None]
    return (grid[j, i] * (1 - fu) + grid[j, i + 1] * fu) * (1 - fv) + (
        grid[j + 1, i] * (1 - fu) + grid[j + 1, i + 1] * fu
    ) * fv


class ChartRenderer:
    """Renders the chart through a true camera, each pixel the mean of ``supersample``^2
    rays (box filter: the sensor's pixel area), the distortion applied exactly through the
    camera's undistortion map (interpolated between pixel centres, ~1e-4 px)."""

    def __init__(
        self,
        rows: int,
        cols: int,
        spacing: float,
        supersample: int = 4,
        pattern: str = 'chessboard',
    ) -> None:
        from sensor_sim.chart import print_albedo

        self.rows, self.cols, self.spacing = rows, cols, spacing
        self.albedo = print_albedo(pattern, rows, cols, spacing)
        self.supersample = int(supersample)
        # id(camera) -> (camera, its undistortion map); holding the camera keeps its id unique
        self._maps: dict[int, tuple[PinholeCamera, FloatArray]] = {}

    def render(
        self,
        camera: PinholeCamera,
        T_base_chart: FloatArray,
        rng: np.random.Generator | None = None,
        noise: float = 0.0,
    ) -> GreyImage:
        """(H, W) uint8 image of the chart at ``T_base_chart``; Gaussian noise ``noise``
        grey levels from ``rng``, then rounding (the camera's quantisation)."""
        from sensor_sim.chart import chart_plate_extent

        key = id(camera)
        if key not in self._maps:
            self._maps[key] = (camera, _undistortion_map(camera))
        grid = self._maps[key][1]
        image = np.full((camera.height, camera.width), BACKGROUND_GREY)
        T_camera_chart = camera.T_camera_base @ T_base_chart
        (x0, x1), (y0, y1) = chart_plate_extent(self.rows, self.cols, self.spacing)
        plate = np.array(
            [(x, y, 0.0) for x in np.linspace(x0, x1, 9) for y in np.linspace(y0, y1, 9)]
        )
        pixels, _ = camera.project(plate @ T_base_chart[:3, :3].T + T_base_chart[:3, 3])
        pixels = pixels[np.all(np.isfinite(pixels), axis=1)]
        if len(pixels) == 0:
            return self._quantise(image, rng, noise)
        u0, v0 = np.maximum(np.floor(pixels.min(axis=0)).astype(int) - 4, 0)
        u1 = min(int(np.ceil(pixels[:, 0].max())) + 5, camera.width)
        v1 = min(int(np.ceil(pixels[:, 1].max())) + 5, camera.height)
        if u1 <= u0 or v1 <= v0:
            return self._quantise(image, rng, noise)
        sample = self._sampler(T_camera_chart)
        # Grey at the pixel corners; only pixels whose four corners differ (an edge of the
        # print crosses them, the squares are far larger than a pixel) are supersampled.
        cu, cv = np.meshgrid(np.arange(u0, u1 + 1) - 0.5, np.arange(v0, v1 + 1) - 0.5)
        corner_grey = sample(_bilinear(grid, cu, cv))
        block = corner_grey[:-1, :-1].copy()
        mixed = (
            (corner_grey[:-1, :-1] != corner_grey[1:, :-1])
            | (corner_grey[:-1, :-1] != corner_grey[:-1, 1:])
            | (corner_grey[:-1, :-1] != corner_grey[1:, 1:])
        )
        mixed = (
            mixed
            | np.roll(mixed, 1, 0)
            | np.roll(mixed, -1, 0)
            | np.roll(mixed, 1, 1)
            | np.roll(mixed, -1, 1)
        )  # an edge may pass between the corners of a pixel
        r, c = np.nonzero(mixed)
        s = self.supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        du, dv = np.meshgrid(offsets, offsets)
        uu = (u0 + c)[:, None] + du.ravel()
        vv = (v0 + r)[:, None] + dv.ravel()
        block[r, c] = sample(_bilinear(grid, uu, vv)).mean(axis=1)
        image[v0:v1, u0:u1] = block
        return self._quantise(image, rng, noise)

    def _sampler(self, T_camera_chart: FloatArray) -> Callable[[FloatArray], FloatArray]:
        """(..., 2) normalised undistorted rays -> (...) grey level of what they hit."""
        R, origin = T_camera_chart[:3, :3], T_camera_chart[:3, 3]
        normal = R[:, 2]

        def sample(xy: FloatArray) -> FloatArray:
            x, y = xy[..., 0], xy[..., 1]
            with np.errstate(divide='ignore', invalid='ignore'):
                depth = (normal @ origin) / (normal[0] * x + normal[1] * y + normal[2])
            chart_x = depth * (R[0, 0] * x + R[1, 0] * y + R[2, 0]) - R[:, 0] @ origin
            chart_y = depth * (R[0, 1] * x + R[1, 1] * y + R[2, 1]) - R[:, 1] @ origin
            albedo = self.albedo(np.column_stack([chart_x.ravel(), chart_y.ravel()])).reshape(
                x.shape
            )
            grey = np.where(albedo > 0.5, WHITE_GREY, BLACK_GREY)
            return np.where(np.isfinite(albedo) & (depth > 0), grey, BACKGROUND_GREY)

        return sample

    @staticmethod
    def _quantise(image: FloatArray, rng: np.random.Generator | None, noise: float) -> GreyImage:
        if noise > 0:
            assert rng is not None, 'noise > 0 needs an rng'
            image = image + rng.normal(0.0, noise, image.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def with_edge_views(rig: Rig, count: int = 4, edge: float = 0.05) -> Rig:
    """``rig`` with ``count`` more views: its first views' boards slid along the left
    camera's x until the board's centre is ``edge`` of the width from the left image's
    edge, alternately left and right, so an image edge cuts them (where the distortion
    is largest). A chessboard is not found there; a ChArUco board's corners are."""
    left = rig.cameras['left']
    centre_chart = np.array([(rig.cols - 1) / 2, (rig.rows - 1) / 2, 0.0]) * rig.spacing
    slid = []
    for i, T in enumerate(rig.T_base_chart[:count]):
        centre = T[:3, :3] @ centre_chart + T[:3, 3]
        u = left.project(centre[None])[0][0, 0]
        depth = (left.T_camera_base[:3, :3] @ centre + left.T_camera_base[:3, 3])[2]
        moved = T.copy()
        target = left.width * (1 - edge if i % 2 else edge)
        moved[:3, 3] += left.T_camera_base[0, :3] * (target - u) * depth / left.K[0, 0]
        slid.append(moved)
    return rig._replace(T_base_chart=list(rig.T_base_chart) + slid)


def render_rig(rig: Rig, seed: int = 0, supersample: int = 4) -> list[dict[str, GreyImage]]:
    """Every view of every camera: [{name: (H, W) uint8}], noise from ``seed``."""
    rng = np.random.default_rng(seed)
    renderer = ChartRenderer(rig.rows, rig.cols, rig.spacing, supersample, rig.pattern)
    return [
        {name: renderer.render(camera, T, rng, rig.noise) for name, camera in rig.cameras.items()}
        for T in rig.T_base_chart
    ]


def true_corners(rig: Rig) -> list[dict[str, FloatArray]]:
    """[{name: (rows * cols, 2)}] true corner pixels of every view and camera."""
    chart = chart_points(rig.rows, rig.cols, rig.spacing)
    return [
        {
            name: camera.project(chart @ T[:3, :3].T + T[:3, 3])[0]
            for name, camera in rig.cameras.items()
        }
        for T in rig.T_base_chart
    ]


def _angle_deg(R: FloatArray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def score_rig(
    truth: Mapping[str, PinholeCamera],
    estimate: Mapping[str, PinholeCamera],
    absolute: bool = False,
    reference: str = 'left',
) -> dict[str, float]:
    """Errors of a calibrated rig against the truth, worst camera per figure.

    Args:
        truth: {name: PinholeCamera}.
        estimate: {name: PinholeCamera} (poses in base_link, or in any frame when
            ``absolute`` is False: poses are compared relative to ``reference``).

    Returns:
        dict: ``fx``, ``fy`` (relative), ``cx``, ``cy`` [px], ``distortion`` (largest
        displacement difference over the image with the true K [px]; where the true
        rays are in front of the camera), ``baseline``
        (relative), ``position`` [m] and ``rotation`` [deg] of each camera relative to
        ``reference`` (or in base_link), ``rect_rows`` (RMS row difference [px] of true
        left / right correspondences rectified with the estimate; needs left and right).
    """
    from vgm_common.calibration_io import stereo_rectification

    out = {k: 0.0 for k in ('fx', 'fy', 'cx', 'cy', 'distortion', 'position', 'rotation')}
    for name, true in truth.items():
        est = estimate[name]
        out['fx'] = max(out['fx'], abs(est.K[0, 0] / true.K[0, 0] - 1))
        out['fy'] = max(out['fy'], abs(est.K[1, 1] / true.K[1, 1] - 1))
        out['cx'] = max(out['cx'], abs(est.K[0, 2] - true.K[0, 2]))
        out['cy'] = max(out['cy'], abs(est.K[1, 2] - true.K[1, 2]))
        u, v = np.meshgrid(np.linspace(0, true.width - 1, 9), np.linspace(0, true.height - 1, 9))
        xy = true.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]))
        d_true = distort(xy, true.D, true.distortion_model) * [true.K[0, 0], true.K[1, 1]]
        d_est = distort(xy, est.D, est.distortion_model) * [true.K[0, 0], true.K[1, 1]]
        # nanmax: a fisheye's image corners may look past 90 deg, where the normalised
        # coordinates (x/z, y/z) do not exist
        out['distortion'] = max(
            out['distortion'], float(np.nanmax(np.linalg.norm(d_true - d_est, axis=1)))
        )
        if absolute:
            T_true, T_est = true.T_base_camera, est.T_base_camera
        else:
            if name == reference:
                continue
            T_true = np.linalg.inv(truth[reference].T_base_camera) @ true.T_base_camera
            T_est = np.linalg.inv(estimate[reference].T_base_camera) @ est.T_base_camera
        out['position'] = max(out['position'], float(np.linalg.norm(T_true[:3, 3] - T_est[:3, 3])))
        out['rotation'] = max(out['rotation'], _angle_deg(T_true[:3, :3].T @ T_est[:3, :3]))
    if 'left' in truth and 'right' in truth:
        b_true = np.linalg.norm(truth['left'].centre_base - truth['right'].centre_base)
        b_est = np.linalg.norm(estimate['left'].centre_base - estimate['right'].centre_base)
        out['baseline'] = float(abs(b_est / b_true - 1))
        out['rect_rows'] = rectified_row_error(truth, estimate, stereo_rectification)
    return out


def rectified_row_error(
    truth: Mapping[str, PinholeCamera],
    estimate: Mapping[str, PinholeCamera],
    stereo_rectification: Rectification,
) -> float:
    """RMS |v_left - v_right| [px] of true correspondences (points 1..3 m in front of the
    true left camera, seen by both) rectified with the estimated pair (for a fisheye
    pair, those inside both rectified images)."""
    rng = np.random.default_rng(0)
    left, right = truth['left'], truth['right']
    u = rng.uniform(0, left.width - 1, 400)
    v = rng.uniform(0, left.height - 1, 400)
    rays = left.pixel_rays_base(np.column_stack([u, v]))
    depth = (
        rng.uniform(0.5, 3.0, 400)[:, None]
        * np.linalg.norm(left.centre_base - right.centre_base)
        / 0.1
    )
    points = left.centre_base + rays * depth
    uv_l, _ = left.project(points)
    uv_r, d_r = right.project(points)
    keep = (d_r > 0) & np.all((uv_r >= 0) & (uv_r < [right.width, right.height]), axis=1)
    rect = stereo_rectification(estimate['left'], estimate['right'])
    rows: list[FloatArray] = []
    inside = np.ones(int(keep.sum()), dtype=bool)
    for name, uv in (('left', uv_l[keep]), ('right', uv_r[keep])):
        camera = estimate[name]
        R, P = rect[name]
        xy = camera.undistort_pixels(uv)
        ray = np.column_stack([xy, np.ones(len(xy))]) @ np.asarray(R).T
        rows.append(P[1, 1] * ray[:, 1] / ray[:, 2] + P[1, 2])
        columns = P[0, 0] * ray[:, 0] / ray[:, 2] + P[0, 2]
        inside &= (ray[:, 2] > 0) & (columns >= 0) & (columns < camera.width)
        inside &= (rows[-1] >= 0) & (rows[-1] < camera.height)
    if 'equidistant' in (left.distortion_model, right.distortion_model):
        # A fisheye pair's rectified images (balance 0) hold only the middle of its
        # field: the rows are compared where both points land in them.
        rows = [r[inside] for r in rows]
    return float(np.sqrt(np.mean((rows[0] - rows[1]) ** 2)))


def camera_in_frame(
    K: FloatArray,
    D: FloatArray,
    T_camera_ref: FloatArray,
    size: tuple[int, int],
    distortion_model: str = 'plumb_bob',
) -> PinholeCamera:
    """The camera of intrinsics ``K``, ``D`` (of ``distortion_model``) whose pose in a
    calibration's reference frame is ``T_camera_ref`` (its ``T_base_camera`` the
    inverse), image ``size`` (width, height) [px]."""
    return PinholeCamera(*size, K, D, invert_transform(T_camera_ref), distortion_model)


def true_projection_error(
    true: PinholeCamera, calibrated: PinholeCamera, depth: float, grid: tuple[int, int] = GRID
) -> FloatArray:
    """(rows, cols) [px]: where the ``calibrated`` camera projects the points the ``true``
    one sees on the grid pixels at ``depth`` [m], minus those pixels: the error
    calib_node's uncertainty predicts. Both poses in their own reference frame (the
    calibration's gauge)."""
    pixels = image_grid((true.width, true.height), grid)
    points = points_at_range(true, pixels, depth)
    return _pixel_errors(calibrated, points, pixels, grid)


def true_projection_error_chart_fixed(
    true: PinholeCamera,
    T_ref_chart_true: Sequence[FloatArray],
    calibrated: PinholeCamera,
    T_ref_chart: Sequence[FloatArray],
    depth: float,
    grid: tuple[int, int] = GRID,
) -> FloatArray:
    """(rows, cols) [px]: :func:`true_projection_error` with the points held fixed to the
    charts (the gauge of calib_node.uncertainty.projection_std_chart_fixed): each true
    point is carried into every true chart frame, back out by the calibrated chart pose,
    averaged over the charts and projected by the calibrated camera."""
    pixels = image_grid((true.width, true.height), grid)
    points = points_at_range(true, pixels, depth)
    moved = np.mean(
        [
            points @ M[:3, :3].T + M[:3, 3]
            for M in (
                T @ invert_transform(T_true) for T, T_true in zip(T_ref_chart, T_ref_chart_true)
            )
        ],
        axis=0,
    )
    return _pixel_errors(calibrated, moved, pixels, grid)


def _pixel_errors(
    camera: PinholeCamera, points: FloatArray, pixels: FloatArray, grid: tuple[int, int]
) -> FloatArray:
    projected, _ = camera.project(points)
    return np.linalg.norm(projected - pixels, axis=1).reshape(grid[1], grid[0])
