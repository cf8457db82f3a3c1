"""Seeded generators of force-tracking tasks: arms, posed surfaces and paths on them.

For the tests and bench/bench_pa10_ik.py (any 7-DOF arm, any surface
orientation). No ROS. Every random choice takes a ``numpy.random.Generator``.

- Arms: PA-10-like URDFs (the PA-10's joint axes, link offsets within +-40 % of the real
  arm's, other joint and velocity limits, a 0.05-0.2 m tool, ``tool0`` at the tip) and the
  7-DOF arms of example-robot-data as they ship (``ROBOT_DATA_ARMS``: the Franka Panda, the
  xArm 7, TIAGo's and TIAGo Pro's arms from the torso, Talos's left arm from the torso,
  Baxter's left arm), each its chain from a base frame to a tip frame, other joints locked.
- Surfaces: planes, paraboloid domes and S1-S3, posed so that the normal under the path's
  centre is tilted 0-45 deg away from the tool's axis at the arm's start pose.
- Paths: a line, an arc, a self-crossing figure eight, a spiral of two turns and a tight
  loop (6 mm radius) near the arm's reach (placed in front of the start pose with the
  elbow opened to 60 % of its angle), as waypoints (origin on the surface, x along
  the tangent, z into the surface: INTERFACES.md /curve/waypoints).
"""

from __future__ import annotations

import copy
import importlib.metadata
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from sensor_sim.scenario import Surface
from sensor_sim.surfaces import height, normal_base, surface_points_base
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.robot_model import (
    PA10_LOWER_LIMITS_RAD,
    PA10_UPPER_LIMITS_RAD,
    PA10_VELOCITY_LIMITS_RAD_S,
    PARAMETER_SETS,
    Pa10Parameters,
    RobotModel,
    load_robot,
    pa10_like_urdf,
)
from vgm_common.topics import TOOL_FRAME

if TYPE_CHECKING:  # imported lazily where used
    from pa10_ik_node.commands import JointCommand, SetPointCommands
    from sensor_sim.arm_sim import SimulatedArm

LINK_SPREAD = 0.4  # link offsets within +-40 % of the real PA-10's
TOOL_RANGE_M = (0.05, 0.2)
# Elbow-up, the PA-10's tool pointing straight down (the default scenario's start pose).
PA10_START_JOINTS = np.array([0.0, 0.388, 0.0, 1.645, 0.0, 1.109, 0.0])  # [rad]
# The Panda's "ready" pose, hand pointing down.
PANDA_START_JOINTS = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.785])  # [rad]
ROBOT_DATA_DIR = 'cmeel.prefix/share/example-robot-data/robots'
PANDA_URDF = f'{ROBOT_DATA_DIR}/panda_description/urdf/panda.urdf'
# name: (URDF under ROBOT_DATA_DIR, base frame, tip frame, start joints [rad]). The start
# joints (the Panda's its "ready" pose) maximise the smallest singular value of the
# 5-row task Jacobian (spin free) within the middle 70 % of each joint's range (scipy
# L-BFGS-B from 12 seeded draws; 0.21-0.28 at the optimum).
ROBOT_DATA_ARMS = {
    'panda': ('panda_description/urdf/panda.urdf', '', 'panda_hand_tcp', PANDA_START_JOINTS),
    'xarm7': (
        'xarm_description/urdf/xarm7.urdf',
        '',
        'link_eef',
        np.array([0.0, 0.018, 0.015, 0.929, 1.393, 0.605, 0.0]),
    ),
    'tiago': (
        'tiago_description/robots/tiago.urdf',
        'torso_lift_link',
        'arm_tool_link',
        np.array([1.38, -0.129, -1.346, 1.939, -0.545, 0.129, -0.768]),
    ),
    'tiago_pro_left': (
        'tiago_pro_description/robots/tiago_pro.urdf',
        'torso_lift_link',
        'arm_left_tool_link',
        np.array([2.094, -0.657, -0.091, -1.907, -1.183, 0.793, 0.0]),
    ),
    'talos_left': (
        'talos_data/robots/talos_reduced.urdf',
        'torso_2_link',
        'wrist_left_ft_tool_link',
        np.array([-0.524, 1.294, 0.096, -1.957, 0.157, 0.905, 0.018]),
    ),
    'baxter_left': (
        'baxter_description/urdf/baxter.urdf',
        '',
        'left_gripper',
        np.array([0.0, -0.13, -1.129, 2.197, 0.782, 1.391, -0.001]),
    ),
}
SURFACE_KINDS = ('plane', 'paraboloid', 'S1', 'S2', 'S3')
PATH_SHAPES = ('line', 'arc', 'figure_eight', 'spiral', 'tight_loop')
WAYPOINT_SPACING_M = 0.001


@dataclass(frozen=True)
class GeneratedArm:
    """A generated arm: its URDF text, start joints [rad] and what was drawn."""

    name: str
    urdf: str
    start_joints: FloatArray
    description: str
    link_offsets_m: tuple[float, ...] = ()  # PA-10-like arms: (d1, d3, d5, d7)
    tool_length_m: float = float('nan')  # PA-10-like arms
    tip_frame: str = TOOL_FRAME  # the tool tip (z = approach axis), a frame of ``urdf``
    base_frame: str = ''  # where the arm's chain starts ('': the URDF's root)


def random_pa10_like_arm(rng: np.random.Generator, name: str = 'pa10_random') -> GeneratedArm:
    """A PA-10-like 7-DOF arm: link offsets d1, d3, d5, d7 each the real arm's times
    U(0.6, 1.4), joint limits each the real arm's times U(0.6, 1.0) (widened to keep
    0.5 rad beyond the start pose), velocity limits times U(0.5, 1.5), a tool of
    U(0.05, 0.2) m. Start pose: ``PA10_START_JOINTS``."""
    real = PARAMETER_SETS['pa10']
    factors = rng.uniform(1 - LINK_SPREAD, 1 + LINK_SPREAD, 4)
    params = Pa10Parameters(*(np.array([real.d1, real.d3, real.d5, real.d7]) * factors))
    upper = np.maximum(
        PA10_UPPER_LIMITS_RAD * rng.uniform(0.6, 1.0, 7), np.abs(PA10_START_JOINTS) + 0.5
    )
    lower = -np.maximum(
        -PA10_LOWER_LIMITS_RAD * rng.uniform(0.6, 1.0, 7), np.abs(PA10_START_JOINTS) + 0.5
    )
    velocity = PA10_VELOCITY_LIMITS_RAD_S * rng.uniform(0.5, 1.5, 7)
    tool = float(rng.uniform(*TOOL_RANGE_M))
    urdf = pa10_like_urdf(params, tool, lower, upper, velocity, name=name)
    description = (
        f'd = ({params.d1:.3f}, {params.d3:.3f}, {params.d5:.3f}, '
        f'{params.d7:.3f}) m, tool {tool:.3f} m'
    )
    return GeneratedArm(
        name,
        urdf,
        PA10_START_JOINTS.copy(),
        description,
        (params.d1, params.d3, params.d5, params.d7),
        tool,
    )


def robot_data_arm(name: str) -> GeneratedArm:
    """An arm of ``ROBOT_DATA_ARMS``: its example-robot-data URDF unedited, with its base
    and tip frames and start joints.

    Raises:
        InvalidInput: an unknown name, or example-robot-data is not installed.
    """
    if name not in ROBOT_DATA_ARMS:
        raise InvalidInput(f'name must be one of {sorted(ROBOT_DATA_ARMS)}', 'name', name)
    relative, base, tip, start = ROBOT_DATA_ARMS[name]
    try:
        distribution = importlib.metadata.distribution('example-robot-data')
        text = distribution.locate_file(f'{ROBOT_DATA_DIR}/{relative}').read_text()
    except (importlib.metadata.PackageNotFoundError, OSError) as err:
        raise InvalidInput(
            f'{relative} of example-robot-data is not available: {err}', 'robot'
        ) from err
    return GeneratedArm(
        name,
        text,
        np.array(start, dtype=float),
        f'{relative} (example-robot-data), {base or "root"} -> {tip}',
        tip_frame=tip,
        base_frame=base,
    )


def panda_arm() -> GeneratedArm:
    """The Franka Panda of example-robot-data, its URDF unedited, tip ``panda_hand_tcp``."""
    return robot_data_arm('panda')


def stretched_joints(
    start_joints: npt.ArrayLike, elbow_index: int = 3, factor: float = 0.6
) -> FloatArray:
    """The start pose with the elbow (joint 4 of the PA-10 and the Panda) opened to
    ``factor`` of its angle: a pose within the limits near the arm's reach."""
    q = np.array(start_joints, dtype=float)
    q[elbow_index] *= factor
    return q


def posed_surface(
    kind: str,
    robot: RobotModel,
    placement_joints: npt.ArrayLike,
    tilt_rad: float,
    rng: np.random.Generator,
    ahead_m: float = 0.1,
) -> Surface:
    """A surface of ``kind`` whose normal under its centre (surface units (0, 0)) is
    tilted by ``tilt_rad`` from the tool's axis at ``placement_joints`` (about a random
    axis across it, random spin about the normal), the centre ``ahead_m`` [m] ahead of
    the tool tip along its axis.

    Args:
        kind: one of ``SURFACE_KINDS``.
        robot: ``RobotModel``; placement_joints: (n,) [rad] (the start pose, or
            ``stretched_joints`` of it for a path near the reach).

    Returns:
        A ``sensor_sim.scenario.Surface``.
    """
    if kind not in SURFACE_KINDS:
        raise InvalidInput(f'kind must be one of {SURFACE_KINDS}', 'kind', kind)
    T0 = robot.forward_kinematics(placement_joints)
    axis_tool = T0[:3, 2]
    centre = T0[:3, 3] + ahead_m * axis_tool
    across = np.cross(axis_tool, rng.normal(size=3))
    across /= np.linalg.norm(across)
    normal_wanted = Rotation.from_rotvec(tilt_rad * across).apply(-axis_tool)
    scale, extent, radius = {
        'plane': (1.0, ((-0.3, 0.3), (-0.3, 0.3)), 1.0),
        'paraboloid': (1.0, ((-0.15, 0.15), (-0.15, 0.15)), float(rng.uniform(0.08, 0.3))),
    }.get(kind, (0.2, ((-0.5, 0.5), (-0.5, 0.5)), 1.0))
    surface = Surface(
        kind=kind,
        T_base_surface=np.eye(4),
        scale=scale,
        extent=extent,
        albedo=0.8,
        roughness=0.0,
        radius=radius,
    )
    normal_local = normal_base(surface, surface_points_base(surface, [[0.0, 0.0]]))[0]
    align, _ = Rotation.align_vectors([normal_wanted], [normal_local])
    spin = Rotation.from_rotvec(rng.uniform(-np.pi, np.pi) * normal_wanted)
    R = (spin * align).as_matrix()
    h0 = float(height(surface, [[0.0, 0.0]])[0])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ (scale * np.array([0.0, 0.0, h0]))
    return replace(surface, T_base_surface=T)


def path_xy_m(shape: str, rng: np.random.Generator) -> tuple[FloatArray, bool]:
    """(M, 2) dense points [m] of a path shape around (0, 0), and whether it is closed."""
    t = np.linspace(0.0, 1.0, 2001)
    if shape == 'line':
        length = rng.uniform(0.04, 0.06)
        angle = rng.uniform(0, np.pi)
        xy = np.outer(t - 0.5, [np.cos(angle), np.sin(angle)]) * length
        return xy, False
    if shape == 'arc':
        radius, sweep = rng.uniform(0.02, 0.035), rng.uniform(0.6, 1.0) * np.pi
        a = sweep * (t - 0.5)
        return radius * np.column_stack([np.sin(a), 1 - np.cos(a)]), False
    if shape == 'figure_eight':  # lemniscate of Gerono: crosses itself at the centre
        size = rng.uniform(0.02, 0.03)
        a = 2 * np.pi * t[:-1]
        return size * np.column_stack([np.sin(a), np.sin(a) * np.cos(a)]), True
    if shape == 'spiral':  # two turns, radius 5 -> 20 mm
        a = 4 * np.pi * t
        r = 0.005 + 0.015 * t
        return np.column_stack([r * np.cos(a), r * np.sin(a)]), False
    if shape == 'tight_loop':  # 6 mm radius: curvature 167 /m
        a = 2 * np.pi * t[:-1]
        return 0.006 * np.column_stack([np.cos(a), np.sin(a)]), True
    raise InvalidInput(f'shape must be one of {PATH_SHAPES}', 'shape', shape)


def surface_waypoints(
    surface: Surface, xy_m: npt.ArrayLike, closed: bool, spacing_m: float = WAYPOINT_SPACING_M
) -> FloatArray:
    """Waypoints (N, 4, 4) about every ``spacing_m`` [m] along the dense surface-frame
    path ``xy_m`` [m] (divided by the surface's scale into surface units): origin on the
    surface, z = -normal, x along the path across z. A closed path's first point is not
    repeated."""
    points = surface_points_base(surface, np.asarray(xy_m) / surface.scale)
    if not np.all(np.isfinite(points)):
        raise InvalidInput("the path leaves the surface's domain", 'path')
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    count = max(int(round(arc[-1] / spacing_m)), 2)
    keep = np.searchsorted(
        arc, np.linspace(0.0, arc[-1], count + 1 - int(closed), endpoint=not closed)
    )
    points = points[np.clip(keep, 0, len(points) - 1)]
    approach = -normal_base(surface, points)
    ahead = np.roll(points, -1, axis=0) - points
    if not closed:
        ahead[-1] = points[-1] - points[-2]
    poses = np.tile(np.eye(4), (len(points), 1, 1))
    for i, (p, z, d) in enumerate(zip(points, approach, ahead)):
        x = d - z * np.dot(z, d)
        x /= np.linalg.norm(x)
        poses[i, :3, :3] = np.column_stack([x, np.cross(z, x), z])
        poses[i, :3, 3] = p
    return poses


@dataclass
class LoopLog:
    """What an offline closed loop recorded, one entry per control step."""

    phases: list[str]
    tips: list[FloatArray]  # (3,) measured tool tip [m]
    forces: list[float]  # [N] true contact force
    qdot_commanded: list[FloatArray]  # (n,) [rad/s] as it reached the arm
    q: list[FloatArray]  # (n,) measured joints [rad]
    step_times: list[float]  # [s] controller.step wall time
    times: list[float] = field(default_factory=list)  # [s] simulated time after the step
    readings: list[float] = field(default_factory=list)  # [N] the pressure the step was given
    stop_latency: float = float('nan')  # [s] from a stop to zero joint velocity


class TrackingControllerLike(Protocol):
    """What ``run_closed_loop`` uses of pa10_ik_node's TrackingController."""

    progress: float  # fraction of the path tracked
    phase: str  # 'approach', 'contact', 'tracking', 'done', 'stopped', 'failed', ...
    stage: str  # within the phase, e.g. 'lifted' once done
    arm_lag: float  # [s] the arm's measured lag, set before each step with node_commands

    def stop(self, reason: str = ...) -> None:
        """Hold still from now on (``phase`` becomes 'stopped'); ``reason`` says why."""
        ...

    def step(
        self, q: FloatArray, measured_force: float, dt: float
    ) -> tuple[FloatArray, Mapping[str, Any]]:
        """One control step at joints ``q`` (n,) [rad] with the measured force [N] over
        ``dt`` [s]. Returns (qdot (n,) [rad/s], info with at least ``'phase'``)."""
        ...


def lifted(controller: TrackingControllerLike) -> bool:
    """``run_closed_loop``'s default end: done and lifted off."""
    return controller.phase == 'done' and controller.stage == 'lifted'


def run_closed_loop(
    controller: TrackingControllerLike,
    robot: RobotModel,
    arm: SimulatedArm,
    surface: Surface,
    stiffness: float,
    dt: float = 0.01,
    max_time: float = 120.0,
    stop_at_progress: float | None = None,
    pressure_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
    hold_time: float = 0.5,
    substeps: int = 2,
    *,
    command_delay_steps: int = 0,
    horizon: float = 0.05,
    node_commands: bool = True,
    lead_arm_lag: bool = False,
    send_set_point: bool = True,
    initial_force: float | None = 0.0,
    before_step: Callable[[float, FloatArray], None] | None = None,
    finished: Callable[[TrackingControllerLike], bool] = lifted,
) -> LoopLog:
    """``controller`` (a pa10_ik_node TrackingController, started) against ``arm`` (a
    ``SimulatedArm``) and the spring contact on ``surface``: the one offline closed loop
    of the tests and the bench.

    Control every ``dt`` [s], the arm stepped ``substeps`` times per period, the command
    as pa10_ik_node sends it (``node_commands``: pa10_ik_node.commands.SetPointCommands,
    the point ``horizon`` [s] ahead of the previous command's set point, led by the
    arm's measured lag if ``lead_arm_lag``, the set point sent at time 0 if
    ``send_set_point``, the node's parameters; false: ``q + qdot
    horizon`` from the measured joints, as the DLS peer node sends it; a hold at time 0
    once the controller stopped or failed), reaching the arm ``command_delay_steps``
    periods late (none before the first: the arm holds; a slow controller or network).
    The pressure is the true force plus N(0, ``pressure_sigma``) noise while in contact
    (never below 0);
    the first step is given ``initial_force`` [N] (None: the reading at the start).
    ``before_step(t, q)`` runs at the start of each period (a test's new path);
    ``stop_at_progress``: call ``controller.stop()`` once progress reaches it. Runs until
    ``finished(controller)`` (default: done and lifted) plus ``hold_time`` [s], until
    stopped or failed (plus ``hold_time``, measuring how long the arm takes to stand
    still) or ``max_time`` [s]."""
    import time

    from pa10_ik_node.commands import JointCommand, SetPointCommands
    from sensor_sim.contact import contact_force

    rng = rng or np.random.default_rng(0)

    def pressure(true_force: float) -> float:
        if true_force > 0 and pressure_sigma > 0:
            return max(0.0, true_force + rng.normal(0.0, pressure_sigma))
        return true_force

    log = LoopLog([], [], [], [], [], [])
    t, ended_at, stopped_at = 0.0, None, None
    if initial_force is None:
        tip = robot.forward_kinematics(arm.q)[:3, 3]
        initial_force = pressure(contact_force(tip, surface, stiffness).force)
    force = initial_force
    names = robot.joint_names
    commands = (
        SetPointCommands(lead_arm_lag, send_set_point=send_set_point) if node_commands else None
    )
    # Before the first command arrives the arm holds where it is.
    on_the_way = [JointCommand(arm.q, np.zeros(robot.n_joints), horizon)] * command_delay_steps
    in_force = np.zeros(robot.n_joints)  # [rad/s] the velocity of the command in force
    while t < max_time:
        q = arm.q
        if before_step is not None:
            before_step(t, q)
        if stop_at_progress is not None and controller.progress >= stop_at_progress:
            controller.stop('stop requested mid-motion')
            stop_at_progress = None
        started = time.perf_counter()
        qdot, info = controller.step(q, force, dt)
        log.step_times.append(time.perf_counter() - started)
        log.readings.append(force)
        halted = controller.phase in ('stopped', 'failed')
        if halted:  # for good: nothing moves the arm again
            arm.set_trajectory(names, [0.0], [q], start_time=t)  # the node's hold
            in_force = np.zeros(robot.n_joints)
            stopped_at = t if stopped_at is None else stopped_at
        else:
            on_the_way.append(_command(commands, controller, q, qdot, t, horizon))
            arriving = on_the_way.pop(0)
            times, positions, velocities = zip(*arriving.points())
            arm.set_trajectory(names, times, positions, velocities, start_time=t)
            in_force = arriving.velocities
        for _ in range(substeps):
            t += dt / substeps
            arm.step(t, dt / substeps)
            standing = np.max(np.abs(arm.qdot)) < 1e-9
            if stopped_at is not None and np.isnan(log.stop_latency) and standing:
                log.stop_latency = t - stopped_at
        tip = robot.forward_kinematics(arm.q)[:3, 3]
        true_force = contact_force(tip, surface, stiffness).force
        force = pressure(true_force)
        log.phases.append(info['phase'])
        log.tips.append(tip)
        log.forces.append(true_force)
        log.qdot_commanded.append(in_force.copy())
        log.q.append(arm.q)
        log.times.append(t)
        if (halted or finished(controller)) and ended_at is None:
            ended_at = t
        if ended_at is not None and t - ended_at >= hold_time:
            break
    return log


def _command(
    commands: SetPointCommands | None,
    controller: TrackingControllerLike,
    q: FloatArray,
    qdot: FloatArray,
    t: float,
    horizon: float,
) -> JointCommand:
    """The moving command ``run_closed_loop`` sends at ``t`` [s]: pa10_ik_node's
    (``commands``) or, without them, the point ``horizon`` ahead of the measured joints."""
    from pa10_ik_node.commands import JointCommand

    if commands is None:
        return JointCommand(q + qdot * horizon, qdot, horizon)
    commands.measure(q, t)
    controller.arm_lag = commands.lag  # for its next step, as pa10_ik_node's session
    # pa10_ik_node's predictor compensates this much of the lag (as in the node)
    config = getattr(controller, 'config', None)
    commands.covered_lag = getattr(config, 'command_latency', 0.0)
    return commands.command(q, qdot, t, horizon)


def path_errors(
    tips: npt.ArrayLike, surface: Surface, path_base: FloatArray, within_m: float = 0.002
) -> tuple[FloatArray, float]:
    """Distances [m] (K,) of the tips' (K, 3) foot points on the surface (along the
    normal) to the dense path polyline ``path_base`` (M, 3), and the fraction of the
    path's points that some foot point came within ``within_m`` [m] of."""
    from sensor_sim.surfaces import signed_height_base

    tips = np.asarray(tips, dtype=float).reshape(-1, 3)
    feet = tips - signed_height_base(surface, tips)[:, None] * normal_base(surface, tips)
    a, b = path_base[:-1], path_base[1:]
    ab = b - a
    lengths2 = np.maximum(np.sum(ab * ab, axis=1), 1e-18)
    distances = np.empty(len(feet))
    for i, foot in enumerate(feet):
        s = np.clip(np.einsum('ij,ij->i', foot - a, ab) / lengths2, 0.0, 1.0)
        distances[i] = np.min(np.linalg.norm(a + s[:, None] * ab - foot, axis=1))
    near = np.array([np.min(np.linalg.norm(feet - p, axis=1)) for p in path_base])
    return distances, float(np.mean(near < within_m))


def goal_figures(
    tips: npt.ArrayLike,
    forces: npt.ArrayLike,
    surface: Surface,
    path_base: FloatArray,
    desired_force: float,
    within_m: float = 0.002,
) -> dict[str, float]:
    """The path and force goal figures of the tool tips (K, 3) [m] and forces (F,) [N]
    measured while tracking (in process or over topics): rms_mm and max_mm (distance of
    the tips' foot points on the surface to the path), passed_fraction (path points with
    a foot point within ``within_m``), force_p95_pct (95th percentile of |force error| /
    desired); NaN (passed 0) with no tips or forces."""
    tips = np.asarray(tips, dtype=float).reshape(-1, 3)
    forces = np.asarray(forces, dtype=float)
    figures = {
        'rms_mm': float('nan'),
        'max_mm': float('nan'),
        'passed_fraction': 0.0,
        'force_p95_pct': float('nan'),
    }
    if len(tips):
        distances, passed = path_errors(tips, surface, path_base, within_m)
        figures.update(
            rms_mm=float(np.sqrt(np.mean(distances**2)) * 1e3),
            max_mm=float(distances.max() * 1e3),
            passed_fraction=passed,
        )
    if len(forces):
        figures['force_p95_pct'] = float(
            np.percentile(np.abs(forces - desired_force), 95) / desired_force * 100
        )
    return figures


def tracking_metrics(
    log: LoopLog,
    surface: Surface,
    path_base: FloatArray,
    desired_force: float,
    robot: RobotModel,
    within_m: float = 0.002,
) -> dict[str, float]:
    """The issue-13 goals of one run, measured on the true state while tracking.

    Args:
        log: ``LoopLog``; surface: the true surface; path_base: (M, 3) the dense true
        path [m]; desired_force [N]; robot: ``RobotModel`` (limits).

    Returns:
        dict: rms_mm (distance of the tip's foot point on the surface to the path),
        passed_fraction (path points with a foot point within ``within_m``),
        force_p95_pct (95th percentile of |force error| / desired), velocity_ratio (largest
        commanded |qdot| / limit), limit_margin_rad (smallest distance of q to a position
        limit), step_ms_median, stop_latency_ms.
    """
    tracking = np.array([phase == 'tracking' for phase in log.phases])
    tips = np.array(log.tips)[tracking] if tracking.any() else np.zeros((0, 3))
    forces = np.array(log.forces)[tracking]
    result: dict[str, float] = {'tracking_steps': int(tracking.sum())}
    result.update(goal_figures(tips, forces, surface, path_base, desired_force, within_m))
    qdot = np.array(log.qdot_commanded)
    q = np.array(log.q)
    result.update(
        velocity_ratio=float(np.max(np.abs(qdot) / robot.velocity_limits)),
        limit_margin_rad=float(np.min(np.minimum(q - robot.lower_limits, robot.upper_limits - q))),
        step_ms_median=float(np.median(log.step_times) * 1e3),
        stop_latency_ms=float(log.stop_latency * 1e3),
    )
    return result


ARM_SIMULATIONS = (('position', 1.0), ('velocity', 1.0), ('position', 0.5), ('velocity', 0.5))


@dataclass(frozen=True)
class CaseSpec:
    """One generated case: an arm x a surface x a path, and how the arm is simulated."""

    arm: GeneratedArm
    surface_kind: str
    tilt_rad: float
    path_shape: str
    arm_mode: str
    speed_scale: float
    seed: int
    # x, y, z [m], roll, pitch, yaw [rad] of the arm's base frame in base_link
    base_placement: tuple[float, ...] = (0.0,) * 6

    @property
    def label(self) -> str:
        """The case in one line: arm / surface kind and tilt [deg] / path shape / arm mode
        and speed scale."""
        return (
            f'{self.arm.name} / {self.surface_kind} {np.degrees(self.tilt_rad):.0f} deg / '
            f'{self.path_shape} / {self.arm_mode} x{self.speed_scale:g}'
        )


@dataclass(frozen=True)
class BuiltCase:
    """A case made concrete: the robot, the posed surface, the waypoints, the dense true
    path (M, 3) [m] and a fresh simulated arm at the start pose."""

    spec: CaseSpec
    robot: RobotModel
    surface: Surface
    waypoints: FloatArray
    path_base: FloatArray
    closed: bool

    def simulated_arm(self) -> SimulatedArm:
        """A new ``SimulatedArm`` of ``robot`` at the arm's start joints, in the spec's arm
        mode and speed scale."""
        from sensor_sim.arm_sim import SimulatedArm

        return SimulatedArm.from_robot_model(
            self.robot, self.spec.arm.start_joints, self.spec.arm_mode, self.spec.speed_scale
        )


def generate_cases(seed: int, random_arms: int = 3, with_panda: bool = True) -> list[CaseSpec]:
    """Every arm (``random_arms`` PA-10-like ones and the Panda) on every surface kind, the
    path shapes and arm simulations cycling, tilts 0-45 deg (the first case of each arm
    untilted, the last one at 45 deg). Returns a list of ``CaseSpec``."""
    rng = np.random.default_rng(seed)
    arms = [random_pa10_like_arm(rng, f'pa10_random{i}') for i in range(random_arms)]
    if with_panda:
        arms.append(panda_arm())
    cases = []
    for i, arm in enumerate(arms):
        for j, kind in enumerate(SURFACE_KINDS):
            tilt = (
                0.0
                if j == 0
                else np.radians(45.0)
                if j == len(SURFACE_KINDS) - 1
                else float(rng.uniform(0.0, np.radians(45.0)))
            )
            mode, scale = ARM_SIMULATIONS[(i + j) % len(ARM_SIMULATIONS)]
            cases.append(
                CaseSpec(
                    arm,
                    kind,
                    tilt,
                    PATH_SHAPES[(i + 2 * j) % len(PATH_SHAPES)],
                    mode,
                    scale,
                    int(rng.integers(2**31)),
                )
            )
    return cases


def build_case(spec: CaseSpec, directory: str | os.PathLike[str]) -> BuiltCase:
    """Write the arm's URDF into ``directory`` and build the case (``BuiltCase``)."""
    from pathlib import Path

    urdf = Path(directory) / f'{spec.arm.name}.urdf'
    urdf.write_text(spec.arm.urdf)
    robot = load_robot(
        str(urdf),
        tip_frame=spec.arm.tip_frame,
        base_frame=spec.arm.base_frame,
        base_placement=list(spec.base_placement),
    )
    rng = np.random.default_rng(spec.seed)
    placement = spec.arm.start_joints
    if spec.path_shape == 'tight_loop':  # near the reach
        placement = stretched_joints(placement)
    surface = posed_surface(spec.surface_kind, robot, placement, spec.tilt_rad, rng)
    xy, closed = path_xy_m(spec.path_shape, rng)
    waypoints = surface_waypoints(surface, xy, closed)
    path_base = surface_points_base(surface, xy / surface.scale)
    if closed:
        path_base = np.vstack([path_base, path_base[:1]])
    return BuiltCase(spec, robot, surface, waypoints, path_base, closed)


def plane_scenario(
    built: BuiltCase, template: Mapping[str, Any], urdf_path: str | os.PathLike[str]
) -> dict[str, Any]:
    """A scenario (the dict of a sensor_sim scenario file) for running ``built`` over
    topics: ``template``'s cameras (posed by position and look_at; moved along with the
    scene), light, noise and contact (a scenario file's dict, e.g. the default one's)
    with the case's posed plane (+-0.5 m of it: the template's curve is
    drawn on it, not tracked) and its arm (the URDF at ``urdf_path``, its tip frame the
    tool tip: no tool length, the start joints, the spec's base placement).

    Raises:
        InvalidInput: a case whose surface is no plane (only planes are posed here).
    """
    if built.surface.kind != 'plane':
        raise InvalidInput(
            f'only a plane case has a scenario here, got {built.surface.kind!r}',
            'surface',
            built.surface.kind,
        )
    T = built.surface.T_base_surface
    data = copy.deepcopy(dict(template))
    # The cameras moved with the scene (sensor_sim refuses a camera that does not see
    # the surface's centre): every position and aim shifted by the same vector.
    aims = [camera['pose']['look_at'] for camera in data['cameras'].values()]
    shift = T[:3, 3] - np.mean(np.array(aims, dtype=float), axis=0)
    for camera in data['cameras'].values():
        for key in ('position', 'look_at'):
            camera['pose'][key] = (np.array(camera['pose'][key], dtype=float) + shift).tolist()
    data['surface'] = {
        'type': 'plane',
        'scale': 1.0,
        'extent': [[-0.5, 0.5], [-0.5, 0.5]],
        'pose': {
            'xyz': T[:3, 3].tolist(),
            'quaternion': Rotation.from_matrix(T[:3, :3]).as_quat().tolist(),
        },
        'albedo': 0.8,
        'roughness': 0.3,
    }
    arm = built.spec.arm
    data['robot'] = {
        'model': str(urdf_path),
        'initial_joints': arm.start_joints.tolist(),
        'tip_frame': arm.tip_frame,
        'base_frame': arm.base_frame,
        'base_placement': [float(x) for x in built.spec.base_placement],
    }
    return data
