"""Scenario files and the camera models they configure.

Every shipped scenario loads and shows its curve to all three cameras; the thesis setups
(chapters 3 and 4) map faithfully onto base_link; bad input fails with one ScenarioError
naming the key; the division model inverts exactly and matches the seed's formula; the
plumb_bob model still matches OpenCV.
"""

import copy
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from sensor_sim.scenario import load_scenario, parse_scenario
from vgm_common.camera_model import PinholeCamera
from vgm_common.errors import InvalidInput, ScenarioError
from vgm_common.geometry import (
    look_at_rotation,
    make_transform,
    matrix_to_quaternion,
    rot_x,
    rot_z,
    rpy_to_matrix,
)

SCENARIO_DIR = Path(__file__).resolve().parents[2] / 'src' / 'sensor_sim' / 'scenarios'
SHIPPED = sorted(SCENARIO_DIR.glob('*.yaml'))
THESIS_FILES = sorted(SCENARIO_DIR.glob('ch[34]_*.yaml'))
CM = 0.01  # [m per thesis unit] in the chapter-3 files
MM = 0.001  # [m per thesis unit] in the chapter-4 file


def ids(paths):
    return [path.stem for path in paths]


# --------------------------------------------------------------------------- helpers


def curve_samples_base(curve, surface, n=1500):
    """Points (N, 3) [m] on a scenario curve, from the formulas of docs/SCENARIO.md."""
    p = curve.params
    kind = curve.kind
    if kind in ('parabola', 'cubic'):
        t = np.linspace(*p['t_range'], n)
        return np.vander(t, p['coefficients'].shape[1], increasing=True) @ p['coefficients'].T
    t = np.linspace(0.0, 2 * np.pi, n)
    if kind == 'ellipse':
        return p['center'] + np.outer(np.cos(t), p['axis_a']) + np.outer(np.sin(t), p['axis_b'])
    if kind == 'circle':
        normal = p['normal'] / np.linalg.norm(p['normal'])
        u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        return p['center'] + p['radius'] * (np.outer(np.cos(t), u) + np.outer(np.sin(t), v))
    if kind == 'line_pair':
        s = np.linspace(0.0, 1.0, n)[:, None]
        return np.vstack([a + s * (b - a) for a, b in p['segments']])
    if kind == 'points':
        return p['points']
    if kind == 'surface_loop':  # the loop is ours; the surface's height h(x, y) is the simulator's
        from sensor_sim.surfaces import surface_points_base

        c, s = np.cos(p['angle']), np.sin(p['angle'])
        local = np.column_stack([p['radii'][0] * np.cos(t), p['radii'][1] * np.sin(t)])
        return surface_points_base(surface, p['center'] + local @ np.array([[c, s], [-s, c]]))
    raise AssertionError(f'no formula for curve kind {kind}')


def assert_inside(camera, points_base, margin_px=0.0, what='points'):
    pixels, depth = camera.project(points_base)
    assert np.all(depth > 0), f'{what} behind the camera'
    u, v = pixels[:, 0], pixels[:, 1]
    assert np.all(np.isfinite(pixels)), f'{what} do not project'
    inside = (
        (u >= margin_px)
        & (u <= camera.width - 1 - margin_px)
        & (v >= margin_px)
        & (v <= camera.height - 1 - margin_px)
    )
    assert inside.all(), (
        f'{what}: {np.count_nonzero(~inside)} of {len(u)} outside the '
        f'{camera.width}x{camera.height} image; u in [{u.min():.1f}, '
        f'{u.max():.1f}], v in [{v.min():.1f}, {v.max():.1f}]'
    )


def euler_zxz(theta, phi, psi):
    """Chapter 3's camera-2 rotation (world -> camera): Rz(psi) Rx(theta) Rz(phi)."""
    return rot_z(psi) @ rot_x(theta) @ rot_z(phi)


def seed_division_project(points_w, f, N, u0, v0, k, R, T):
    """The seed's chapter-4 camera (4.2.1-4.2.4) evaluated literally, in focal-plane units:
    the distorted radius is the real non-negative root of k r^3 + r - r_u (numpy roots)."""
    X = points_w @ R.T + T
    Xu, Yu = f * X[:, 0] / X[:, 2], f * X[:, 1] / X[:, 2]
    pixels = []
    for xu, yu in zip(Xu, Yu):
        roots = np.roots([k, 0.0, 1.0, -np.hypot(xu, yu)])
        r = min(root.real for root in roots if abs(root.imag) < 1e-9 and root.real >= 0)
        scale = 1.0 / (1.0 + k * r * r)
        pixels.append((N * xu * scale + u0, N * yu * scale + v0))
    return np.array(pixels)


def camera_from_seed(width, height, f, N, u0, v0, k, R, T, scale):
    """Our camera for the seed's parameters; world lengths times ``scale`` give metres."""
    K = np.array([[f * N, 0.0, u0], [0.0, f * N, v0], [0.0, 0.0, 1.0]])
    pose = make_transform(R.T, -R.T @ np.asarray(T, dtype=float) * scale)
    return PinholeCamera(width, height, K, [k * f * f], pose, 'division')


# --------------------------------------------------------------------------- shipped files


def test_the_thesis_setups_are_shipped():
    names = {path.stem for path in SHIPPED}
    assert {
        'ch3_parabola_perfect',
        'ch3_ellipse_perfect',
        'ch3_line_pair',
        'ch3_parabola_general',
        'ch3_cubic_planar',
        'ch3_cubic_general',
        'ch4_calibration',
    } <= names


@pytest.mark.parametrize('path', SHIPPED, ids=ids(SHIPPED))
def test_shipped_scenario_loads(path):
    scenario = load_scenario(path)
    assert scenario.name == path.stem
    assert set(scenario.cameras) == {'left', 'right', 'aux'}


@pytest.mark.parametrize('path', SHIPPED, ids=ids(SHIPPED))
def test_curve_is_inside_every_image(path):
    scenario = load_scenario(path)
    points = curve_samples_base(scenario.curve, scenario.surface)
    assert np.all(np.isfinite(points))
    for name, camera in scenario.cameras.items():
        assert_inside(camera, points, what=f'{name}: curve samples')


# the scenarios whose curve floats in front of a background plane (elsewhere it lies on
# the surface)
PLANE_BACKED = [p for p in SHIPPED if load_scenario(p).surface.kind == 'plane']


@pytest.mark.parametrize('path', PLANE_BACKED, ids=ids(PLANE_BACKED))
def test_background_plane_is_behind_the_curve(path):
    """Along every camera ray through a curve sample the plane comes after the sample, inside
    its extent: the curve floats in front of it and is seen against it."""
    scenario = load_scenario(path)
    surface = scenario.surface
    points = curve_samples_base(scenario.curve, surface)
    R, origin = surface.T_base_surface[:3, :3], surface.T_base_surface[:3, 3]
    normal = R[:, 2]
    for name, camera in scenario.cameras.items():
        centre = camera.centre_base
        rays = points - centre
        t_plane = ((origin - centre) @ normal) / (rays @ normal)  # the sample is at t = 1
        assert np.all(t_plane > 1.0), f'{name}: the plane is not behind the curve'
        hits_surface = (centre + t_plane[:, None] * rays - origin) @ R / surface.scale
        (x0, x1), (y0, y1) = surface.extent
        assert np.all(
            (hits_surface[:, 0] > x0)
            & (hits_surface[:, 0] < x1)
            & (hits_surface[:, 1] > y0)
            & (hits_surface[:, 1] < y1)
        ), name


@pytest.mark.parametrize('path', THESIS_FILES, ids=ids(THESIS_FILES))
def test_chart_is_whole_in_every_image_at_every_stage_pose(path):
    """Every inner corner and the printed squares around them (one square beyond the
    corners) are inside every image, printed face toward the camera."""
    scenario = load_scenario(path)
    chart = scenario.calibration
    rows, cols, spacing = chart.rows, chart.cols, chart.spacing
    x = np.linspace(-spacing, cols * spacing, 4 * cols + 5)
    y = np.linspace(-spacing, rows * spacing, 4 * rows + 5)
    gx, gy = np.meshgrid(x, y)
    printed_chart = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    for index, T_base_chart in enumerate(chart.T_base_chart):
        printed_base = printed_chart @ T_base_chart[:3, :3].T + T_base_chart[:3, 3]
        for name, camera in scenario.cameras.items():
            assert_inside(
                camera, printed_base, margin_px=2.0, what=f'{name}: chart at stage pose {index}'
            )
            to_chart = T_base_chart[:3, 3] - camera.centre_base
            assert T_base_chart[:3, 2] @ to_chart > 0, f'{name} sees the back of the chart'


# Thesis chapter 3 (ALGORITHMS.md §2.4): curve x(t) in thesis units, its t range, camera 2's
# centre and Euler angles (theta, phi, psi) [rad].
CHAPTER3 = {
    'ch3_parabola_perfect': (
        lambda t: (16 * t**2, 4 * t, 40 + 0 * t),
        (-4, 4),
        (100, 0, 0),
        (0, 0, 0),
    ),
    'ch3_ellipse_perfect': (
        lambda t: (
            5 + 3 * np.cos(t) - 2 * np.sin(t),
            4 - 2 * np.cos(t) + 3 * np.sin(t),
            0.82 - 0.02 * np.cos(t) - 0.02 * np.sin(t),
        ),
        (0, 2 * np.pi),
        (15, 0, 0),
        (0, 0, 0),
    ),
    'ch3_line_pair': (lambda t: (4 + 5 * t, 5 + t, 10 + 0 * t), (0, 1), (20, 0, 0), (0, 0, 0)),
    'ch3_parabola_general': (
        lambda t: (
            40 + 9.96195 * t - 0.31751 * t**2,
            70 + 0.59696 * t + 4.980975 * t**2,
            100 + 0.63502 * t + 0.29848 * t**2,
        ),
        (-4, 4),
        (30, 80, 30),
        (np.pi / 4,) * 3,
    ),
    'ch3_cubic_planar': (
        lambda t: (t, t**3 + 2 * t**2 + 5 * t + 1, 10 + 0 * t),
        (-1, 1),
        (12, 0, 0),
        (0, 0, 0),
    ),
    # t from -0.5, not -1: below t = -0.943 the curve is behind camera 2 (see the file).
    'ch3_cubic_general': (
        lambda t: (t**3 + t + 4, t**3 + 2 * t**2 + 5 * t + 1, 3 * t**3 + 2 * t**2 + 3 * t + 25),
        (-0.5, 1),
        (15, 10, 20),
        tuple(np.deg2rad([5, 20, 15])),
    ),
}


@pytest.mark.parametrize('name', sorted(CHAPTER3))
def test_chapter3_setup_maps_the_thesis(name):
    """Our pixels, undone by K, are the thesis's image coordinates X = f x/z (f = 1) of the
    thesis's curve, 1 unit = 1 cm, in both thesis cameras; aux is off the line c1-c2."""
    curve_units, t_range, c2_units, angles = CHAPTER3[name]
    scenario = load_scenario(SCENARIO_DIR / f'{name}.yaml')
    t = np.linspace(*t_range, 200)
    points_units = np.column_stack(curve_units(t))
    if scenario.curve.kind in ('parabola', 'cubic'):
        assert np.allclose(scenario.curve.params['t_range'], t_range)
        ours = curve_samples_base(scenario.curve, scenario.surface, n=200)
        assert np.allclose(ours, points_units * CM, rtol=0, atol=1e-12)
    thesis = {
        'left': (np.eye(3), np.zeros(3)),
        'right': (euler_zxz(*angles), np.array(c2_units, dtype=float)),
    }
    for camera_name, (R, c) in thesis.items():
        camera = scenario.cameras[camera_name]
        assert np.allclose(camera.T_base_camera[:3, :3], R.T, atol=1e-12)
        assert np.allclose(camera.centre_base, c * CM, atol=1e-12)
        x_cam = (points_units - c) @ R.T
        X_thesis = x_cam[:, :2] / x_cam[:, 2:]
        pixels, _ = camera.project(points_units * CM)
        assert np.allclose(camera.undistort_pixels(pixels), X_thesis, atol=1e-9)
    c1, c2 = np.zeros(3), np.array(c2_units) * CM
    aux = scenario.cameras['aux'].centre_base
    distance_to_baseline = np.linalg.norm(np.cross(aux - c1, c2 - c1)) / np.linalg.norm(c2 - c1)
    assert distance_to_baseline > 0.01  # [m]


def test_chapter4_cameras_reproduce_the_seed_projection():
    """Tables 4.1 / 4.2 through the seed's formulas give exactly our cameras' pixels for the
    seed's 8 x 8 x 8 control grid (units mm), which lies on the chart's corners."""
    scenario = load_scenario(SCENARIO_DIR / 'ch4_calibration.yaml')
    g = np.arange(8) * 10.0
    grid_mm = np.array([(x, y, z) for z in g for y in g for x in g])
    seed = {
        'left': dict(
            f=10, N=200, u0=20, v0=19, k=0.15152, R=np.eye(3), T=np.array([60, 35, 1210.0])
        ),
        'right': dict(
            f=25,
            N=144,
            u0=256,
            v0=192,
            k=0.15152,
            R=rpy_to_matrix(0.15152, 0.20916, -1.90),  # Rz(a) Ry(b) Rx(g)
            T=np.array([-38, 35, 1210.0]),
        ),
    }
    for name, parameters in seed.items():
        camera = scenario.cameras[name]
        expected = seed_division_project(grid_mm, **parameters)
        pixels, _ = camera.project(grid_mm * MM)
        assert np.max(np.abs(pixels - expected)) < 1e-6, name
        assert_inside(camera, grid_mm * MM, what=f'{name}: control points')
    left_pixels, _ = scenario.cameras['left'].project(grid_mm * MM)
    assert np.allclose(left_pixels.min(axis=0), [104, 67], atol=1)  # ALGORITHMS.md §3.6
    assert np.allclose(left_pixels.max(axis=0), [208, 174], atol=1)
    chart = scenario.calibration
    r, c = np.divmod(np.arange(chart.rows * chart.cols), chart.cols)
    corners = np.column_stack([c * chart.spacing, r * chart.spacing, np.zeros(r.size)])
    corners_mm = np.vstack([corners @ T[:3, :3].T + T[:3, 3] for T in chart.T_base_chart]) / MM
    corner_set = {tuple(p) for p in np.round(corners_mm, 6)}
    assert {tuple(p) for p in grid_mm} <= corner_set


# --------------------------------------------------------------------------- bad input

MINIMAL = """
seed: 1
rate: 10.0
surface: {type: plane, pose: {xyz: [0.0, 0.0, 1.0], rpy: [3.141592653589793, 0.0, 0.0]},
          extent: [[-1.0, 1.0], [-1.0, 1.0]]}
curve: {type: ellipse, center: [0.0, 0.0, 0.99], axis_a: [0.1, 0.0, 0.0],
        axis_b: [0.0, 0.05, 0.0]}
cameras:
  left: {width: 640, height: 480, fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0,
         pose: {xyz: [-0.05, 0.0, 0.0], rpy: [0.0, 0.0, 0.0]}}
  right: {width: 640, height: 480, fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0,
          pose: {xyz: [0.05, 0.0, 0.0], rpy: [0.0, 0.0, 0.0]}}
  aux: {width: 640, height: 480, fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0,
        pose: {position: [0.0, -0.2, 0.0], look_at: [0.0, 0.0, 1.0]}}
lighting: {direction: [0.0, 0.0, -1.0]}
calibration:
  rows: 5
  cols: 6
  spacing: 0.02
  poses: [{xyz: [-0.05, -0.04, 0.5], rpy: [0.0, 0.0, 0.0]}]
robot: {initial_joints: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]}
contact: {stiffness: 1000.0}
"""


def minimal():
    return yaml.safe_load(MINIMAL)


def edited(data, key, value=...):
    """A deep copy of ``data`` with the dotted ``key`` set to ``value`` (deleted if omitted)."""
    data = copy.deepcopy(data)
    *parents, last = key.split('.')
    node = data
    for part in parents:
        node = node[part]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return data


def assert_one_error(error_info, key):
    """One ScenarioError, not a chain: one line that starts with the key, which it carries."""
    error = error_info.value
    message = str(error)
    assert type(error) is ScenarioError
    assert error.key == key
    assert message.startswith(f'{key}:'), message
    assert '\n' not in message
    assert error.__cause__ is None
    assert error.__context__ is None or error.__suppress_context__


def test_documented_example_loads():
    text = (Path(__file__).resolve().parents[2] / 'docs' / 'SCENARIO.md').read_text()
    example = text.split('## Example', 1)[1].split('```yaml\n', 1)[1].split('```', 1)[0]
    scenario = parse_scenario(yaml.safe_load(example))
    assert scenario.cameras['right'].distortion_model == 'division'


def test_the_tool_is_the_models_own_unless_given(tmp_path):
    """The PA-10 models carry their 0.1 m tool; a URDF's tip frame is the tool tip as its
    author wrote it; a tip frame and tool length given are taken as they are."""
    from vgm_common.robot_model import pa10_urdf

    assert parse_scenario(minimal()).robot.tool_length == 0.1
    (tmp_path / 'arm.urdf').write_text(pa10_urdf('pa10', 0.1))
    data = edited(minimal(), 'robot.model', 'arm.urdf')
    robot = parse_scenario(data, tmp_path / 'scenario.yaml').robot
    assert (robot.tool_length, robot.tip_frame) == (0.0, 'tool0')
    data = edited(edited(data, 'robot.tip_frame', 'pa10_link7'), 'robot.tool_length', 0.05)
    robot = parse_scenario(data, tmp_path / 'scenario.yaml').robot
    assert (robot.tool_length, robot.tip_frame) == (0.05, 'pa10_link7')


def test_minimal_scenario_is_valid():
    scenario = parse_scenario(minimal())
    assert scenario.calibration.rows == 5
    assert scenario.cameras['left'].distortion_model == 'plumb_bob'


BAD = [
    # missing keys
    ('cameras.right.fx', ...),
    ('contact.stiffness', ...),
    ('surface.type', ...),
    ('robot.initial_joints', ...),
    # wrong types
    ('cameras.left.fx', 'six hundred'),  # a string where a number is expected
    ('seed', True),  # a bool where an int is expected
    ('cameras.left.width', True),
    ('calibration.rows', 5.0),  # a float where an int is expected
    ('rate', [10.0]),
    ('lighting.direction', 'down'),
    ('robot.initial_joints', [0.0] * 6),
    # values out of range
    ('cameras.aux.fy', -500.0),
    ('curve.contrast', 1.5),
    ('lighting.direction', [0.0, 0.0, 0.0]),
    ('curve.axis_b', [0.0, 0.05]),
    # unknown names
    ('surface.type', 'torus'),
    ('curve.type', 'spiral'),
    ('cameras.left.distortion_model', 'fisheye'),
    ('robot.tip_frame', 'flange'),  # no such frame in the model
]


@pytest.mark.parametrize('key, value', BAD, ids=[f'{k}={v!r}' for k, v in BAD])
def test_bad_value_names_its_key(key, value):
    with pytest.raises(ScenarioError) as info:
        parse_scenario(edited(minimal(), key, value))
    assert_one_error(info, key)


@pytest.mark.parametrize(
    'key, text',
    [
        ('lighting.intensity', '.nan'),
        ('cameras.aux.fy', '.inf'),
        ('cameras.left.cx', '-.inf'),
        ('surface.pose.xyz', '[0.0, .nan, 1.0]'),
    ],
)
def test_non_finite_yaml_number_names_its_key(tmp_path, key, text):
    data = edited(minimal(), key, '@@')
    path = tmp_path / 'scenario.yaml'
    path.write_text(yaml.safe_dump(data).replace("'@@'", text))
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert_one_error(info, key)


def test_circle_needs_a_normal():
    data = edited(
        minimal(),
        'curve',
        {'type': 'circle', 'center': [0.0, 0.0, 0.99], 'normal': [0.0, 0.0, 0.0], 'radius': 0.1},
    )
    with pytest.raises(ScenarioError) as info:
        parse_scenario(data)
    assert_one_error(info, 'curve.normal')


def test_camera_looking_away_names_its_pose():
    data = edited(
        minimal(), 'cameras.aux.pose', {'position': [0.0, -0.2, 0.0], 'look_at': [0.0, -0.2, -1.0]}
    )
    with pytest.raises(ScenarioError) as info:
        parse_scenario(data)
    assert_one_error(info, 'cameras.aux.pose')
    assert 'looks away' in str(info.value)


def test_chessboard_with_even_rows_plus_cols_is_refused():
    data = edited(edited(minimal(), 'calibration.rows', 6), 'calibration.cols', 8)
    with pytest.raises(ScenarioError) as info:
        parse_scenario(data)
    assert_one_error(info, 'calibration.rows')
    assert 'odd' in str(info.value)


@pytest.mark.parametrize(
    'model, distortion',
    [
        ('division', [0.1, 0.0]),
        ('plumb_bob', [0.1]),
        ('division', ['kappa']),
        ('equidistant', [0.1] * 5),
        ('rational_polynomial', [0.1] * 5),
    ],
)
def test_distortion_must_fit_its_model(model, distortion):
    data = edited(
        edited(minimal(), 'cameras.left.distortion_model', model),
        'cameras.left.distortion',
        distortion,
    )
    with pytest.raises(ScenarioError) as info:
        parse_scenario(data)
    assert_one_error(info, 'cameras.left.distortion')


def test_division_camera_is_read():
    data = edited(
        edited(minimal(), 'cameras.left.distortion_model', 'division'),
        'cameras.left.distortion',
        [15.152],
    )
    camera = parse_scenario(data).cameras['left']
    assert camera.distortion_model == 'division'
    assert camera.D.tolist() == [15.152]


@pytest.mark.parametrize(
    'model, distortion',
    [
        ('rational_polynomial', [0.4, 0.05, 1e-3, -1e-3, 0.0, 0.8, 0.06, 0.0]),
        ('equidistant', [0.03, -0.008, 0.002, -0.0005]),
    ],
)
def test_wide_lens_camera_is_read_and_renders_through_its_model(model, distortion):
    """The scenario's camera of a CameraInfo model projects as OpenCV does (what the
    renderer draws through): a point at 60 deg off the axis."""
    import cv2

    data = edited(
        edited(minimal(), 'cameras.left.distortion_model', model),
        'cameras.left.distortion',
        distortion,
    )
    camera = parse_scenario(data).cameras['left']
    assert camera.distortion_model == model
    point_camera = np.array([[np.sin(np.radians(60)), 0.0, np.cos(np.radians(60))]])
    T = camera.T_base_camera
    pixel, _ = camera.project(point_camera @ T[:3, :3].T + T[:3, 3])
    zero = np.zeros(3)
    if model == 'equidistant':
        expected = cv2.fisheye.projectPoints(
            point_camera.reshape(-1, 1, 3), zero, zero, camera.K, np.array(distortion)
        )[0]
    else:
        expected = cv2.projectPoints(point_camera, zero, zero, camera.K, np.array(distortion))[0]
    np.testing.assert_allclose(pixel, expected.reshape(1, 2), atol=1e-9)


POINTS_CSV = {
    'plain': '0.0,0.0,0.99\n0.1,0.0,0.99\n0.1,0.05,0.99\n',
    'header': 'x,y,z\n0.0,0.0,0.99\n0.1,0.0,0.99\n0.1,0.05,0.99\n',
    'comments, blanks, spaces, CRLF': (
        '# curve samples [m]\r\n\r\n0.0, 0.0, 0.99\r\n'
        '0.1, 0.0, 0.99  # second\r\n0.1, 0.05, 0.99\r\n'
    ),
}


@pytest.mark.parametrize('text', POINTS_CSV.values(), ids=POINTS_CSV.keys())
def test_points_curve_reads_csv(tmp_path, text):
    (tmp_path / 'curve.csv').write_text(text, newline='')
    data = edited(minimal(), 'curve', {'type': 'points', 'file': 'curve.csv', 'closed': True})
    scenario = parse_scenario(data, tmp_path / 'scenario.yaml')  # relative to the scenario
    expected = [[0.0, 0.0, 0.99], [0.1, 0.0, 0.99], [0.1, 0.05, 0.99]]
    assert np.array_equal(scenario.curve.params['points'], expected)
    assert scenario.curve.params['closed'] is True
    absolute = edited(data, 'curve.file', str(tmp_path / 'curve.csv'))
    assert np.array_equal(parse_scenario(absolute).curve.params['points'], expected)


@pytest.mark.parametrize(
    'text',
    [None, '', 'x,y,z\n', '0,0,1\n0,0.1,a\n', '0,0\n1,1\n', '0,0,1\n', '0,0,1\n0,nan,1\n'],
    ids=['missing', 'empty', 'header only', 'not a number', 'two columns', 'one row', 'nan'],
)
def test_unreadable_points_csv_names_curve_file(tmp_path, text):
    if text is not None:
        (tmp_path / 'curve.csv').write_text(text)
    data = edited(minimal(), 'curve', {'type': 'points', 'file': 'curve.csv'})
    with pytest.raises(ScenarioError) as info:
        parse_scenario(data, tmp_path / 'scenario.yaml')
    assert_one_error(info, 'curve.file')


def test_points_closed_must_be_a_boolean(tmp_path):
    (tmp_path / 'curve.csv').write_text(POINTS_CSV['plain'])
    data = edited(minimal(), 'curve', {'type': 'points', 'file': 'curve.csv', 'closed': 'no'})
    with pytest.raises(ScenarioError) as info:
        parse_scenario(data, tmp_path / 'scenario.yaml')
    assert_one_error(info, 'curve.closed')


def test_unreadable_scenario_file_is_one_error(tmp_path):
    with pytest.raises(ScenarioError):
        load_scenario(tmp_path / 'missing.yaml')
    (tmp_path / 'broken.yaml').write_text('surface: [unclosed\n')
    with pytest.raises(ScenarioError):
        load_scenario(tmp_path / 'broken.yaml')


# --------------------------------------------------------------------------- poses


def test_the_three_pose_forms_give_the_same_transform():
    position, target, up = np.array([0.03, -0.1, 0.05]), np.array([0.0, 0.02, 0.99]), [0, -1, 0]
    R = look_at_rotation(position, target, up)
    rpy = [np.arctan2(R[2, 1], R[2, 2]), -np.arcsin(R[2, 0]), np.arctan2(R[1, 0], R[0, 0])]
    assert np.allclose(rpy_to_matrix(*rpy), R, atol=1e-14)
    forms = [
        {'position': position.tolist(), 'look_at': target.tolist(), 'up': up},
        {'xyz': position.tolist(), 'rpy': [float(a) for a in rpy]},
        {'xyz': position.tolist(), 'quaternion': matrix_to_quaternion(R).tolist()},
    ]
    transforms = [
        parse_scenario(edited(minimal(), 'cameras.aux.pose', form)).cameras['aux'].T_base_camera
        for form in forms
    ]
    for T in transforms:
        assert np.allclose(T, make_transform(R, position), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- camera models


def random_camera_points(rng, count, camera):
    """Points in base_link whose optical-frame direction is within the image's field."""
    xy = rng.uniform([-0.6, -0.45], [0.6, 0.45], size=(count, 2))
    depth = rng.uniform(0.5, 3.0, count)
    points_camera = np.column_stack([xy * depth[:, None], depth])
    return points_camera @ camera.T_base_camera[:3, :3].T + camera.T_base_camera[:3, 3], xy


def random_pose(rng):
    return make_transform(rpy_to_matrix(*rng.uniform(-np.pi, np.pi, 3)), rng.normal(0, 1, 3))


@pytest.mark.parametrize('kappa', [15.152, 94.7, 0.5, 1e-9, 0.0, -0.2])
def test_division_projection_and_undistortion_are_inverse(kappa):
    rng = np.random.default_rng(4)
    K = np.array([[800.0, 0.0, 300.0], [0.0, 780.0, 250.0], [0.0, 0.0, 1.0]])
    camera = PinholeCamera(640, 480, K, [kappa], random_pose(rng), 'division')
    points_base, xy = random_camera_points(rng, 500, camera)
    pixels, depth = camera.project(points_base)
    assert np.all(np.isfinite(pixels))
    assert np.allclose(camera.undistort_pixels(pixels), xy, rtol=0, atol=1e-12)
    # and the other way round: pixels -> rays -> pixels
    rays = camera.pixel_rays_base(pixels)
    back, _ = camera.project(camera.centre_base + 2.0 * rays)
    assert np.allclose(back, pixels, rtol=0, atol=1e-9)


def test_division_agrees_with_the_seed_formula():
    rng = np.random.default_rng(43)
    for f, N, u0, v0, k in [
        (10, 200, 20, 19, 0.15152),
        (25, 144, 256, 192, 0.15152),
        (8.95, 204, 21, 19, 0.1439),
    ]:
        R = rpy_to_matrix(*rng.uniform(-0.3, 0.3, 3))
        T = rng.uniform([-50, -50, 900], [50, 50, 1500])
        points = rng.uniform(-100, 100, size=(300, 3))
        camera = camera_from_seed(640, 480, f, N, u0, v0, k, R, T, scale=MM)
        pixels, _ = camera.project(points * MM)
        expected = seed_division_project(points, f, N, u0, v0, k, R, T)
        assert np.max(np.abs(pixels - expected)) < 1e-9


def test_division_beyond_the_fold_gives_nan():
    """With kappa < 0, x_d = x_u / (1 + kappa |x_d|^2) has no solution for |x_u| past
    2 / (3 sqrt(-3 kappa)); such points must not get a pixel."""
    kappa = -0.3
    fold = 2 / (3 * np.sqrt(-3 * kappa))
    camera = PinholeCamera(640, 480, np.diag([500.0, 500.0, 1.0]), [kappa], np.eye(4), 'division')
    pixels, _ = camera.project(np.array([[0.9 * fold, 0.0, 1.0], [1.1 * fold, 0.0, 1.0]]))
    assert np.all(np.isfinite(pixels[0])) and np.all(np.isnan(pixels[1]))


def test_plumb_bob_agrees_with_opencv():
    rng = np.random.default_rng(5)
    K = np.array([[610.0, 0.0, 318.0], [0.0, 605.0, 243.0], [0.0, 0.0, 1.0]])
    for D in ([-0.28, 0.09, 0.001, -0.0015, -0.01], [0.05, -0.02, 0.0, 0.0, 0.0], [0.0] * 5):
        camera = PinholeCamera(640, 480, K, D, random_pose(rng))
        points_base, xy = random_camera_points(rng, 400, camera)
        pixels, _ = camera.project(points_base)
        T_camera_base = camera.T_camera_base
        rvec, _ = cv2.Rodrigues(T_camera_base[:3, :3])
        expected, _ = cv2.projectPoints(points_base, rvec, T_camera_base[:3, 3], K, np.array(D))
        assert np.max(np.abs(pixels - expected.reshape(-1, 2))) < 1e-9
        assert np.allclose(camera.undistort_pixels(pixels), xy, rtol=0, atol=1e-9)


def test_unknown_distortion_model_is_refused():
    with pytest.raises(InvalidInput):
        PinholeCamera(640, 480, np.eye(3), [0.0] * 5, np.eye(4), 'fisheye')
    with pytest.raises(InvalidInput):
        PinholeCamera(640, 480, np.eye(3), [0.0] * 5, np.eye(4), 'division')


def test_a_handheld_chart_covers_the_images_as_a_handheld_calibration_asks():
    """calibration.motion handheld: the hand's poses are seeded, show every corner to
    every camera, and spread over the left image as calib_node's coverage rule (with its
    default min_coverage 0.5) requires."""
    from calib_node.coverage import Coverage, view_parameters
    from sensor_sim.chart import chart_corners_chart
    from sensor_sim.scenario import with_chart_motion

    stage = load_scenario(SCENARIO_DIR / 'default.yaml')
    handheld = with_chart_motion(stage, 'handheld')
    again = with_chart_motion(stage, 'handheld')
    calibration = handheld.calibration
    assert calibration.motion == 'handheld' and len(calibration.T_base_chart) == 24
    np.testing.assert_array_equal(calibration.T_base_chart, again.calibration.T_base_chart)
    assert with_chart_motion(handheld, 'stage').calibration.T_base_chart == (
        stage.calibration.T_base_chart
    )
    corners = chart_corners_chart(calibration.rows, calibration.cols, calibration.spacing)
    coverage = Coverage()
    for T in calibration.T_base_chart:
        for name, camera in handheld.cameras.items():
            pixels, depth = camera.project(corners @ T[:3, :3].T + T[:3, 3])
            assert np.all(depth > 0) and np.all(pixels >= 0), name
            assert np.all(pixels < [camera.width, camera.height]), name
        left = handheld.cameras['left']
        pixels, _ = left.project(corners @ T[:3, :3].T + T[:3, 3])
        parameters = view_parameters(
            pixels, calibration.rows, calibration.cols, (left.width, left.height)
        )
        if coverage.is_new(parameters):
            coverage.add(parameters)
    assert len(coverage.kept) >= 10 and coverage.missing(0.5) == '', coverage.summary()
