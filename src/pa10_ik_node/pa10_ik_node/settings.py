"""pa10_ik_node's settings outside the tracking task (``tracking.TrackingConfig``): the
arm's model, the velocity IK and the control loop. Each field made by ``setting`` is the
one source of the node parameter of its name (default, unit, range, description); the
node declares them and ``scripts/generate_params.py`` writes the params file and the
README table from them. No ROS.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pa10_ik_node.ik import METHODS, RateSolver
from pa10_ik_node.thesis import fixed_step_matrix
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.robot_model import RobotModel, load_robot, own_tool_length
from vgm_common.settings import setting

OWN_TOOL = -1.0  # tool_length: the model's own
THESIS_WEIGHTS = (1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0)  # §6.6
POSITIVE = (1e-9, 1e9)
# Keys of load_robot's errors that are parameters of their own; any other is the model's.
_ROBOT_KEYS = ('tip_frame', 'base_frame', 'base_placement')


def _check_tool_length(value: float) -> str | None:
    if value < 0 and value != OWN_TOOL:
        return f"a length >= 0 [m], or {OWN_TOOL:g} for the model's own"
    return None


def _check_weights(values: Sequence[float]) -> str | None:
    if not values or any(not np.isfinite(v) or v == 0 for v in values):
        return 'every weight must be finite and non-zero'
    return None


def _check_placement(values: Sequence[float]) -> str | None:
    return None if len(values) == 6 else 'needs 6 numbers'


@dataclass(frozen=True)
class ArmSettings:
    """The arm pa10_ik_node drives: its kinematic model, tip and speed cap."""

    robot: str = setting(
        'pa10', "Kinematic model: 'pa10', 'pa10_thesis' or a URDF path.", read_only=True
    )
    tool_length: float = setting(
        OWN_TOOL,
        "Tool beyond tip_frame along its z axis [m]; -1: the model's own (0.1 m for the "
        'built-in pa10 models, 0 for a URDF, whose tip frame is the tool tip). Must match '
        "the scenario's robot.tool_length.",
        range=(OWN_TOOL, 1.0),
        check=_check_tool_length,
        read_only=True,
    )
    tip_frame: str = setting(
        'tool0',
        'Tip frame of the URDF, any of its frames (z = approach axis); /tool/pressure '
        "must be stamped in it (the scenario's robot.tip_frame).",
        read_only=True,
    )
    base_frame: str = setting(
        '',
        "Frame of the URDF the arm's chain starts at ('': its root); joints moving it (a "
        "torso's, a lift's) are locked at neutral.",
        read_only=True,
    )
    base_placement: tuple[float, ...] = setting(
        (0.0,) * 6,
        'x, y, z [m], roll, pitch, yaw [rad] of base_frame in base_link (the frame of the '
        "waypoints and /tool_pose); = the scenario's robot.base_placement.",
        check=_check_placement,
        read_only=True,
    )
    max_joint_velocity: float = setting(
        1.0,
        "Cap on every joint speed, on top of the model's limits.",
        unit='rad/s',
        range=(0.01, 10.0),
        read_only=True,
    )

    @property
    def tool_length_m(self) -> float:
        """[m] The tool beyond tip_frame: ``tool_length``, or the model's own at -1."""
        return own_tool_length(self.robot) if self.tool_length < 0 else self.tool_length

    @property
    def tip_description(self) -> str:
        """How the model's tip is made, as a failure names it."""
        return f'tip_frame {self.tip_frame!r} + tool_length {self.tool_length_m:g} m'

    def load(self) -> RobotModel:
        """The arm's model. Raises ``InvalidInput`` keyed by the parameter at fault
        (``robot`` for a model that cannot be read)."""
        try:
            return load_robot(
                self.robot,
                self.tool_length_m,
                self.tip_frame,
                base_frame=self.base_frame,
                base_placement=self.base_placement,
            )
        except InvalidInput as error:
            key = error.key if error.key in _ROBOT_KEYS else 'robot'
            raise InvalidInput(f'parameter {key}: {error}', key, error.value) from None


@dataclass(frozen=True)
class SolverSettings:
    """The velocity IK (``ik.RateSolver``) and the thesis's fixed-step rule it reports."""

    method: str = setting(
        'ours',
        'Velocity IK: ours (closed-form KKT + feedback, joint '
        'limits), primal_dual (the thesis network), dls (reference).',
        choices=METHODS,
    )
    weights: tuple[float, ...] = setting(
        (1.0,) * 7,
        f'Diagonal of W, non-zero (may be indefinite, e.g. the thesis {list(THESIS_WEIGHTS)}).',
        check=_check_weights,
    )
    K: float = setting(100.0, 'Penalty gain of the primal-dual network.', range=POSITIVE)
    mu: float = setting(
        0.02,
        "Step size of the thesis's fixed-step rule for qdot. The node integrates the "
        'network exactly; with method primal_dual its diagnostics report the spectral '
        'radius of the fixed-step rule at mu, eta and the current joints '
        '(fixed_step_radius; > 1: the literal rule would diverge there).',
        range=POSITIVE,
    )
    eta: float = setting(
        0.02, "Step size of the thesis's fixed-step rule for lambda (see mu).", range=POSITIVE
    )
    damping: float = setting(
        0.05, 'DLS damping; largest adaptive damping of ours.', range=(0.0, 10.0)
    )

    def solver(self) -> RateSolver:
        """A new solver of these settings."""
        return RateSolver(self.method, self.weights, K=self.K, damping=self.damping)

    def fixed_step_radius(self, J: FloatArray) -> float:
        """Spectral radius of the thesis's literal learning rules (mu, eta) on the tip
        Jacobian ``J`` (m, n): below 1 they converge, above they diverge."""
        matrix = fixed_step_matrix(J, np.diag(self.weights), self.K, self.mu, self.eta)
        return float(np.max(np.abs(np.linalg.eigvals(matrix))))


def weights_per_joint(n_joints: int, weights: Sequence[float]) -> str | None:
    """Why ``weights`` are not one per joint of an ``n_joints`` arm (None: they are)."""
    count = len(weights)
    return None if count == n_joints else f"'weights' needs {n_joints} values, got {count}"


@dataclass(frozen=True)
class LoopSettings:
    """The control loop around the task: its rates, the inputs' watchdog, the command's
    horizon and whether it starts by itself (``session.TrackingSession`` reads them)."""

    rate: float = setting(100.0, 'Control rate.', unit='Hz', range=(100.0, 1000.0), read_only=True)
    # [s] pressure or joint states older than this while the task is active stop it;
    # also the freshness required to start.
    pressure_timeout: float = setting(
        1.0,
        'Pressure (or joint state) older than this [s] while active: stop.',
        range=(0.01, 60.0),
    )
    command_horizon: float = setting(
        0.05, 'time_from_start of the commanded point.', unit='s', range=(0.001, 1.0)
    )
    # Off by default: over topics on the loaded 2-core machine it helped some half-speed
    # runs and made others worse, with adapt_response compounding it (README, "What
    # misses its goal").
    lead_arm_lag: bool = setting(
        False,
        "Command one measured arm lag ahead (q + lag * qdot; the lag of the arm's "
        'joint states behind the set points sent, diagnostics arm_lag_ms, at most 0.1 s).',
    )
    # On by default: over topics (bench_pa10_ik.py --over-topics, 12 cases) the half-speed
    # arms' measured lag fell from 54-84 to 7-9 ms and their path RMS from 0.097-0.144 to
    # 0.015-0.017 mm, the other cases as before (12 of 12 within the path, force and
    # limit goals; 8 of 12 without it).
    send_set_point: bool = setting(
        True,
        'Send each moving command with the set point continued from the previous one as '
        'a first point at time 0 (else one point: the controller interpolates from the '
        "arm's state, which a lagging arm trails by several control steps).",
    )
    auto_start: bool = setting(
        False, 'Start as soon as valid waypoints, joint states and pressure are there.'
    )
    diagnostics_rate: float = setting(
        2.0, 'Rate of the tracking diagnostics.', unit='Hz', range=(0.1, 50.0), read_only=True
    )

    @property
    def control_period(self) -> float:
        """[s] The nominal control step."""
        return 1.0 / self.rate
