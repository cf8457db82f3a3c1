"""Scenario files: the simulator's input (INTERFACES.md, "The scenario file").

``load_scenario(path)`` reads a YAML file, checks every key and returns a frozen
``Scenario``. Any problem raises ``ScenarioError`` whose message names the key, e.g.
``cameras.left.fx: expected a positive number, got -3``. The full format is documented
in docs/SCENARIO.md; units are SI (metres, radians, newtons, seconds) unless a key says
otherwise.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vgm_common.camera_model import DISTORTION_MODELS, DISTORTION_SIZES, PinholeCamera
from vgm_common.errors import ScenarioError
from vgm_common.geometry import (
    FloatArray,
    look_at_rotation,
    make_transform,
    quaternion_to_matrix,
    rpy_to_matrix,
)
from vgm_common.topics import TOOL_FRAME

SURFACE_TYPES = ('plane', 'S1', 'S2', 'S3', 'vase', 'sphere', 'heightmap')
CURVE_TYPES = ('parabola', 'ellipse', 'circle', 'line_pair', 'cubic', 'surface_loop', 'points')
CAMERA_NAMES = ('left', 'right', 'aux')
CHART_PATTERNS = ('chessboard', 'charuco')
CHART_MOTIONS = ('stage', 'handheld')  # how the chart is shown for calibration
CurveParameter = FloatArray | float | bool  # a value of Curve.params


@dataclass(frozen=True)
class Surface:
    """A height field z = h(x, y) in the surface frame, scaled and posed in base_link.

    ``kind`` names h (see sensor_sim.surfaces); the formula is evaluated in surface units
    and every coordinate is multiplied by ``scale`` [m/unit] before ``T_base_surface``.
    """

    kind: str
    T_base_surface: np.ndarray
    scale: float
    extent: tuple  # ((x_min, x_max), (y_min, y_max)) [surface units]
    albedo: float
    roughness: float  # Oren-Nayar sigma [rad]; 0 = Lambertian
    radius: float = 1.0  # sphere only [surface units]
    heights: np.ndarray | None = None  # heightmap only: z grid, rows along y
    cell: float = 1.0  # heightmap only: grid spacing [surface units]


@dataclass(frozen=True)
class Curve:
    """The dark curve drawn in the scene. Geometry per ``kind``; see docs/SCENARIO.md."""

    kind: str
    line_width_px: float
    contrast: float  # fraction of the brightness removed on the line, in (0, 1]
    samples: int
    params: dict[str, CurveParameter] = field(default_factory=dict)


@dataclass(frozen=True)
class Lighting:
    """The distant light: its direction in base_link, intensity and ambient term (grey
    level = 255 albedo (intensity R + ambient), R the Oren-Nayar factor)."""

    direction_base: np.ndarray  # unit vector from the surface toward the (distant) light
    intensity: float
    ambient: float


@dataclass(frozen=True)
class Noise:
    """Standard deviations of the Gaussian sensor noise: on every pixel and on the pressure
    sensor."""

    image_sigma: float  # [grey levels]
    pressure_sigma: float  # [N]


@dataclass(frozen=True)
class Calibration:
    """The calibration stage: the chart (pattern, inner corners, square size; a ChArUco
    board's marker size and ArUco dictionary), the captures taken at each pose and the
    chart's stage poses in base_link."""

    pattern: str
    rows: int  # inner corners
    cols: int
    spacing: float  # [m]
    captures_per_pose: int
    T_base_chart: tuple[FloatArray, ...]  # one 4x4 pose per view shown
    motion: str = 'stage'  # 'handheld': T_base_chart are a hand's poses around the stage's
    handheld_views: int = 24  # how many a hand shows
    T_base_stage: tuple[FloatArray, ...] = ()  # the stage poses as the file gives them
    dictionary: str = 'DICT_5X5_100'  # charuco: the predefined ArUco dictionary
    marker_size: float = 0.0  # charuco: marker side [m]; 0: 0.75 spacing


@dataclass(frozen=True)
class Robot:
    """The arm: its model (checked to load when the scenario is), start joints, the tip
    frame (z = approach axis; the pressure is stamped in it) and the tool length added
    beyond it."""

    model: str  # 'pa10', 'pa10_thesis' or a URDF path
    initial_joints: np.ndarray  # [rad] (7,)
    tool_length: float  # [m]
    tip_frame: str = TOOL_FRAME
    base_frame: str = ''  # where the arm's chain starts ('': the URDF's root)
    base_placement: tuple[float, ...] = (0.0,) * 6  # base_frame in base_link: xyz [m], rpy [rad]


@dataclass(frozen=True)
class Scenario:
    """A whole scenario file, validated: scene, cameras, light, noise, calibration stage,
    arm and contact; see docs/SCENARIO.md."""

    name: str
    path: Path
    seed: int
    rate: float  # camera frame rate [Hz]
    surface: Surface
    curve: Curve
    cameras: dict[str, PinholeCamera]  # 'left' | 'right' | 'aux' -> the true cameras
    lighting: Lighting
    noise: Noise
    calibration: Calibration | None
    robot: Robot
    contact_stiffness: float  # [N/m]


class _Section:
    """A mapping being validated, which knows its dotted key path for error messages."""

    data: dict[str, Any]  # parsed YAML: values of any type
    key: str

    def __init__(self, data: object, key: str) -> None:
        if not isinstance(data, dict):
            raise ScenarioError(f'{key}: expected a mapping, got {data!r}', key=key)
        self.data, self.key = data, key

    def path(self, name: str) -> str:
        return f'{self.key}.{name}' if self.key else name

    def has(self, name: str) -> bool:
        return name in self.data

    def raw(self, name: str, default: object = ...) -> Any:
        if name not in self.data:
            if default is ...:
                raise ScenarioError(
                    f'{self.path(name)}: required key is missing', key=self.path(name)
                )
            return default
        return self.data[name]

    def section(self, name: str, default: object = ...) -> _Section:
        return _Section(self.raw(name, default), self.path(name))

    def number(
        self,
        name: str,
        default: object = ...,
        minimum: float | None = None,
        maximum: float | None = None,
        positive: bool = False,
    ) -> float:
        value = self.raw(name, default)
        key = self.path(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ScenarioError(f'{key}: expected a number, got {value!r}', key=key)
        value = float(value)
        if not math.isfinite(value):
            raise ScenarioError(f'{key}: expected a finite number, got {value!r}', key=key)
        if positive and value <= 0:
            raise ScenarioError(f'{key}: expected a positive number, got {value!r}', key=key)
        if minimum is not None and value < minimum:
            raise ScenarioError(f'{key}: must be >= {minimum}, got {value!r}', key=key)
        if maximum is not None and value > maximum:
            raise ScenarioError(f'{key}: must be <= {maximum}, got {value!r}', key=key)
        return value

    def integer(self, name: str, default: object = ..., minimum: int | None = None) -> int:
        value = self.raw(name, default)
        key = self.path(name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ScenarioError(f'{key}: expected an integer, got {value!r}', key=key)
        if minimum is not None and value < minimum:
            raise ScenarioError(f'{key}: must be >= {minimum}, got {value!r}', key=key)
        return value

    def boolean(self, name: str, default: object = ...) -> bool:
        value = self.raw(name, default)
        if not isinstance(value, bool):
            key = self.path(name)
            raise ScenarioError(f'{key}: expected true or false, got {value!r}', key=key)
        return value

    def string(
        self, name: str, default: object = ..., choices: Sequence[str] | None = None
    ) -> str:
        value = self.raw(name, default)
        key = self.path(name)
        if not isinstance(value, str):
            raise ScenarioError(f'{key}: expected a string, got {value!r}', key=key)
        if choices is not None and value not in choices:
            raise ScenarioError(
                f'{key}: expected one of {", ".join(choices)}, got {value!r}', key=key
            )
        return value

    def vector(
        self,
        name: str,
        length: int | None = None,
        default: object = ...,
        shape: tuple[int, ...] | None = None,
    ) -> FloatArray:
        value = self.raw(name, default)
        key = self.path(name)
        try:
            if isinstance(value, (str, bytes)):
                raise TypeError
            array = np.array(value, dtype=float)
        except (TypeError, ValueError):
            raise ScenarioError(
                f'{key}: expected a list of numbers, got {value!r}', key=key
            ) from None
        expected = shape or ((length,) if length else None)
        if (expected and array.shape != expected) or (not expected and array.ndim != 1):
            want = 'x'.join(map(str, expected)) if expected else 'a flat list'
            raise ScenarioError(f'{key}: expected {want} numbers, got {value!r}', key=key)
        if not np.all(np.isfinite(array)):
            raise ScenarioError(f'{key}: expected finite numbers, got {value!r}', key=key)
        return array

    def pose(self, name: str, default: object = ...) -> FloatArray:
        """A pose in base_link: {xyz, rpy} | {xyz, quaternion: [x, y, z, w]} |
        {position, look_at[, up]} (camera optical frame looking at a point)."""
        pose = self.section(name, default)
        if pose.has('look_at'):
            position = pose.vector('position', 3)
            target = pose.vector('look_at', 3)
            if np.linalg.norm(target - position) < 1e-9:
                raise ScenarioError(
                    f'{pose.path("look_at")}: equals position', key=pose.path('look_at')
                )
            up = pose.vector('up', 3, default=[0.0, 0.0, 1.0])
            return make_transform(look_at_rotation(position, target, up), position)
        xyz = pose.vector('xyz', 3)
        if pose.has('quaternion'):
            q = pose.vector('quaternion', 4)
            if np.linalg.norm(q) < 1e-9:
                raise ScenarioError(
                    f'{pose.path("quaternion")}: zero quaternion', key=pose.path('quaternion')
                )
            return make_transform(quaternion_to_matrix(q), xyz)
        return make_transform(rpy_to_matrix(*pose.vector('rpy', 3, default=[0, 0, 0])), xyz)


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML file. Raises ScenarioError naming the bad key."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as error:
        raise ScenarioError(f'cannot read scenario file {path}: {error.strerror}') from None
    except yaml.YAMLError as error:
        raise ScenarioError(f'{path} is not valid YAML: {error}') from None
    return parse_scenario(data, path)


def parse_scenario(data: object, path: str | Path = Path('scenario.yaml')) -> Scenario:
    """Validate an already parsed scenario mapping; relative files resolve beside ``path``."""
    root = _Section(data, '')
    base_dir = Path(path).parent
    surface = _parse_surface(root.section('surface'), base_dir)
    cameras = {name: _parse_camera(root.section('cameras').section(name)) for name in CAMERA_NAMES}
    lighting = root.section('lighting')
    direction = lighting.vector('direction', 3)
    if np.linalg.norm(direction) < 1e-9:
        raise ScenarioError('lighting.direction: must not be zero', key='lighting.direction')
    noise = root.section('noise', default={})
    robot = root.section('robot')
    scenario = Scenario(
        name=root.string('name', default=Path(path).stem),
        path=Path(path),
        seed=root.integer('seed', minimum=0),
        rate=root.number('rate', positive=True),
        surface=surface,
        curve=_parse_curve(root.section('curve'), base_dir),
        cameras=cameras,
        lighting=Lighting(
            direction / np.linalg.norm(direction),
            lighting.number('intensity', default=1.0, minimum=0.0),
            lighting.number('ambient', default=0.05, minimum=0.0),
        ),
        noise=Noise(
            noise.number('image_sigma', default=0.0, minimum=0.0),
            noise.number('pressure_sigma', default=0.0, minimum=0.0),
        ),
        calibration=(
            _parse_calibration(root.section('calibration')) if root.has('calibration') else None
        ),
        robot=_parse_robot(robot, base_dir),
        contact_stiffness=root.section('contact').number('stiffness', positive=True),
    )
    _check_cameras_see_surface(scenario)
    if scenario.calibration is not None:
        scenario = with_chart_motion(scenario, scenario.calibration.motion)
    return scenario


def _parse_robot(section: _Section, base_dir: Path) -> Robot:
    """robot: the model ('pa10', 'pa10_thesis' or a URDF path, relative to the scenario
    file), its tip frame and the tool beyond it (default: the model's own, 0.1 m for the
    PA-10 models, none for a URDF), loaded here so that a URDF that is no 7-DOF arm with
    that frame and joint limits, or start joints outside them, is a scenario error naming
    the key."""
    from vgm_common.errors import InvalidInput
    from vgm_common.robot_model import PARAMETER_SETS, load_robot, own_tool_length

    model = section.string('model', default='pa10')
    if model not in PARAMETER_SETS:
        model = str(base_dir / model)
    initial_joints = section.vector('initial_joints', 7)
    tool_length = section.number('tool_length', default=own_tool_length(model), minimum=0.0)
    tip_frame = section.string('tip_frame', default=TOOL_FRAME)
    base_frame = section.string('base_frame', default='')
    base_placement = tuple(section.vector('base_placement', 6, default=[0.0] * 6).tolist())
    try:
        robot = load_robot(
            model, tool_length, tip_frame, base_frame=base_frame, base_placement=base_placement
        )
    except InvalidInput as error:
        named = error.key if error.key in ('tip_frame', 'base_frame', 'base_placement') else None
        key = section.path(named or 'model')
        raise ScenarioError(f'{key}: {error}', key=key) from None
    outside = (initial_joints < robot.lower_limits) | (initial_joints > robot.upper_limits)
    if np.any(outside):
        i = int(np.flatnonzero(outside)[0])
        raise ScenarioError(
            f'{section.path("initial_joints")}: {robot.joint_names[i]} at '
            f'{initial_joints[i]} rad is outside its limits '
            f'[{robot.lower_limits[i]:.4g}, {robot.upper_limits[i]:.4g}]',
            key=section.path('initial_joints'),
        )
    return Robot(model, initial_joints, tool_length, tip_frame, base_frame, base_placement)


def _parse_surface(section: _Section, base_dir: Path) -> Surface:
    kind = section.string('type', choices=SURFACE_TYPES)
    extent = section.vector('extent', shape=(2, 2), default=[[-1, 1], [-1, 1]])
    for axis, (low, high) in zip('xy', extent):
        if not low < high:
            raise ScenarioError(
                f'{section.path("extent")}: {axis} range must increase', key=section.path('extent')
            )
    heights, cell = None, 1.0
    if kind == 'heightmap':
        file_key = section.path('file')
        file = base_dir / section.string('file')
        try:
            heights = np.load(file) if file.suffix == '.npy' else _read_csv(file)
        except (OSError, ValueError) as error:
            raise ScenarioError(
                f'{file_key}: cannot read height map {file}: {error}', key=file_key
            ) from None
        if heights.ndim != 2 or min(heights.shape) < 2 or not np.all(np.isfinite(heights)):
            raise ScenarioError(
                f'{file_key}: expected a finite 2D grid of at least 2x2', key=file_key
            )
        heights.setflags(write=False)
        cell = section.number('cell', positive=True)
    return Surface(
        kind=kind,
        T_base_surface=section.pose('pose', default={'xyz': [0, 0, 0]}),
        scale=section.number('scale', default=1.0, positive=True),
        extent=tuple(map(tuple, extent)),
        albedo=section.number('albedo', default=0.8, minimum=0.0, maximum=1.0),
        roughness=section.number('roughness', default=0.0, minimum=0.0, maximum=math.pi / 2),
        radius=section.number('radius', default=1.0, positive=True),
        heights=heights,
        cell=cell,
    )


def _parse_curve(section: _Section, base_dir: Path) -> Curve:
    kind = section.string('type', choices=CURVE_TYPES)
    params: dict[str, CurveParameter] = {}
    if kind in ('parabola', 'cubic'):
        degree = 2 if kind == 'parabola' else 3
        coefficients = section.vector('coefficients', shape=(3, degree + 1))
        params = {
            'coefficients': coefficients,
            't_range': section.vector('t_range', 2, default=[-1.0, 1.0]),
        }
    elif kind == 'ellipse':
        params = {
            'center': section.vector('center', 3),
            'axis_a': section.vector('axis_a', 3),
            'axis_b': section.vector('axis_b', 3),
        }
    elif kind == 'circle':
        params = {
            'center': section.vector('center', 3),
            'normal': section.vector('normal', 3),
            'radius': section.number('radius', positive=True),
        }
        if np.linalg.norm(params['normal']) < 1e-9:
            raise ScenarioError(
                f'{section.path("normal")}: must not be zero', key=section.path('normal')
            )
    elif kind == 'line_pair':
        params = {'segments': section.vector('segments', shape=(2, 2, 3))}
    elif kind == 'surface_loop':
        params = {
            'center': section.vector('center', 2),
            'radii': section.vector('radii', 2),
            'angle': section.number('angle', default=0.0),
        }
        if np.any(params['radii'] <= 0):
            raise ScenarioError(
                f'{section.path("radii")}: must be positive', key=section.path('radii')
            )
    elif kind == 'points':
        file_key = section.path('file')
        file = base_dir / section.string('file')
        try:
            points = _read_csv(file)
        except (OSError, ValueError) as error:
            raise ScenarioError(
                f'{file_key}: cannot read curve points {file}: {error}', key=file_key
            ) from None
        if points.shape[1] != 3 or len(points) < 2 or not np.all(np.isfinite(points)):
            raise ScenarioError(
                f'{file_key}: expected finite x,y,z rows (at least 2)', key=file_key
            )
        params = {'points': points, 'closed': section.boolean('closed', default=False)}
    return Curve(
        kind=kind,
        line_width_px=section.number('line_width_px', default=3.0, positive=True),
        contrast=section.number('contrast', default=0.7, minimum=0.0, maximum=1.0),
        samples=section.integer('samples', default=2000, minimum=2),
        params=params,
    )


def _read_csv(file: str | Path) -> FloatArray:
    """Comma-separated numbers as an (N, M) array; '#' comments and one leading header
    line of column names (e.g. ``x,y,z``) are skipped. Raises OSError / ValueError."""
    lines = [line.split('#')[0].strip() for line in Path(file).read_text().splitlines()]
    lines = [line for line in lines if line]
    # A header has no number in it; a row with some numbers is data, even if malformed.
    if lines and not any(_is_number(cell) for cell in lines[0].split(',')):
        lines = lines[1:]
    if not lines:
        raise ValueError('no numeric rows')
    return np.loadtxt(lines, delimiter=',', ndmin=2)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _parse_camera(section: _Section) -> PinholeCamera:
    width = section.integer('width', minimum=1)
    height = section.integer('height', minimum=1)
    fx = section.number('fx', positive=True)
    fy = section.number('fy', positive=True)
    K = np.array(
        [[fx, 0.0, section.number('cx')], [0.0, fy, section.number('cy')], [0.0, 0.0, 1.0]]
    )
    # plumb_bob: D = (k1, k2, p1, p2, k3); division (the thesis's chapter 4): D = (kappa,)
    model = section.string('distortion_model', default='plumb_bob', choices=DISTORTION_MODELS)
    size = DISTORTION_SIZES[model]
    D = section.vector('distortion', size, default=[0.0] * size)
    return PinholeCamera(width, height, K, D, section.pose('pose'), model)


def _parse_calibration(section: _Section) -> Calibration:
    from vgm_common.charuco import charuco_board

    pattern = section.string('pattern', default='chessboard', choices=CHART_PATTERNS)
    rows = section.integer('rows', minimum=2)
    cols = section.integer('cols', minimum=2)
    spacing = section.number('spacing', positive=True)
    dictionary = section.string('dictionary', default='DICT_5X5_100')
    marker_size = section.number('marker_size', default=0.0, minimum=0.0)
    if pattern == 'charuco':  # its markers' ids fix the orientation: any rows, cols
        try:
            charuco_board(rows, cols, spacing, marker_size, dictionary)
        except ValueError as error:
            raise ScenarioError(
                f'{section.path("dictionary")}: {error}', key=section.path('dictionary')
            ) from None
    elif (rows + cols) % 2 == 0:
        raise ScenarioError(
            f'{section.path("rows")}: rows + cols must be odd so the '
            'chessboard has no 180-degree symmetry',
            key=section.path('rows'),
        )
    poses = section.raw('poses')
    if not isinstance(poses, list) or not poses:
        raise ScenarioError(
            f'{section.path("poses")}: expected a non-empty list of poses',
            key=section.path('poses'),
        )
    pose_list = _Section({str(i): p for i, p in enumerate(poses)}, section.path('poses'))
    return Calibration(
        pattern=pattern,
        rows=rows,
        cols=cols,
        spacing=spacing,
        captures_per_pose=section.integer('captures_per_pose', default=1, minimum=1),
        T_base_chart=tuple(pose_list.pose(str(i)) for i in range(len(poses))),
        motion=section.string('motion', default='stage', choices=CHART_MOTIONS),
        handheld_views=section.integer('handheld_views', default=24, minimum=4),
        dictionary=dictionary,
        marker_size=marker_size,
    )


def with_chart_motion(scenario: Scenario, motion: str) -> Scenario:
    """``scenario`` with its calibration chart shown by ``motion``: 'stage' (at the stage
    poses) or 'handheld' (``handheld_views`` poses a hand shows around the stage's,
    spread over the images: sensor_sim.handheld). Raises ScenarioError if the scenario
    has no calibration section or leaves no room for a hand's poses."""
    from sensor_sim.chart import chart_corners_chart
    from sensor_sim.handheld import handheld_chart_poses

    calibration = scenario.calibration
    if calibration is None:
        raise ScenarioError('calibration: a chart motion needs a calibration section')
    if motion not in CHART_MOTIONS:
        raise ScenarioError(
            f'calibration.motion: {motion!r} is not one of {", ".join(CHART_MOTIONS)}',
            key='calibration.motion',
        )
    stage = calibration.T_base_stage or calibration.T_base_chart
    poses = stage
    if motion == 'handheld':
        corners = chart_corners_chart(calibration.rows, calibration.cols, calibration.spacing)
        poses = handheld_chart_poses(
            stage, corners, scenario.cameras, calibration.handheld_views, scenario.seed
        )
    shown = dataclasses.replace(calibration, T_base_chart=poses, motion=motion, T_base_stage=stage)
    return dataclasses.replace(scenario, calibration=shown)


def surface_centre_base(surface: Surface) -> FloatArray:
    """The surface frame origin lifted by nothing: where the scene is, in base_link."""
    (x0, x1), (y0, y1) = surface.extent
    centre_surface = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]) * surface.scale
    return surface.T_base_surface[:3, :3] @ centre_surface + surface.T_base_surface[:3, 3]


def _check_cameras_see_surface(scenario: Scenario) -> None:
    """A camera that cannot see the surface's centre is a scenario mistake: say which."""
    centre = surface_centre_base(scenario.surface)
    for name, camera in scenario.cameras.items():
        pixel, depth = camera.project(centre[None, :])
        u, v = pixel[0]
        if not (depth[0] > 0 and 0 <= u < camera.width and 0 <= v < camera.height):
            key = f'cameras.{name}.pose'
            raise ScenarioError(
                f'{key}: camera {name} looks away from the scene (the '
                f'surface centre {np.round(centre, 3).tolist()} is not in '
                'its image)',
                key=key,
            )


def resolve_scenario_path(name_or_path: str | Path) -> Path:
    """A scenario file path, or the name of one shipped with sensor_sim ('default',
    'S1', 'ch3_parabola_perfect', ...), found through the ament index."""
    path = Path(name_or_path).expanduser()
    if path.suffix in ('.yaml', '.yml') or path.exists():
        return path
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    try:
        share = Path(get_package_share_directory('sensor_sim'))
    except PackageNotFoundError:
        raise ScenarioError(
            f'scenario {name_or_path!r} is not a file and sensor_sim is '
            'not installed to look it up by name'
        ) from None
    shipped = share / 'scenarios' / f'{name_or_path}.yaml'
    if not shipped.exists():
        names = sorted(p.stem for p in (share / 'scenarios').glob('*.yaml'))
        raise ScenarioError(f'no scenario named {name_or_path!r}; shipped: {", ".join(names)}')
    return shipped
