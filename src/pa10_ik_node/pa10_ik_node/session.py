"""A tracking session without ROS: it takes the measured joints, the pressure and the
waypoints, checks them, starts and stops the task, and at every control step returns the
joint command and the measured tool pose, the phase changes to log and the tracking
diagnostic. pa10_ik_node only converts messages, publishes and logs what the session
returns; the session is unit-tested on plain arrays with an injected clock (the
stale-pressure stop among others).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np

from pa10_ik_node.commands import JointCommand, SetPointCommands
from pa10_ik_node.path import validate_waypoints
from pa10_ik_node.settings import ArmSettings, LoopSettings, SolverSettings, weights_per_joint
from pa10_ik_node.tracking import ACTIVE_PHASES, TrackingConfig, TrackingController, Unreachable
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.geometry import FloatArray
from vgm_common.topics import BASE_FRAME, JOINT_STATES_TOPIC, PRESSURE_TOPIC, WAYPOINTS_TOPIC

MAX_FORCE_N = 1e4  # a pressure reading beyond this is a broken sensor, not a contact
JOINT_LIMIT_SLACK_RAD = 0.1  # a measured joint this far outside its limits is no reading
STEP_TIMES_KEPT = 500  # control step (and IK) times kept for the medians in the diagnostics
# The joint measured this long before the control step at most is taken as measured then
# (older: the joint state's stamp is on another clock, its receipt counts).
MAX_JOINT_STATE_AGE_S = 0.1
# [s] A joint state this old is no measurement to act on: the task waits for a new one
# (no command, its timers still). Far beyond the 5 ms between the simulator's joint states
# and their jitter on a loaded machine, far below the 2 s the task allows an arm to make
# no progress: judged on an old reading (a simulator starved for 2 s within a
# pressure_timeout of 3 s), a moving arm looked stuck and the approach failed.
OLD_JOINT_STATE_S = 0.25


class ControlOutput(NamedTuple):
    """What a control step publishes: the measured tool pose (4, 4) in base_link and the
    joint command, if any."""

    T_base_tool: FloatArray
    command: JointCommand | None


class PhaseChange(NamedTuple):
    """A phase the task entered, as the node logs it: ``level`` 'error' (failed), 'warn'
    (stopped) or 'info', ``message`` the line at that level, ``summary`` a line about the
    finished tracking ('' unless done)."""

    level: str
    message: str
    summary: str


class Status(NamedTuple):
    """The tracking diagnostic: ``level`` 'ok', 'warn' or 'error', ``message`` (the phase
    and why), ``values`` (key -> value, as /diagnostics carries them)."""

    level: str
    message: str
    values: dict[str, Any]


class TrackingSession:
    """The measured state of the arm and its tracking task, between messages.

    Args:
        controller: the task (its robot, solver and settings).
        tip_frame: the frame /tool/pressure must be stamped in.
        settings: the loop's settings (``LoopSettings``), read at each use: a new one
            assigned to ``settings`` applies at the next step.
        solver_settings: how ``controller``'s solver was made (the diagnostics report
            them); ``configure_solver`` changes both.
        clock: monotonic seconds (``time.monotonic``; a test's own clock).
    """

    def __init__(
        self,
        controller: TrackingController,
        tip_frame: str,
        settings: LoopSettings,
        solver_settings: SolverSettings | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.controller = controller
        self.robot = controller.robot
        self.tip_frame = tip_frame
        self.settings = settings
        self.solver_settings = solver_settings or SolverSettings()
        self.control_period = settings.control_period  # [s] (rate is read-only)
        self.clock = clock
        self.joint_index = {name: i for i, name in enumerate(self.robot.joint_names)}
        self.q: FloatArray | None = None  # measured joints, robot order [rad]
        self.force = 0.0  # [N]
        self.joint_state_time: float | None = None  # clock() when measured [s]
        self.pressure_time: float | None = None
        self.waypoints: FloatArray | None = None  # (N, 4, 4) base_link
        self.last_step: float | None = None  # clock() of the previous control step
        self.commands = SetPointCommands()  # the moving commands and the arm's lag
        self.last_info: dict[str, Any] = {}
        self.step_times: deque[float] = deque(maxlen=STEP_TIMES_KEPT)  # [s]
        self.ik_times: deque[float] = deque(maxlen=STEP_TIMES_KEPT)  # [s] the solve alone
        self.null_space_failures = 0
        self.last_failure_condition = ''
        self.internal_errors = 0  # failures of the caller's own code (``fail``)
        self.logged_phase = controller.phase  # the phase ``phase_change`` last told

    @classmethod
    def create(
        cls,
        arm: ArmSettings,
        solver: SolverSettings,
        tracking: TrackingConfig,
        loop: LoopSettings,
        clock: Callable[[], float] = time.monotonic,
    ) -> TrackingSession:
        """The session of the arm ``arm`` describes (``InvalidInput`` keyed by the
        parameter at fault if its model cannot be loaded), its solver and task."""
        robot = arm.load()
        if reason := weights_per_joint(robot.n_joints, solver.weights):
            raise InvalidInput(f'parameters: {reason}', 'weights', solver.weights)
        controller = TrackingController(
            robot,
            solver.solver(),
            tracking,
            max_joint_velocity=arm.max_joint_velocity,
            tip_description=arm.tip_description,
        )
        return cls(controller, arm.tip_frame, loop, solver, clock)

    def configure_solver(self, settings: SolverSettings) -> None:
        """Use a solver of ``settings`` from the next step on."""
        self.solver_settings = settings
        self.controller.solver = settings.solver()

    # --- inputs ----------------------------------------------------------------------

    def take_joint_state(
        self, names: Sequence[str], positions: Sequence[float], age: float = 0.0
    ) -> None:
        """Keep the measured joints, measured ``age`` [s] ago (its stamp's age; 0 or
        beyond MAX_JOINT_STATE_AGE_S: now); ``InvalidInput`` for a reading that cannot be
        the arm's (unknown, duplicate or missing names, non-finite or far outside the
        joint limits)."""
        names = list(names)
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise InvalidInput(f'duplicate joint names {duplicates}', 'name', duplicates)
        unknown = sorted(set(names) - set(self.joint_index))
        if unknown:
            raise InvalidInput(f'unknown joint names {unknown}', 'name', unknown)
        missing = sorted(set(self.joint_index) - set(names))
        if missing or len(names) != len(positions):
            raise InvalidInput(
                f'need one position for each of {self.robot.n_joints} '
                f'joints (missing {missing}, {len(positions)} '
                f'positions for {len(names)} names)',
                'position',
            )
        q = np.empty(self.robot.n_joints)
        for name, value in zip(names, positions):
            q[self.joint_index[name]] = value
        q = self.robot.check_q(q)
        lower = self.robot.lower_limits - JOINT_LIMIT_SLACK_RAD
        upper = self.robot.upper_limits + JOINT_LIMIT_SLACK_RAD
        outside = np.flatnonzero((q < lower) | (q > upper))
        if outside.size:
            i = int(outside[0])
            raise InvalidInput(
                f'{self.robot.joint_names[i]} at {q[i]:.6g} rad is more than '
                f'{JOINT_LIMIT_SLACK_RAD} rad outside its limits '
                f'[{self.robot.lower_limits[i]:.4g}, {self.robot.upper_limits[i]:.4g}]',
                'position',
                q[i],
            )
        self.q = q
        if not 0.0 <= age <= MAX_JOINT_STATE_AGE_S:
            age = 0.0
        self.joint_state_time = self.clock() - age

    def take_pressure(self, frame: str, force: float) -> None:
        """Keep the measured force [N]; ``InvalidInput`` for another frame than the tip's
        or a reading no sensor gives."""
        if frame != self.tip_frame:
            raise InvalidInput(
                f'frame {frame!r}, expected the tip frame {self.tip_frame!r} '
                '(parameter tip_frame)',
                'frame_id',
                frame,
            )
        if not (np.isfinite(force) and abs(force) <= MAX_FORCE_N):
            raise InvalidInput(
                f'force.z is {force} N, beyond the sanity bound '
                f'+-{MAX_FORCE_N:g} N (a broken sensor)',
                'force.z',
                force,
            )
        self.force = float(force)
        self.pressure_time = self.clock()

    def take_waypoints(self, frame: str, waypoints: FloatArray) -> str | None:
        """Keep a path (N, 4, 4) in ``frame``; a running task takes it over from its
        progress. Returns a line to log about the takeover (None if none);
        ``InvalidInput`` for a path that cannot be followed."""
        if frame != BASE_FRAME:
            raise InvalidInput(f'frame {frame!r}, expected {BASE_FRAME!r}', 'frame_id', frame)
        waypoints = validate_waypoints(waypoints)
        takeover = None
        if self.controller.phase in ACTIVE_PHASES and self.q is not None:
            tip = self.robot.forward_kinematics(self.q)[:3, 3]
            self.controller.update_path(waypoints, tip)
            takeover = (
                f'took over a new path of {len(waypoints)} waypoints at '
                f'progress {self.controller.progress:.3f}'
            )
        self.waypoints = waypoints
        return takeover

    # --- the task --------------------------------------------------------------------

    def missing_inputs(self) -> list[str]:
        """The topics without a (recent) message, which the task needs to start."""
        missing = []
        if self.waypoints is None:
            missing.append(WAYPOINTS_TOPIC)
        if not self._fresh(self.joint_state_time):
            missing.append(JOINT_STATES_TOPIC)
        if not self._fresh(self.pressure_time):
            missing.append(PRESSURE_TOPIC)
        return missing

    def start(self) -> tuple[bool, str, JointCommand | None]:
        """Start the task on the newest path: (success, message, a hold to send if
        starting failed on an unreachable path)."""
        missing = self.missing_inputs()
        waypoints = self.waypoints
        if missing or waypoints is None or self.q is None:  # None: among the missing
            return False, f'cannot start: no recent {", ".join(missing)}', None
        self.commands.restart()  # a new task's commands start from the measured joints
        try:
            self.controller.start(waypoints, self.q)
        except Unreachable as error:
            self.controller.fail(f'unreachable waypoints: {error}')
            return False, self.controller.reason, self.hold()
        except VgmError as error:
            return False, f'cannot start: {error}', None
        path = self.controller.path
        assert path is not None  # set by start()
        return (
            True,
            f'started on {len(waypoints)} waypoints: a {path.length * 1e3:.0f} mm path, about '
            f'{self.controller.nominal_tracking_time():.1f} s along it',
            None,
        )

    def stop(self, reason: str) -> JointCommand | None:
        """Stop the task; returns the hold to send."""
        self.controller.stop(reason)
        return self.hold()

    def fail(self, reason: str) -> JointCommand | None:
        """Fail a running task on an internal error of the caller (a solver, a singular
        configuration, a bug), counted in ``internal_errors``; returns the hold to send."""
        self.internal_errors += 1
        if self.controller.phase in (*ACTIVE_PHASES, 'done'):
            self.controller.fail(reason)
        return self.hold()

    def hold(self) -> JointCommand | None:
        """Zero velocity at the measured position, now (horizon 0: a position arm does
        not coast on to a point ahead, a velocity arm gets zero at once); None before
        any joint state."""
        self.commands.restart()
        if self.q is None:
            return None
        return JointCommand(self.q.copy(), np.zeros(self.robot.n_joints), 0.0)

    def control_step(self, auto_start: bool = False) -> ControlOutput | None:
        """One step of the loop: the watchdog on the inputs, the controller's step and
        the command; None before any joint state."""
        q = self.q
        if q is None:
            return None
        controller = self.controller
        if auto_start and controller.phase == 'idle' and not self.missing_inputs():
            hold = self.start()[2]
            if hold is not None:  # an unreachable path: failed before moving
                return ControlOutput(self.robot.forward_kinematics(q), hold)
        # The step the timer really took (a loaded machine runs it late), bounded so one
        # long stall does not become a jump: the reference then moves at the set speed.
        now = self.clock()
        timeout = self.settings.pressure_timeout
        stalled = self.last_step is not None and now - self.last_step > timeout / 2
        if self.last_step is None:
            dt = self.control_period
        else:
            dt = min(now - self.last_step, 3 * self.control_period)
        self.last_step = now
        # After a stall of the caller's own executor the sensors' newest messages are
        # still queued behind this step: judge their freshness on the next one.
        if controller.phase in ACTIVE_PHASES and not stalled:
            for stamp, topic, what in (
                (self.pressure_time, PRESSURE_TOPIC, 'pressure'),
                (self.joint_state_time, JOINT_STATES_TOPIC, 'joint states'),
            ):
                if not self._fresh(stamp):
                    controller.stop(f'stale {what}: no {topic} for more than {timeout} s')
                    return ControlOutput(self.robot.forward_kinematics(q), self.hold())
        if controller.phase not in (*ACTIVE_PHASES, 'done'):
            self.commands.restart()  # nothing sent: the next command starts afresh
            return ControlOutput(self.robot.forward_kinematics(q), None)
        assert self.joint_state_time is not None  # set with q
        if now - self.joint_state_time > OLD_JOINT_STATE_S:
            return ControlOutput(self.robot.forward_kinematics(q), None)
        controller.arm_lag = self.commands.lag
        started = time.perf_counter()
        qdot, info = controller.step(q, self.force, dt)
        self.step_times.append(time.perf_counter() - started)
        if 'ik_time' in info:
            self.ik_times.append(info['ik_time'])
        self.last_info = info
        self._note_solver_failure(info)
        if controller.phase in ('stopped', 'failed'):
            command = self.hold()
        else:
            self.commands.measure(q, self.joint_state_time)
            self.commands.covered_lag = controller.config.command_latency
            self.commands.compensate_lag = self.settings.lead_arm_lag
            self.commands.send_set_point = self.settings.send_set_point
            command = self.commands.command(q, qdot, now, self.settings.command_horizon)
        return ControlOutput(info['T'], command)

    def _note_solver_failure(self, info: dict[str, Any]) -> None:
        if info.get('diverged'):
            self.null_space_failures += 1
            self.last_failure_condition = (
                'W + K J^T J not positive definite at any K (near a singularity): the '
                'network diverges; used the KKT solution'
            )
        elif info.get('null_space_positive') is False:
            self.null_space_failures += 1
            self.last_failure_condition = (
                f'W not positive on null(J) (min eigenvalue '
                f'{info.get("min_null_eigenvalue", float("nan")):.3g}); fell back to |W|'
            )

    # --- what the node reports ---------------------------------------------------------

    def phase_change(self) -> PhaseChange | None:
        """The phase the task entered since the last call, as the lines to log (None if
        it is the same)."""
        controller = self.controller
        phase = controller.phase
        if phase == self.logged_phase:
            return None
        self.logged_phase = phase
        summary = ''
        if phase == 'done':
            rms, force_band = controller.stats.summary()
            summary = (
                f'tracking done: rms position error {rms * 1e3:.3f} mm, force within '
                f'+-{force_band:.3f} N of desired ({controller.config.desired_force} N)'
            )
        if phase == 'failed':
            return PhaseChange('error', f'phase failed: {controller.reason}', summary)
        if phase == 'stopped':
            return PhaseChange('warn', f'phase stopped: {controller.reason}', summary)
        return PhaseChange('info', f'phase {phase}', summary)

    def status(self) -> Status:
        """The tracking diagnostic: phase, progress, errors, the arm's response, the
        solver's failures and the step time."""
        controller, info, force = self.controller, self.last_info, self.force
        config = controller.config
        phase = controller.phase
        if phase == 'approach' and controller.stage == 'descend' and force > 0:
            phase = 'contact'  # touching, force building up
        values: dict[str, Any] = {
            'phase': phase,
            'stage': controller.stage,
            'progress': f'{controller.progress:.4f}',
            'position_error_m': f'{info.get("position_error", float("nan")):.6f}',
            'force_N': f'{force:.4f}',
            'force_error_N': f'{force - config.desired_force:.4f}',
            'arm_response': f'{controller.response:.3f}',
            'phi_rad': f'{info.get("phi", float("nan")):.5f}',
            'step_time_ms': _median_ms(self.step_times),
            'ik_time_ms': _median_ms(self.ik_times),
            'arm_lag_ms': f'{self.commands.lag * 1e3:.1f}',
            'method': self.solver_settings.method,
            'force_law': config.force_law,
            'reason': controller.reason,
        }
        if self.solver_settings.method == 'primal_dual':
            values['failure_condition'] = self.last_failure_condition or 'none detected'
            values['null_space_failures'] = self.null_space_failures
            if self.q is not None:
                radius = self.solver_settings.fixed_step_radius(self.robot.jacobian(self.q))
                values['fixed_step_radius'] = f'{radius:.6g}'
        rms, force_band = controller.stats.summary()
        values.update(rms_position_error_m=f'{rms:.6f}', max_force_error_N=f'{force_band:.4f}')
        level = {'failed': 'error', 'stopped': 'warn'}.get(controller.phase, 'ok')
        message = controller.phase + (f': {controller.reason}' if controller.reason else '')
        return Status(level, message, values)

    def _fresh(self, stamp: float | None) -> bool:
        return stamp is not None and self.clock() - stamp <= self.settings.pressure_timeout


def _median_ms(times: deque[float]) -> str:
    """The median of ``times`` [s] in ms, as the diagnostics carry it ('nan': none)."""
    return f'{np.median(times) * 1e3:.4f}' if times else 'nan'
