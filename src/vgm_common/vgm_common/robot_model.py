"""Kinematic model of the 7-DOF Mitsubishi PA-10 (ALGORITHMS.md §6.2) on Pinocchio.

The PA-10 chain is

    T_base_tool(q) = Rz(q1) Tz(d1) Ry(q2) Rz(q3) Tz(d3) Ry(q4) Rz(q5) Tz(d5)
                     Ry(q6) Rz(q7) Tz(d7 + tool_length)

so the zero pose points straight up and the tool frame ``tool0`` has its z axis along the
approach direction. ``pa10_urdf`` writes that chain as a URDF; ``load_robot`` builds a
``RobotModel`` from it (or from any URDF with a ``tool0`` frame) for forward kinematics
and the geometric Jacobian.

Regenerate the committed URDFs from the repository root with
``PYTHONPATH=src/vgm_common python -m vgm_common.robot_model``.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import numpy as np
import numpy.typing as npt
import pinocchio as pin

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.topics import BASE_FRAME, TOOL_FRAME

N_JOINTS = 7
JOINT_NAMES = tuple(f'pa10_joint{i}' for i in range(1, N_JOINTS + 1))
AXES = ('z', 'y', 'z', 'y', 'z', 'y', 'z')  # S1, S2, S3, E1, E2, W1, W2
JointValues = FloatArray | Sequence[float]  # one value per joint, (n,)


def _read_only(values: npt.ArrayLike) -> FloatArray:
    array = np.array(values, dtype=float)
    array.flags.writeable = False
    return array


# Limits of the real arm, S1..W2, from the PA-10-7C spec sheet (Mitsubishi Heavy
# Industries). The thesis gives none, so both parameter sets share them.
PA10_UPPER_LIMITS_RAD = _read_only(np.deg2rad([177, 94, 174, 137, 255, 165, 255]))
PA10_LOWER_LIMITS_RAD = _read_only(-PA10_UPPER_LIMITS_RAD)
PA10_VELOCITY_LIMITS_RAD_S = _read_only([1.0, 1.0, 2.0, 2.0, 2 * np.pi, 2 * np.pi, 2 * np.pi])
PA10_EFFORT_LIMITS_NM = _read_only([232.0, 232.0, 100.0, 100.0, 14.5, 14.5, 14.5])
# Plausible link masses (arm ~35 kg with its base); they only matter for dynamics,
# which nothing here uses, but Pinocchio and RViz expect every moving link to have them.
_LINK_MASS_KG = (8.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0)
_LINK_RADIUS_M = 0.06


@dataclass(frozen=True)
class Pa10Parameters:
    """Link offsets of one PA-10 model [m] (ALGORITHMS.md §6.2)."""

    d1: float  # base to the S2 axis
    d3: float  # S2 to the E1 axis
    d5: float  # E1 to the W1 axis
    d7: float  # W1 axis to the flange


PARAMETER_SETS = {
    'pa10': Pa10Parameters(d1=0.317, d3=0.45, d5=0.48, d7=0.07),  # real PA-10-7C
    'pa10_thesis': Pa10Parameters(d1=0.0, d3=1.8, d5=3.6, d7=0.6),  # thesis; d1 not given
}
PA10_TOOL_LENGTH_M = 0.1  # [m] the shipped PA-10's tool, flange to tip


def own_tool_length(robot: str | os.PathLike[str]) -> float:
    """[m] The tool beyond the tip frame that ``robot`` carries when nobody says otherwise:
    the built-in PA-10 models' ``PA10_TOOL_LENGTH_M``, none for a URDF (its author's tip
    frame is the tool tip)."""
    return PA10_TOOL_LENGTH_M if isinstance(robot, str) and robot in PARAMETER_SETS else 0.0


def pa10_urdf(name: str, tool_length: float = 0.0) -> str:
    """URDF text of a PA-10 parameter set.

    Args:
        name: a key of ``PARAMETER_SETS`` (``'pa10'`` or ``'pa10_thesis'``).
        tool_length: [m] distance from the flange to ``tool0`` along the flange z axis.

    Returns:
        The URDF as a string: ``base_link``, ``pa10_link1``..``pa10_link7`` joined by the
        revolute ``pa10_joint1``..``pa10_joint7``, and ``tool0`` on the fixed
        ``pa10_joint_tool``.

    Raises:
        InvalidInput: unknown ``name`` or non-finite ``tool_length``.
    """
    tool_length = _finite_float(tool_length, 'tool_length')
    return pa10_like_urdf(
        _parameters(name),
        tool_length,
        name=name,
        comment=f'vgm_common.robot_model.pa10_urdf({name!r}, tool_length={_num(tool_length)})',
    )


def pa10_like_urdf(
    params: Pa10Parameters,
    tool_length: float = 0.0,
    lower: JointValues = PA10_LOWER_LIMITS_RAD,
    upper: JointValues = PA10_UPPER_LIMITS_RAD,
    velocity: JointValues = PA10_VELOCITY_LIMITS_RAD_S,
    name: str = 'pa10_like',
    comment: str | None = None,
) -> str:
    """URDF text of an arm with the PA-10's joint axes and other link offsets / limits.

    Args:
        params: ``Pa10Parameters`` (link offsets [m]).
        tool_length: [m] flange to ``tool0`` along the flange z axis.
        lower, upper: (7,) position limits [rad]; velocity: (7,) speed limits [rad/s].
        name: the robot's name; comment: what generated it (written into the file).
    """
    tool_length = _finite_float(tool_length, 'tool_length')
    # Joint i+1 sits at the end of link i; the offsets sit on the links before the y joints.
    offsets_m = [params.d1, 0.0, params.d3, 0.0, params.d5, 0.0, params.d7 + tool_length]
    lengths_m = [params.d1, 0.0, params.d3, 0.0, params.d5, 0.0, params.d7]
    comment = comment or f'{name}: {params}, tool_length={_num(tool_length)}'
    lines = [
        '<?xml version="1.0"?>',
        f'<!-- Generated by {comment}; do not edit. -->',
        f'<robot name="{name}">',
        '  <link name="base_link"/>',
    ]
    parent = BASE_FRAME
    parent_offset_m = 0.0
    for i in range(N_JOINTS):
        link = f'pa10_link{i + 1}'
        axis = {'y': '0 1 0', 'z': '0 0 1'}[AXES[i]]
        lines += [
            f'  <joint name="{JOINT_NAMES[i]}" type="revolute">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{link}"/>',
            f'    <origin xyz="0 0 {_num(parent_offset_m)}" rpy="0 0 0"/>',
            f'    <axis xyz="{axis}"/>',
            f'    <limit lower="{_num(lower[i])}" '
            f'upper="{_num(upper[i])}" '
            f'velocity="{_num(velocity[i])}" '
            f'effort="{_num(PA10_EFFORT_LIMITS_NM[i])}"/>',
            '  </joint>',
            *_link_xml(link, _LINK_MASS_KG[i], lengths_m[i]),
        ]
        parent, parent_offset_m = link, offsets_m[i]
    lines += [
        '  <joint name="pa10_joint_tool" type="fixed">',
        f'    <parent link="{parent}"/>',
        f'    <child link="{TOOL_FRAME}"/>',
        f'    <origin xyz="0 0 {_num(parent_offset_m)}" rpy="0 0 0"/>',
        '  </joint>',
        f'  <link name="{TOOL_FRAME}"/>',
        '</robot>',
    ]
    return '\n'.join(lines) + '\n'


def urdf_with_tool0(
    urdf_text: str,
    parent_link: str,
    xyz: Iterable[float] = (0.0, 0.0, 0.0),
    rpy: Iterable[float] = (0.0, 0.0, 0.0),
) -> str:
    """``urdf_text`` with a ``tool0`` link fixed to ``parent_link`` at ``xyz`` [m] /
    ``rpy`` [rad] (e.g. the Panda of example-robot-data, whose tip is ``panda_hand_tcp``).

    Raises:
        InvalidInput: not a URDF, no link ``parent_link``, or a ``tool0`` already there.
    """
    try:
        root = ElementTree.fromstring(urdf_text)
    except ElementTree.ParseError as err:
        raise InvalidInput(f'not a URDF: {err}', 'urdf') from err
    links = {link.get('name') for link in root.iter('link')}
    if parent_link not in links:
        raise InvalidInput(f'no link {parent_link!r} in the URDF', 'parent_link', parent_link)
    if TOOL_FRAME in links:
        raise InvalidInput(f'the URDF already has a {TOOL_FRAME} link', 'urdf')
    joint = ElementTree.SubElement(
        root, 'joint', name=f'{parent_link}_{TOOL_FRAME}_joint', type='fixed'
    )
    ElementTree.SubElement(joint, 'parent', link=parent_link)
    ElementTree.SubElement(joint, 'child', link=TOOL_FRAME)
    ElementTree.SubElement(
        joint, 'origin', xyz=' '.join(_num(v) for v in xyz), rpy=' '.join(_num(v) for v in rpy)
    )
    ElementTree.SubElement(root, 'link', name=TOOL_FRAME)
    return ElementTree.tostring(root, encoding='unicode')


def _link_xml(name: str, mass_kg: float, length_m: float) -> list[str]:
    """A link modelled as a solid cylinder of ``length_m`` along its z axis."""
    r = _LINK_RADIUS_M
    i_xx = mass_kg * (3 * r**2 + length_m**2) / 12
    i_zz = mass_kg * r**2 / 2
    com = f'0 0 {_num(length_m / 2)}'
    lines = [
        f'  <link name="{name}">',
        '    <inertial>',
        f'      <origin xyz="{com}" rpy="0 0 0"/>',
        f'      <mass value="{_num(mass_kg)}"/>',
        f'      <inertia ixx="{_num(i_xx)}" ixy="0" ixz="0" iyy="{_num(i_xx)}" iyz="0" '
        f'izz="{_num(i_zz)}"/>',
        '    </inertial>',
    ]
    if length_m > 0:  # joint housings of zero length get no visual
        lines += [
            '    <visual>',
            f'      <origin xyz="{com}" rpy="0 0 0"/>',
            f'      <geometry><cylinder radius="{_num(r)}" length="{_num(length_m)}"/></geometry>',
            '    </visual>',
        ]
    return lines + ['  </link>']


def _num(value: float) -> str:
    """Shortest text that parses back to the same double."""
    return repr(float(value))


def write_urdfs(directory: str | Path) -> None:
    """Write ``<name>.urdf`` (tool_length 0) for every parameter set into ``directory``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name in PARAMETER_SETS:
        (directory / f'{name}.urdf').write_text(pa10_urdf(name))


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A serial arm's kinematics: Pinocchio model and data plus the limits, read-only.

    Joint vectors are ordered as ``joint_names`` ([rad] for revolute joints). The methods
    reuse ``data`` as scratch space, so one instance must not be shared between threads.
    """

    model: pin.Model
    data: pin.Data
    joint_names: tuple[str, ...]
    lower_limits: np.ndarray  # [rad], (n,)
    upper_limits: np.ndarray  # [rad], (n,)
    velocity_limits: np.ndarray  # [rad/s], (n,)
    tool_frame_id: int

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return len(self.joint_names)

    def check_q(self, q: npt.ArrayLike) -> FloatArray:
        """``q`` as a new float array of shape (n,); raises ``InvalidInput`` otherwise."""
        return as_joint_vector(q, self.n_joints, 'q')

    def forward_kinematics(self, q: npt.ArrayLike) -> FloatArray:
        """T_base_tool: 4x4 pose of the tool frame in ``base_link`` at joints ``q`` (n,)."""
        q = self.check_q(q)
        pin.forwardKinematics(self.model, self.data, q)
        return pin.updateFramePlacement(self.model, self.data, self.tool_frame_id).homogeneous

    def jacobian(self, q: npt.ArrayLike) -> FloatArray:
        """6 x n geometric Jacobian of the tool frame at ``q``, base-aligned axes.

        Rows 0-2 map qdot to the tool origin's linear velocity [m/s] and rows 3-5 to the
        tool's angular velocity [rad/s], both expressed in ``base_link``
        (Pinocchio's LOCAL_WORLD_ALIGNED).
        """
        q = self.check_q(q)
        return np.array(
            pin.computeFrameJacobian(
                self.model, self.data, q, self.tool_frame_id, pin.LOCAL_WORLD_ALIGNED
            )
        )


def load_robot(
    robot: str | os.PathLike[str],
    tool_length: float = 0.0,
    tip_frame: str = TOOL_FRAME,
    n_joints: int | None = N_JOINTS,
    base_frame: str = '',
    base_placement: Sequence[float] | None = None,
) -> RobotModel:
    """Build the kinematic model of ``robot``.

    Args:
        robot: ``'pa10'``, ``'pa10_thesis'`` or the path of a URDF file.
        tool_length: [m] extra offset of the tip along the tip frame's z axis.
        tip_frame: name of the tip frame in a URDF file (the PA-10 models use ``tool0``).
        n_joints: how many joints must move ``tip_frame`` (7: the arms this graph drives;
            None: any number).
        base_frame: the frame the arm's chain starts at ('': the URDF's root): joints
            moving it (a humanoid's torso, a mobile base's lift) are locked at neutral.
        base_placement: (6,) x, y, z [m], roll, pitch, yaw [rad] of ``base_frame`` in
            ``base_link``, the frame of every pose (None: the same frame).

    Returns:
        A ``RobotModel`` of the joints that move ``tip_frame``; any other joints (a
        gripper's fingers, say) are locked at their neutral position.

    Raises:
        InvalidInput: unknown model, unreadable URDF, missing tip frame, a joint with more
            than one coordinate or without position and velocity limits, another number
            of joints than ``n_joints``, or a non-finite ``tool_length``. The message
            names the joint or frame.
    """
    tool_length = _finite_float(tool_length, 'tool_length')
    model, tool_length, continuous = _build_model(robot, tool_length)
    model = _reduce_to_tip_chain(model, robot, tip_frame, base_frame)
    _place_base(model, base_frame, base_placement)
    for name in model.names[1:]:
        if name in continuous:
            raise InvalidInput(
                f'{robot}: joint {name} is continuous; every joint needs '
                'position limits (make it revolute with a <limit>)',
                'robot',
                name,
            )
    names = _joint_names(model, robot, tip_frame, n_joints)
    _check_joint_limits(model, robot, names)
    tool_frame_id = _extend_tip(model, tip_frame, tool_length)
    return RobotModel(
        model=model,
        data=model.createData(),
        joint_names=names,
        lower_limits=_read_only(model.lowerPositionLimit),
        upper_limits=_read_only(model.upperPositionLimit),
        velocity_limits=_read_only(model.velocityLimit),
        tool_frame_id=tool_frame_id,
    )


def _build_model(
    robot: str | os.PathLike[str], tool_length: float
) -> tuple[pin.Model, float, set[str]]:
    """Pinocchio model of a parameter set (its URDF carries the tool) or a URDF file, the
    tool length [m] still to add at the tip (0 for a parameter set) and the names of its
    continuous joints (refused if they move the tip)."""
    if not isinstance(robot, (str, os.PathLike)):
        raise InvalidInput(f'robot must be a model name or a path, got {robot!r}', 'robot', robot)
    if isinstance(robot, str) and robot in PARAMETER_SETS:
        return pin.buildModelFromXML(pa10_urdf(robot, tool_length)), 0.0, set()
    if not Path(robot).is_file():
        raise InvalidInput(
            f'robot must be one of {sorted(PARAMETER_SETS)} or a URDF file, got {robot!r}',
            'robot',
            robot,
        )
    try:
        text = Path(robot).read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise InvalidInput(f'cannot read URDF {robot}: {err}', 'robot', robot) from err
    continuous = _check_urdf_joints(text, robot)
    try:
        return pin.buildModelFromXML(text), tool_length, continuous
    except (RuntimeError, ValueError) as err:
        raise InvalidInput(f'cannot parse URDF {robot}: {err}', 'robot', robot) from err


def _reduce_to_tip_chain(
    model: pin.Model, robot: str | os.PathLike[str], tip_frame: str, base_frame: str = ''
) -> pin.Model:
    """``model`` with every joint that does not move ``tip_frame``, or moves
    ``base_frame`` too, locked at neutral."""
    for key, name, what in (
        ('tip_frame', tip_frame, 'the tool tip, z = approach axis'),
        ('base_frame', base_frame, "the arm's base"),
    ):
        if name and not model.existFrame(name):
            raise InvalidInput(
                f'{robot} has no frame {name!r} ({what}): set {key} to one of its '
                f'frames, {_frame_suggestions(model, name)}',
                key,
                name,
            )
    chain = set(model.supports[model.frames[model.getFrameId(tip_frame)].parentJoint])
    if base_frame:
        above = set(model.supports[model.frames[model.getFrameId(base_frame)].parentJoint])
        if not above <= chain:
            raise InvalidInput(
                f'{robot}: base_frame {base_frame!r} is not on the chain to {tip_frame!r}',
                'base_frame',
                base_frame,
            )
        chain -= above - {0}
    off_chain = [j for j in range(1, model.njoints) if j not in chain]
    if off_chain:
        model = pin.buildReducedModel(model, off_chain, pin.neutral(model))
    return model


def _place_base(model: pin.Model, base_frame: str, base_placement: Sequence[float] | None) -> None:
    """Re-root ``model`` (in place) so that poses are in ``base_link``, where
    ``base_frame`` (fixed: the joints moving it are locked) sits at ``base_placement``."""
    if not base_frame and base_placement is None:
        return
    placement = np.zeros(6) if base_placement is None else np.asarray(base_placement, float)
    if placement.shape != (6,) or not np.all(np.isfinite(placement)):
        raise InvalidInput(
            f'base_placement must be 6 finite numbers (x, y, z, roll, pitch, yaw), got '
            f'{base_placement!r}',
            'base_placement',
            base_placement,
        )
    M_link_base = pin.SE3(pin.rpy.rpyToMatrix(*placement[3:]), placement[:3])
    M_root_base = pin.SE3.Identity()
    if base_frame:
        data = model.createData()
        pin.framesForwardKinematics(model, data, pin.neutral(model))
        M_root_base = data.oMf[model.getFrameId(base_frame)].copy()
    M = M_link_base * M_root_base.inverse()
    for j in range(1, model.njoints):
        if model.parents[j] == 0:
            model.jointPlacements[j] = M * model.jointPlacements[j]
    for i, frame in enumerate(model.frames):
        if frame.parentJoint == 0:
            frame.placement = M * frame.placement
            model.frames[i] = frame


def _frame_suggestions(model: pin.Model, wanted: str, listed: int = 12) -> str:
    """The model's link frames as a short list: all of them when few, else the names
    nearest to ``wanted`` and the chains' end links (where a tool tip usually is)."""
    links = [f.name for f in model.frames if f.type == pin.FrameType.BODY]
    if len(links) <= listed:
        return ', '.join(links)
    parents = {model.frames[f.parentFrame].name for f in model.frames if f.parentFrame}
    ends = [name for name in links if name not in parents]
    nearest = difflib.get_close_matches(wanted, links, n=4, cutoff=0.3)
    shown = list(dict.fromkeys(nearest + ends))[:listed]
    return f'e.g. {", ".join(shown)} ({len(links)} in all)'


def _joint_names(
    model: pin.Model, robot: str | os.PathLike[str], tip_frame: str, n_joints: int | None
) -> tuple[str, ...]:
    """The joint names of ``model``; raises unless each joint has one coordinate and there
    are ``n_joints`` of them (None: any number)."""
    if model.nq != model.njoints - 1 or model.nv != model.nq:
        # Continuous (nq=2) or free joints would break "one entry per joint name".
        raise InvalidInput(
            f'{robot}: every joint must have exactly one coordinate', 'robot', robot
        )
    names = tuple(model.names[1:])
    if n_joints is not None and len(names) != n_joints:
        raise InvalidInput(
            f'{robot}: {len(names)} joints move {tip_frame!r} '
            f'({", ".join(names) or "none"}); a {n_joints}-DOF serial arm '
            'is needed',
            'robot',
            robot,
        )
    return names


def _check_joint_limits(
    model: pin.Model, robot: str | os.PathLike[str], names: tuple[str, ...]
) -> None:
    """Every joint needs finite position limits lower < upper and a velocity limit > 0."""
    lower, upper = model.lowerPositionLimit, model.upperPositionLimit
    for i, name in enumerate(names):
        if not (np.isfinite(lower[i]) and np.isfinite(upper[i]) and lower[i] < upper[i]):
            raise InvalidInput(
                f'{robot}: joint {name} has no usable position limits '
                f'[{lower[i]}, {upper[i]}] (need finite lower < upper)',
                'robot',
                name,
            )
        if not (np.isfinite(model.velocityLimit[i]) and model.velocityLimit[i] > 0):
            raise InvalidInput(
                f'{robot}: joint {name} has no velocity limit '
                f'({model.velocityLimit[i]}; need > 0)',
                'robot',
                name,
            )


def _extend_tip(model: pin.Model, tip_frame: str, tool_length: float) -> int:
    """Move ``tip_frame`` of ``model`` (in place) ``tool_length`` [m] along its z axis;
    returns its frame id."""
    tool_frame_id: int = model.getFrameId(tip_frame)
    if tool_length != 0.0:
        frame = model.frames[tool_frame_id]
        frame.placement = frame.placement * pin.SE3(np.eye(3), np.array([0, 0, tool_length]))
        model.frames[tool_frame_id] = frame
    return tool_frame_id


def _check_urdf_joints(text: str, robot: str | os.PathLike[str]) -> set[str]:
    """Name a moving joint without ``<limit>`` (urdfdom only says the XML is invalid);
    returns the names of the continuous joints (a problem only if they move the tip)."""
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as err:
        raise InvalidInput(f'cannot parse URDF {robot}: {err}', 'robot', robot) from err
    continuous = set()
    for joint in root.iter('joint'):
        kind, name = joint.get('type'), joint.get('name')
        if kind == 'continuous':
            continuous.add(str(name))
        if kind in ('revolute', 'prismatic'):
            limit = joint.find('limit')
            missing = [
                key
                for key in ('lower', 'upper', 'velocity')
                if limit is None or limit.get(key) is None
            ]
            if missing:
                raise InvalidInput(
                    f'{robot}: joint {name} lacks limits ({", ".join(missing)} '
                    'missing in <limit>)',
                    'robot',
                    name,
                )
    return continuous


def workspace_reach(robot: RobotModel) -> tuple[FloatArray, float]:
    """(shoulder (3,), reach [m]) of a ``RobotModel``: the tip stays within ``reach`` of
    the shoulder in every configuration.

    The shoulder is the point of the first joint's axis closest to the second joint's
    axis (where they cross, on most arms; TIAGo's and Talos's second joint sits off the
    first one's axis): the first joint turns everything about that axis, so the second
    joint's origin stays at its distance from the shoulder, and every later joint's
    origin stays at its distance from the one before (each joint turns about an axis
    through its own origin). Their sum, tool included, bounds the tip's distance.
    """
    model = robot.model
    data = model.createData()
    q = np.zeros(robot.n_joints)
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    origins = [data.oMi[j].translation.copy() for j in range(1, model.njoints)]
    tip = data.oMf[robot.tool_frame_id].translation.copy()
    shoulder = origins[0]
    if len(origins) > 1:
        first, second = (
            pin.getJointJacobian(model, data, j, pin.LOCAL_WORLD_ALIGNED)[3:, model.idx_vs[j]]
            for j in (1, 2)
        )
        shoulder = _closest_point_on_axis(origins[0], first, origins[1], second)
    chain = [shoulder, *origins[1:], tip]
    reach = sum(np.linalg.norm(b - a) for a, b in zip(chain[:-1], chain[1:]))
    return shoulder, float(reach)


def _closest_point_on_axis(
    point: FloatArray, direction: FloatArray, other_point: FloatArray, other_direction: FloatArray
) -> FloatArray:
    """The point of the line through ``point`` along the unit ``direction`` closest to the
    line through ``other_point`` along the unit ``other_direction`` (parallel lines: the
    foot of ``other_point``)."""
    offset = point - other_point
    cosine = float(direction @ other_direction)
    sine2 = 1.0 - cosine**2
    if sine2 < 1e-12:
        return point + float(direction @ (other_point - point)) * direction
    s = (cosine * float(other_direction @ offset) - float(direction @ offset)) / sine2
    return point + s * direction


def as_joint_vector(q: npt.ArrayLike, n: int, key: str = 'q') -> FloatArray:
    """``q`` as a new finite float array of shape (n,); raises ``InvalidInput`` otherwise."""
    try:
        array = np.array(q, dtype=float)
    except (TypeError, ValueError) as err:
        raise InvalidInput(f'{key} must be {n} numbers, got {q!r}', key, q) from err
    if array.shape != (n,):
        raise InvalidInput(f'{key} must have shape ({n},), got {array.shape}', key, q)
    if not np.all(np.isfinite(array)):
        raise InvalidInput(f'{key} must be finite, got {array}', key, q)
    return array


def _parameters(name: str) -> Pa10Parameters:
    try:
        return PARAMETER_SETS[name]
    except (KeyError, TypeError):
        raise InvalidInput(
            f'unknown PA-10 parameter set {name!r}, expected one of {sorted(PARAMETER_SETS)}',
            'robot',
            name,
        ) from None


def _finite_float(value: Any, key: str) -> float:
    """``value`` (a parameter: anything) as a finite float, else InvalidInput."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InvalidInput(f'{key} must be a number, got {value!r}', key, value) from None
    if not np.isfinite(value):
        raise InvalidInput(f'{key} must be finite, got {value}', key, value)
    return value


if __name__ == '__main__':
    write_urdfs(Path(__file__).resolve().parents[1] / 'urdf')
