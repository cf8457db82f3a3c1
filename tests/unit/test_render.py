"""Renderer, curves and chart against independent ground truth: OpenCV projection, closed-
form shading, OpenCV chessboard detection. Small cameras where full size is not needed."""

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from sensor_sim import chart, curves, surfaces
from sensor_sim.render import SceneRenderer, add_noise
from sensor_sim.scenario import Curve, load_scenario
from vgm_common.geometry import make_transform, rot_y, rpy_to_matrix, transform_points

SCENARIOS = Path(__file__).resolve().parents[2] / 'src' / 'sensor_sim' / 'scenarios'
SHIPPED = sorted(SCENARIOS.glob('*.yaml'))
RIG_SCENARIOS = ('default', 'S1', 'S2')  # the closed-loop rig: arm, surface, loop curve


def small_camera(camera, factor=0.25):
    """The same camera with fewer, larger pixels (same field of view and distortion)."""
    K = camera.K.copy()
    K[:2] *= factor
    K[:2, 2] += 0.5 * factor - 0.5  # keep pixel centres on the same rays
    return replace(
        camera, width=round(camera.width * factor), height=round(camera.height * factor), K=K
    )


@pytest.fixture(scope='module')
def default():
    return load_scenario(SCENARIOS / 'default.yaml')


@pytest.fixture(scope='module')
def small(default):
    """The default scenario seen by 160 x 120 cameras."""
    return replace(
        default, cameras={name: small_camera(camera) for name, camera in default.cameras.items()}
    )


@pytest.fixture(scope='module')
def small_renderer(small):
    return SceneRenderer(small)


@pytest.fixture(scope='module')
def left_renderer(default):
    """The default scenario's full-size left camera alone (for the chart)."""
    return SceneRenderer(replace(default, cameras={'left': default.cameras['left']}))


def plane_scenario(scenario, roughness=0.0, contrast=0.0, curve=None):
    """A tilted plane where the default surface is, with an optional curve."""
    surface = replace(
        scenario.surface,
        kind='plane',
        roughness=roughness,
        T_base_surface=make_transform(rot_y(0.2), [0.6, 0.0, 0.2]),
    )
    return replace(
        scenario, surface=surface, curve=curve or replace(scenario.curve, contrast=contrast)
    )


def opencv_project(camera, points_base):
    T = camera.T_camera_base
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    pixels, _ = cv2.projectPoints(
        np.ascontiguousarray(points_base), rvec, T[:3, 3], camera.K, camera.D
    )
    return pixels.reshape(-1, 2)


def pixel_grid(camera):
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    return np.stack([u, v], axis=-1)


def test_projection_agrees_with_opencv_on_surface_and_curve(small, small_renderer):
    for name, camera in small.cameras.items():
        hits = small_renderer.hit_points_base(name).reshape(-1, 3)
        hits = hits[np.isfinite(hits[:, 0])][::7]
        curve_points = curves.curve_points_base(small.curve, small.surface)
        for points in (hits, curve_points):
            pixels, _ = camera.project(points)
            np.testing.assert_allclose(pixels, opencv_project(camera, points), atol=1e-6)
    assert np.any(small.cameras['left'].D != 0)  # the check covers distortion


def test_ray_hits_reproject_to_their_pixel_and_lie_on_the_surface(small, small_renderer):
    for name, camera in small.cameras.items():
        hits = small_renderer.hit_points_base(name)
        hit = np.isfinite(hits[..., 0])
        assert hit.mean() > 0.1
        pixels = opencv_project(camera, hits[hit])
        np.testing.assert_allclose(pixels, pixel_grid(camera)[hit], atol=1e-6)
        # On S3, by its own formula (independent of the renderer's height code).
        local = surfaces.to_surface_units(small.surface, hits[hit])
        x, y, z = local.T
        assert np.max(np.abs(z - (x * y + 0.5 * x - 0.6))) < 1e-9


def test_depth_is_the_optical_axis_z_of_the_hit(small, small_renderer):
    for name, camera in small.cameras.items():
        depth = small_renderer.depth(name)
        assert depth.dtype == np.float32 and depth.shape == (camera.height, camera.width)
        hits = small_renderer.hit_points_base(name)
        hit = np.isfinite(hits[..., 0])
        np.testing.assert_array_equal(np.isfinite(depth), hit)
        z_camera = camera.to_camera(hits[hit])[:, 2]
        np.testing.assert_allclose(depth[hit], z_camera, rtol=1e-6)


def test_lambert_shading_is_the_closed_form(small):
    scenario = plane_scenario(small)
    renderer = SceneRenderer(scenario)
    light = scenario.lighting
    normal = scenario.surface.T_base_surface[:3, 2]
    expected = (
        255
        * scenario.surface.albedo
        * (light.intensity * normal @ light.direction_base + light.ambient)
    )
    for name in scenario.cameras:
        image, depth = renderer.scene_image(name), renderer.depth(name)
        assert np.isfinite(depth).mean() > 0.1
        np.testing.assert_allclose(image[np.isfinite(depth)], expected, rtol=1e-12)
        assert np.all(image[~np.isfinite(depth)] < expected / 4)  # dark background


def oren_nayar_by_angles(normal, light, view, sigma, tan_beta=True):
    """Oren-Nayar factor from polar/azimuth angles in a tangent frame (no albedo)."""
    e1 = np.cross(normal, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    theta_i, theta_r = np.arccos(light @ normal), np.arccos(view @ normal)
    phi_i = np.arctan2(light @ e2, light @ e1)
    phi_r = np.arctan2(view @ e2, view @ e1)
    A = 1 - 0.5 * sigma**2 / (sigma**2 + 0.33)
    B = 0.45 * sigma**2 / (sigma**2 + 0.09)
    alpha, beta = max(theta_i, theta_r), min(theta_i, theta_r)
    f_beta = np.tan(beta) if tan_beta else np.sin(beta)
    return np.cos(theta_i) * (A + B * max(0.0, np.cos(phi_r - phi_i)) * np.sin(alpha) * f_beta)


@pytest.mark.parametrize('variant', ['oren_nayar', 'thesis'])
def test_oren_nayar_shading_matches_the_angle_form(small, variant):
    sigma = 0.4
    scenario = plane_scenario(small, roughness=sigma)
    renderer = SceneRenderer(scenario, variant=variant)
    lambert = SceneRenderer(plane_scenario(small)).scene_image('left')
    light = scenario.lighting
    normal = scenario.surface.T_base_surface[:3, 2]
    camera = scenario.cameras['left']
    image, hits = renderer.scene_image('left'), renderer.hit_points_base('left')
    rows, cols = np.nonzero(np.isfinite(renderer.depth('left')))
    for index in np.linspace(0, len(rows) - 1, 12).astype(int):
        r, c = rows[index], cols[index]
        view = camera.centre_base - hits[r, c]
        view /= np.linalg.norm(view)
        factor = oren_nayar_by_angles(
            normal, light.direction_base, view, sigma, tan_beta=variant == 'oren_nayar'
        )
        expected = 255 * scenario.surface.albedo * (light.intensity * factor + light.ambient)
        assert image[r, c] == pytest.approx(expected, rel=1e-9)
    # Roughness flattens the shading: darker than Lambert (A < 1) except where the
    # back-scattering term wins; with this rig it changes every lit pixel.
    lit = np.isfinite(renderer.depth('left'))
    assert np.min(np.abs(image[lit] - lambert[lit])) > 1.0


def test_curve_is_darker_by_the_contrast(small, small_renderer):
    clean = SceneRenderer(replace(small, curve=replace(small.curve, contrast=0.0)))
    contrast = small.curve.contrast
    for name, camera in small.cameras.items():
        image, background = small_renderer.scene_image(name), clean.scene_image(name)
        # The pixel nearest each curve sample is within 0.71 px of the line: fully covered.
        pixels, _ = camera.project(curves.curve_points_base(small.curve, small.surface))
        cols, rows = np.rint(pixels).astype(int).T
        np.testing.assert_allclose(
            image[rows, cols], (1 - contrast) * background[rows, cols], rtol=1e-12
        )
        # Away from the line (3 px and more) nothing changes.
        far = np.ones(image.shape, bool)
        for dr in range(-3, 4):
            for dc in range(-3, 4):
                far[
                    np.clip(rows + dr, 0, camera.height - 1),
                    np.clip(cols + dc, 0, camera.width - 1),
                ] = False
        np.testing.assert_array_equal(image[far], background[far])


@pytest.mark.parametrize('offset, visible', [(-0.03, False), (0.0, True), (0.03, True)])
def test_curve_behind_the_surface_is_hidden(small, offset, visible):
    """A circle 3 cm below the plane is hidden; on it or above it, it is drawn."""
    scenario = plane_scenario(small)
    normal = scenario.surface.T_base_surface[:3, 2]
    circle = Curve(
        kind='circle',
        line_width_px=2.0,
        contrast=0.5,
        samples=500,
        params={
            'center': np.array([0.6, 0.0, 0.2]) + offset * normal,
            'normal': normal,
            'radius': 0.06,
        },
    )
    with_curve = SceneRenderer(replace(scenario, curve=circle))
    without = SceneRenderer(replace(scenario, curve=replace(circle, contrast=0.0)))
    for name in scenario.cameras:
        darkened = np.sum(with_curve.scene_image(name) < without.scene_image(name) - 1)
        assert (darkened > 20) == visible


def test_chessboard_corners_are_found_where_they_are(default, left_renderer):
    calibration = default.calibration
    pose = 2
    image = add_noise(
        left_renderer.chart_image('left', pose),
        default.noise.image_sigma,
        np.random.default_rng(0),
    )
    found, corners = cv2.findChessboardCorners(image, (calibration.cols, calibration.rows))
    assert found
    corners = cv2.cornerSubPix(
        image,
        corners,
        (5, 5),
        (-1, -1),
        (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4),
    )
    corners = corners.reshape(-1, 2)
    truth_base = transform_points(
        calibration.T_base_chart[pose],
        chart.chart_corners_chart(calibration.rows, calibration.cols, calibration.spacing),
    )
    truth, _ = default.cameras['left'].project(truth_base)
    # OpenCV may start at either end of the board.
    rms = min(
        np.sqrt(np.mean(np.sum((order - truth) ** 2, axis=1)))
        for order in (corners, corners[::-1])
    )
    assert rms < 0.1


def test_black_square_is_outside_corner_zero(default, left_renderer):
    calibration = default.calibration
    rows, cols, s = calibration.rows, calibration.cols, calibration.spacing
    image = left_renderer.chart_image('left', 0)
    probes_chart = np.array(
        [
            [-s / 2, -s / 2, 0],  # outside corner (0, 0): black
            [s / 2, -s / 2, 0],  # its neighbour: white
            [(cols - 0.5) * s, (rows - 0.5) * s, 0],
        ]
    )  # opposite: white
    pixels, _ = default.cameras['left'].project(
        transform_points(calibration.T_base_chart[0], probes_chart)
    )
    cols_px, rows_px = np.rint(pixels).astype(int).T
    black, white, opposite = image[rows_px, cols_px]
    assert black < 0.2 * white and opposite > 5 * black


def test_chart_supersampling_skips_only_uniform_pixels(small):
    """The chart image equals the mean of supersample^2 rays in every pixel, including a
    chart seen nearly edge-on (slivers thinner than a pixel) and one cut by the surface."""
    from sensor_sim.render import _chart_pixel_box, _chart_sampler, _interpolate_normalized

    poses = (
        small.calibration.T_base_chart[3],
        make_transform(rpy_to_matrix(np.pi / 2, 0.0, 0.4), [0.6, 0.0, 0.4]),
        make_transform(rpy_to_matrix(np.pi + 0.2, 0.1, 0.2), [0.45, -0.1, 0.18]),
    )
    scenario = replace(small, calibration=replace(small.calibration, T_base_chart=poses))
    renderer = SceneRenderer(scenario, supersample=4)
    calibration, camera = scenario.calibration, scenario.cameras['left']
    offsets = (np.arange(4) + 0.5) / 4 - 0.5
    for index, T_base_chart in enumerate(poses):
        (u0, u1), (v0, v1) = _chart_pixel_box(
            camera, T_base_chart, calibration.rows, calibration.cols, calibration.spacing
        )
        rows, cols = np.mgrid[v0:v1, u0:u1]
        du, dv = np.meshgrid(offsets, offsets)
        u = cols.reshape(-1, 1) + du.ravel()
        v = rows.reshape(-1, 1) + dv.ravel()
        x, y = _interpolate_normalized(renderer._view('left').normalized, u.ravel(), v.ravel())
        grey, depth = _chart_sampler(scenario, camera, T_base_chart)(
            x.reshape(u.shape), y.reshape(u.shape)
        )
        scene_depth = renderer.depth('left')[v0:v1, u0:u1].reshape(-1, 1).astype(float)
        scene = renderer.scene_image('left')[v0:v1, u0:u1].reshape(-1, 1)
        expected = np.where(depth < np.nan_to_num(scene_depth, nan=np.inf), grey, scene)
        np.testing.assert_array_equal(
            renderer.chart_image('left', index)[v0:v1, u0:u1],
            expected.mean(axis=1).reshape(rows.shape),
        )


def test_chart_frame_layout():
    corners = chart.chart_corners_chart(3, 4, 0.05)
    assert corners.shape == (12, 3)
    np.testing.assert_allclose(corners[1 * 4 + 2], [2 * 0.05, 1 * 0.05, 0.0])
    albedo = chart.chart_albedo(
        [[-0.025, -0.025], [0.025, -0.025], [0.025, 0.025], [-0.075, 0.0], [-0.2, 0.0]], 3, 4, 0.05
    )
    assert albedo[0] == chart.BLACK_ALBEDO and albedo[2] == chart.BLACK_ALBEDO
    assert albedo[1] == chart.WHITE_ALBEDO
    assert albedo[3] == chart.WHITE_ALBEDO  # the margin
    assert np.isnan(albedo[4])  # off the plate


def test_add_noise_is_seeded_and_has_the_right_sigma():
    clean = np.full((200, 300), 127.3)
    first = add_noise(clean, 3.0, np.random.default_rng([7, 0, 1]))
    second = add_noise(clean, 3.0, np.random.default_rng([7, 0, 1]))
    assert first.dtype == np.uint8 and first.tobytes() == second.tobytes()
    assert first.std() == pytest.approx(3.0, rel=0.03)
    assert first.mean() == pytest.approx(127.3, abs=0.05)
    other = add_noise(clean, 3.0, np.random.default_rng([7, 1, 1]))
    assert other.tobytes() != first.tobytes()
    assert add_noise(np.array([[-5.0, 300.0]]), 0.0, np.random.default_rng(0)).tolist() == [
        [0, 255]
    ]


def test_renders_are_deterministic(small):
    first, second = SceneRenderer(small), SceneRenderer(small)
    assert first.scene_image('aux').tobytes() == second.scene_image('aux').tobytes()


def test_curve_pieces_and_sampling(default):
    surface = default.surface
    loop = curves.curve_polylines(default.curve, surface)
    assert len(loop) == 1 and np.array_equal(loop[0][0], loop[0][-1])  # closed
    points = curves.curve_points_base(default.curve, surface)
    assert points.shape == (default.curve.samples, 3)
    np.testing.assert_allclose(surfaces.signed_height_base(surface, points), 0.0, atol=1e-12)
    spacing = np.linalg.norm(np.diff(loop[0], axis=0), axis=1)
    assert spacing.std() < 1e-3 * spacing.mean()  # even in arc length
    segments = np.array(
        [[[0.5, -0.1, 0.2], [0.7, -0.1, 0.2]], [[0.5, 0.1, 0.2], [0.6, 0.1, 0.25]]]
    )
    pair = Curve(
        kind='line_pair',
        line_width_px=2.0,
        contrast=0.5,
        samples=100,
        params={'segments': segments},
    )
    pieces = curves.curve_polylines(pair, surface)
    assert len(pieces) == 2 and sum(len(p) for p in pieces) == 100
    for piece, (start, end) in zip(pieces, segments):
        np.testing.assert_allclose(piece[[0, -1]], [start, end], atol=1e-15)
    parabola = Curve(
        kind='parabola',
        line_width_px=2.0,
        contrast=0.5,
        samples=50,
        params={
            'coefficients': np.array([[0.6, 0.1, 0.0], [0.0, 0.0, 0.1], [0.2, 0.0, 0.0]]),
            't_range': np.array([-1.0, 1.0]),
        },
    )
    arc = curves.curve_polylines(parabola, surface)[0]
    np.testing.assert_allclose(arc[[0, -1]], [[0.5, 0.1, 0.2], [0.7, 0.1, 0.2]], atol=1e-15)
    np.testing.assert_allclose(arc[:, 1], 0.1 * ((arc[:, 0] - 0.6) / 0.1) ** 2, atol=1e-12)


@pytest.mark.parametrize('path', SHIPPED, ids=[p.stem for p in SHIPPED])
def test_every_shipped_scenario_loads(path):
    scenario = load_scenario(path)
    points = curves.curve_points_base(scenario.curve, scenario.surface)
    assert np.all(np.isfinite(points))


@pytest.mark.parametrize('name', RIG_SCENARIOS)
def test_rig_scenarios_show_the_curve_and_the_whole_chart(name):
    """The closed-loop scenarios: the curve and the whole chart plate, at every stage pose,
    inside all three images, the printed face toward each camera, above the surface."""
    scenario = load_scenario(SCENARIOS / f'{name}.yaml')
    calibration = scenario.calibration
    (x0, x1), (y0, y1) = chart.chart_plate_extent(
        calibration.rows, calibration.cols, calibration.spacing
    )
    x, y = np.meshgrid(np.linspace(x0, x1, 12), np.linspace(y0, y1, 9))
    plate = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    plates_base = [transform_points(T, plate) for T in calibration.T_base_chart]
    curve_points = curves.curve_points_base(scenario.curve, scenario.surface)
    for camera in scenario.cameras.values():
        for points in [curve_points] + plates_base:
            pixels, depth = camera.project(points)
            assert np.all(depth > 0)
            assert np.all((pixels >= 2) & (pixels <= [camera.width - 3, camera.height - 3]))
        for T_base_chart in calibration.T_base_chart:
            # The printed face (-z of the chart frame) faces the camera.
            assert (camera.centre_base - T_base_chart[:3, 3]) @ T_base_chart[:3, 2] < 0
    for points in plates_base:
        clearance = surfaces.signed_height_base(scenario.surface, points)
        assert np.all(clearance[np.isfinite(clearance)] > 0.02)
