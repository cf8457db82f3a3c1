"""A tracking session without ROS: it takes the measured joints, the pressure and the
waypoints, checks them, starts and stops the task, and at every control step returns the
joint command and the measured tool pose. pa10_ik_node only converts messages, publishes
and logs what the session returns; the session is unit-tested on plain arrays with an
injected clock (the stale-pressure stop among others).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, Protocol

import numpy as np

from pa10_ik_node.path import validate_waypoints
from pa10_ik_node.tracking import ACTIVE_PHASES, TrackingController, Unreachable
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.geometry import FloatArray
from vgm_common.topics import BASE_FRAME, JOINT_STATES_TOPIC, PRESSURE_TOPIC, WAYPOINTS_TOPIC

MAX_FORCE_N = 1e4  # a pressure reading beyond this is a broken sensor, not a contact
JOINT_LIMIT_SLACK_RAD = 0.1  # a measured joint this far outside its limits is no reading
STEP_TIMES_KEPT = 500  # control step times kept for the median in the diagnostics


class JointCommand(NamedTuple):
    """One trajectory point: ``positions`` (n,) [rad] at ``horizon`` [s] from now, moving
    at ``velocities`` (n,) [rad/s] (horizon 0: a hold, at once)."""

    positions: FloatArray
    velocities: FloatArray
    horizon: float


class ControlOutput(NamedTuple):
    """What a control step publishes: the measured tool pose (4, 4) in base_link and the
    joint command, if any."""

    T_base_tool: FloatArray
    command: JointCommand | None


class SessionSettings(Protocol):
    """The session's settings that may change while it runs (pa10_ik_node passes its
    parameters, which a set_parameters call changes): read at every use, never copied."""

    # [s] pressure or joint states older than this while the task is active stop it;
    # also the freshness required to start.
    pressure_timeout: float
    command_horizon: float  # [s] time_from_start of the commanded point


class TrackingSession:
    """The measured state of the arm and its tracking task, between messages.

    Args:
        controller: the task (its robot, solver and settings).
        tip_frame: the frame /tool/pressure must be stamped in.
        settings: ``pressure_timeout`` and ``command_horizon`` (``SessionSettings``), as
            they are at each step.
        control_period: [s] the nominal control step.
        clock: monotonic seconds (``time.monotonic``; a test's own clock).
    """

    def __init__(
        self,
        controller: TrackingController,
        tip_frame: str,
        settings: SessionSettings,
        control_period: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.controller = controller
        self.robot = controller.robot
        self.tip_frame = tip_frame
        self.settings = settings
        self.control_period = control_period
        self.clock = clock
        self.joint_index = {name: i for i, name in enumerate(self.robot.joint_names)}
        self.q: FloatArray | None = None  # measured joints, robot order [rad]
        self.force = 0.0  # [N]
        self.joint_state_time: float | None = None  # clock() at receipt [s]
        self.pressure_time: float | None = None
        self.waypoints: FloatArray | None = None  # (N, 4, 4) base_link
        self.last_step: float | None = None  # clock() of the previous control step
        self.last_info: dict[str, Any] = {}
        self.step_times: deque[float] = deque(maxlen=STEP_TIMES_KEPT)  # [s]
        self.null_space_failures = 0
        self.last_failure_condition = ''

    # --- inputs ----------------------------------------------------------------------

    def take_joint_state(self, names: Sequence[str], positions: Sequence[float]) -> None:
        """Keep the measured joints; ``InvalidInput`` for a reading that cannot be the
        arm's (unknown, duplicate or missing names, non-finite or far outside the joint
        limits)."""
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
        self.joint_state_time = self.clock()

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
        """Fail a running task (an internal error); returns the hold to send."""
        if self.controller.phase in (*ACTIVE_PHASES, 'done'):
            self.controller.fail(reason)
        return self.hold()

    def hold(self) -> JointCommand | None:
        """Zero velocity at the measured position, now (horizon 0: a position arm does
        not coast on to a point ahead, a velocity arm gets zero at once); None before
        any joint state."""
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
            return ControlOutput(self.robot.forward_kinematics(q), None)
        started = time.perf_counter()
        qdot, info = controller.step(q, self.force, dt)
        self.step_times.append(time.perf_counter() - started)
        self.last_info = info
        self._note_solver_failure(info)
        if controller.phase in ('stopped', 'failed'):
            command = self.hold()
        else:
            horizon = self.settings.command_horizon
            command = JointCommand(q + qdot * horizon, qdot, horizon)
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

    def _fresh(self, stamp: float | None) -> bool:
        return stamp is not None and self.clock() - stamp <= self.settings.pressure_timeout
