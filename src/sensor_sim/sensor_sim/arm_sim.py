"""A simulated position-controlled arm that follows joint trajectories.

The command follows the ros2_control joint_trajectory_controller convention: a
trajectory names its joints in any order, its points have ``time_from_start`` relative to
a start time, and a new trajectory replaces the old one. The arm moves toward the
interpolated set point as fast as its joint velocity limits allow and never leaves its
position limits; there are no dynamics beyond that.

Two more arms for the controller to cope with (``mode``, ``speed_scale``): a
``'velocity'`` arm follows only the commanded velocities (a velocity interface: each
point's velocity holds until that point's time, then zero; positions are ignored, so it
drifts unless its commander closes the loop on the measured state), and an arm slower
than commanded: ``speed_scale`` < 1 scales the commanded velocity (velocity mode) or
makes the position follow its set point with a first-order lag (position mode: each step
closes only that fraction of the gap). And an arm whose commands take effect late
(``command_delay``): a controller or network with that much latency.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import TYPE_CHECKING, Self

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

if TYPE_CHECKING:  # pinocchio, imported only for the type
    from vgm_common.robot_model import RobotModel

ARM_MODES = ('position', 'velocity')
# A commanded velocity beyond this multiple of a joint's limit is a broken controller's,
# refused rather than silently clamped (limits are enforced either way while moving).
IMPLAUSIBLE_SPEED = 10.0
# A set point this far beyond a joint's position limit is a broken command (1e300 rad),
# refused; closer ones (a commander's rounding at a limit) are clamped while moving.
LIMIT_SLACK_RAD = 0.1


class SimulatedArm:
    """Joint positions [rad] and velocities [rad/s] of an arm driven by trajectories.

    Args:
        joint_names: the n joint names; state vectors are in this order.
        lower_limits, upper_limits: (n,) position limits [rad].
        velocity_limits: (n,) positive speed limits [rad/s].
        q0: (n,) initial positions [rad], within the limits. The arm holds them.
        mode: ``'position'`` (follow the interpolated set point) or ``'velocity'``
            (follow only the commanded velocities).
        speed_scale: in (0, 1]: the fraction of the commanded motion the arm makes.
        command_delay: [s] >= 0: each trajectory takes effect only this long after its
            ``start_time`` (its times then count from there), the previous one in force
            until then.

    Raises:
        InvalidInput: inconsistent or non-finite limits, ``q0`` outside them, an unknown
            mode, a speed_scale outside (0, 1] or a negative or non-finite command_delay.
    """

    def __init__(
        self,
        joint_names: Iterable[str],
        lower_limits: npt.ArrayLike,
        upper_limits: npt.ArrayLike,
        velocity_limits: npt.ArrayLike,
        q0: npt.ArrayLike,
        mode: str = 'position',
        speed_scale: float = 1.0,
        command_delay: float = 0.0,
    ) -> None:
        if mode not in ARM_MODES:
            raise InvalidInput(f'mode must be one of {ARM_MODES}, got {mode!r}', 'mode', mode)
        if not (isinstance(speed_scale, (int, float)) and 0.0 < speed_scale <= 1.0):
            raise InvalidInput(
                f'speed_scale must be in (0, 1], got {speed_scale!r}', 'speed_scale', speed_scale
            )
        if not (isinstance(command_delay, (int, float)) and 0.0 <= command_delay < np.inf):
            raise InvalidInput(
                f'command_delay must be a finite number >= 0 [s], got {command_delay!r}',
                'command_delay',
                command_delay,
            )
        self.mode, self.speed_scale = mode, float(speed_scale)
        self.command_delay = float(command_delay)
        # Trajectories received but not yet in force: (time they take effect [s], command).
        self._pending: deque[tuple[float, tuple[FloatArray, FloatArray, FloatArray | None]]] = (
            deque()
        )
        self.joint_names = tuple(joint_names)
        n = len(self.joint_names)
        if len(set(self.joint_names)) != n:
            raise InvalidInput(
                f'duplicate joint names {self.joint_names}', 'joint_names', self.joint_names
            )
        self._lower = _read_only(_vector(lower_limits, n, 'lower_limits'))
        self._upper = _read_only(_vector(upper_limits, n, 'upper_limits'))
        self._qdot_max = _read_only(_vector(velocity_limits, n, 'velocity_limits'))
        if np.any(self._lower > self._upper) or np.any(self._qdot_max <= 0):
            raise InvalidInput('need lower <= upper and velocity limits > 0')
        q0 = _vector(q0, n, 'q0')
        if np.any(q0 < self._lower) or np.any(q0 > self._upper):
            raise InvalidInput(f'q0 {q0} is outside the joint limits', 'q0', q0)
        self._q = q0
        self._qdot = np.zeros(n)
        self._stepped_to: float | None = None  # [s] the time ``step`` last advanced to
        self._last_dt = 0.0  # [s] and by how much
        self.hold()

    @classmethod
    def from_robot_model(
        cls,
        robot: RobotModel,
        q0: npt.ArrayLike,
        mode: str = 'position',
        speed_scale: float = 1.0,
        command_delay: float = 0.0,
    ) -> Self:
        """An arm with the joints and limits of a ``vgm_common.robot_model.RobotModel``."""
        return cls(
            robot.joint_names,
            robot.lower_limits,
            robot.upper_limits,
            robot.velocity_limits,
            q0,
            mode,
            speed_scale,
            command_delay,
        )

    @property
    def q(self) -> FloatArray:
        """(n,) current positions [rad] (a copy)."""
        return self._q.copy()

    @property
    def qdot(self) -> FloatArray:
        """(n,) velocities [rad/s] over the last step (a copy)."""
        return self._qdot.copy()

    def hold(self) -> None:
        """Replace the command by holding the current position, at once (the simulator's
        own reaction to a bad command: no delay), dropping trajectories not yet in force."""
        self._pending.clear()
        self._set_command(np.zeros(1), self._q[np.newaxis], None, start_time=-np.inf)

    def set_trajectory(
        self,
        joint_names: str | Iterable[str],
        times_from_start: npt.ArrayLike,
        positions: npt.ArrayLike,
        velocities: npt.ArrayLike | None = None,
        start_time: float = 0.0,
    ) -> None:
        """Replace the command by a trajectory.

        Args:
            joint_names: the arm's n joint names, in any order, each once.
            times_from_start: (N,) strictly increasing times >= 0 [s] after ``start_time``.
            positions: (N, n) positions [rad], columns in the order of ``joint_names``.
            velocities: (N, n) velocities [rad/s] for cubic Hermite interpolation, or
                None / empty for linear interpolation.
            start_time: [s] simulation time at which ``times_from_start`` counts from 0.

        The arm holds its current position until ``start_time`` (+ ``command_delay``: the
        previous trajectory stays in force until then); if the first point is later than
        0 s, the trajectory starts from the state it then has; after the last point the
        arm holds that point.
        A single point at 0 s means "go there now", as fast as the limits allow.

        Raises:
            InvalidInput: unknown, missing or duplicate joint names, wrong shapes,
                non-finite values, times not strictly increasing, positions beyond the
                position limits by more than LIMIT_SLACK_RAD or velocities beyond
                IMPLAUSIBLE_SPEED times the limits. The previous command stays in force.
        """
        order = self._column_order(joint_names)
        times = _array(times_from_start, 'times_from_start')
        n_points, n = len(times), len(order)
        if times.shape != (n_points,) or n_points == 0:
            raise InvalidInput(
                f'times_from_start must be a non-empty 1-D list, got shape {times.shape}',
                'times_from_start',
                times_from_start,
            )
        if times[0] < 0 or np.any(np.diff(times) <= 0):
            raise InvalidInput(
                f'times_from_start must be >= 0 and strictly increasing, got {times}',
                'times_from_start',
                times_from_start,
            )
        positions = _array(positions, 'positions', (n_points, n))
        self._check_within_limits(positions[:, order])
        if velocities is not None and np.size(velocities) == 0:
            velocities = None
        if velocities is not None:
            velocities = _array(velocities, 'velocities', (n_points, n))
            velocities = velocities[:, order]
            too_fast = np.abs(velocities) > IMPLAUSIBLE_SPEED * self._qdot_max
            if np.any(too_fast):
                raise InvalidInput(
                    f'velocities up to {np.abs(velocities).max():.3g} rad/s: beyond '
                    f'{IMPLAUSIBLE_SPEED:g} times the joint limits, not a command to follow',
                    'velocities',
                    velocities,
                )
        start = _array(start_time, 'start_time')
        if start.shape != ():
            raise InvalidInput(f'start_time must be a number, got {start}', 'start_time', start)
        if self.command_delay > 0:
            self._pending.append(
                (float(start) + self.command_delay, (times, positions[:, order], velocities))
            )
        else:
            # Received between two steps: from where the arm is then, not where the last
            # step left it (which drops the motion in between from every command).
            state = self._state_at(float(start))
            self._set_command(times, positions[:, order], velocities, start, state)

    def step(self, t: float, dt: float) -> tuple[FloatArray, FloatArray]:
        """Advance the arm by ``dt`` [s] toward the set point at time ``t`` [s].

        Each joint moves at most ``velocity_limit * dt`` and stops at its position limits.

        Returns:
            (q, qdot): (n,) new positions [rad] and the velocities over the step [rad/s].
        """
        if not (np.isfinite(t) and np.isfinite(dt) and dt > 0):
            raise InvalidInput(f'need finite t and dt > 0, got t={t}, dt={dt}', 'dt', dt)
        # A command in force at the step's start (within a nanosecond of stamp rounding)
        # drives it, as a prompt one received then does.
        while self._pending and self._pending[0][0] <= t - dt + 1e-9:
            effective, command = self._pending.popleft()
            self._set_command(*command, effective)
        max_step = self._qdot_max * dt
        if self.mode == 'velocity':
            motion = self.speed_scale * self.commanded_velocity(t) * dt
        else:
            motion = self.speed_scale * (self.desired(t) - self._q)
        q_new = self._q + np.clip(motion, -max_step, max_step)
        q_new = np.clip(q_new, self._lower, self._upper)
        self._qdot = (q_new - self._q) / dt
        self._q = q_new
        self._stepped_to, self._last_dt = float(t), float(dt)
        return self.q, self.qdot

    def _state_at(self, t: float) -> tuple[FloatArray, FloatArray]:
        """(q, qdot) at time ``t`` [s]: the arm moves on between the simulation's steps at
        the velocity of the last one (within its limits), as joint_trajectory_controller
        reads the state at the time it takes a trajectory; the last step's state at or
        before that step's time. Moved on for one step's time at most: a simulation
        stalled longer does not guess where the arm would have gone."""
        if self._stepped_to is None or not t > self._stepped_to:
            return self._q.copy(), self._qdot.copy()
        ahead = min(t - self._stepped_to, self._last_dt)
        q = np.clip(self._q + self._qdot * ahead, self._lower, self._upper)
        return q, self._qdot.copy()

    def follow_velocity(
        self,
        joint_names: str | Iterable[str],
        qdot: npt.ArrayLike,
        t: float,
        period: float,
        horizon: float = 0.05,
        substeps: int = 2,
    ) -> float:
        """One control period of a velocity controller in an offline closed loop (tests,
        bench): the command pa10_ik_node sends (q + qdot * horizon at ``horizon`` [s] with
        velocity qdot, from time ``t``), followed in ``substeps`` steps as sensor_sim's
        faster loop does. Returns the time after the period [s]."""
        velocity = np.asarray(qdot)
        self.set_trajectory(
            joint_names, [horizon], [self._q + horizon * velocity], [velocity], start_time=t
        )
        for _ in range(substeps):
            t += period / substeps
            self.step(t, period / substeps)
        return t

    def commanded_velocity(self, t: float) -> FloatArray:
        """(n,) velocity command [rad/s] at time ``t`` [s] (velocity mode): the velocity of
        the point the trajectory is heading for (its positions' slope where it has no
        velocities), zero before the start and after the last point."""
        times, positions, velocities = self._times, self._positions, self._velocities
        tau = t - self._start_time
        if tau < 0 or tau >= times[-1] or len(times) < 2:
            return np.zeros(len(self._q))
        i = max(int(np.searchsorted(times, tau, side='right')) - 1, 0)
        if velocities is not None:
            return velocities[i + 1].copy()
        return (positions[i + 1] - positions[i]) / (times[i + 1] - times[i])

    def desired(self, t: float) -> FloatArray:
        """(n,) set point [rad] of the current command at time ``t`` [s]."""
        times, positions, velocities = self._times, self._positions, self._velocities
        tau = t - self._start_time
        if tau < 0:
            return self._q_at_command.copy()
        if tau <= times[0]:
            return positions[0].copy()
        if tau >= times[-1]:
            return positions[-1].copy()
        i = np.searchsorted(times, tau, side='right') - 1
        h = times[i + 1] - times[i]
        s = (tau - times[i]) / h
        if velocities is None:
            return positions[i] + s * (positions[i + 1] - positions[i])
        # Cubic Hermite basis on [0, 1]; velocities scale by the segment length h.
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        return (
            h00 * positions[i]
            + h10 * h * velocities[i]
            + h01 * positions[i + 1]
            + h11 * h * velocities[i + 1]
        )

    def _set_command(
        self,
        times: FloatArray,
        positions: FloatArray,
        velocities: FloatArray | None,
        start_time: float | FloatArray,
        start_state: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        if times[0] > 0:
            # As joint_trajectory_controller does: start from where the arm is (at
            # ``start_state`` (q, qdot), else as the last step left it).
            q, qdot = start_state or (self._q, self._qdot)
            times = np.concatenate([[0.0], times])
            positions = np.vstack([q, positions])
            if velocities is not None:
                velocities = np.vstack([qdot, velocities])
        self._times, self._positions, self._velocities = times, positions, velocities
        self._start_time = float(start_time)
        self._q_at_command = self._q.copy()  # held until start_time

    def _check_within_limits(self, positions: FloatArray) -> None:
        """Raise InvalidInput naming the first joint of ``positions`` ((N, n), arm order)
        beyond its limits by more than LIMIT_SLACK_RAD."""
        beyond = (positions < self._lower - LIMIT_SLACK_RAD) | (
            positions > self._upper + LIMIT_SLACK_RAD
        )
        if not np.any(beyond):
            return
        point, joint = (int(i) for i in np.argwhere(beyond)[0])
        raise InvalidInput(
            f'point {point}: {self.joint_names[joint]} at {positions[point, joint]:.4g} rad is '
            f'beyond its limits [{self._lower[joint]:.4g}, {self._upper[joint]:.4g}] by more '
            f'than {LIMIT_SLACK_RAD:g} rad, not a command to follow',
            'positions',
            positions,
        )

    def _column_order(self, joint_names: str | Iterable[str]) -> npt.NDArray[np.intp]:
        """Indices that put columns given in ``joint_names`` order into the arm's order."""
        names = [joint_names] if isinstance(joint_names, str) else list(joint_names)
        unknown = sorted(set(names) - set(self.joint_names))
        if unknown:
            raise InvalidInput(f'unknown joint names {unknown}', 'joint_names', unknown)
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise InvalidInput(f'duplicate joint names {duplicates}', 'joint_names', duplicates)
        missing = [name for name in self.joint_names if name not in names]
        if missing:
            raise InvalidInput(f'missing joint names {missing}', 'joint_names', missing)
        return np.array([names.index(name) for name in self.joint_names])


def _array(value: npt.ArrayLike, key: str, shape: tuple[int, ...] | None = None) -> FloatArray:
    """``value`` as a new finite float array (of ``shape``, if given); raises
    ``InvalidInput`` otherwise."""
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError) as err:  # ragged lists, strings
        raise InvalidInput(f'{key} must be numbers, got {value!r}', key, value) from err
    if shape is not None and array.shape != shape:
        raise InvalidInput(
            f'{key} must have shape {shape}, got {array.shape}',
            key,
            array,
        )
    if not np.all(np.isfinite(array)):
        raise InvalidInput(f'{key} must be finite, got {array}', key, value)
    return array


def _vector(value: npt.ArrayLike, n: int, key: str) -> FloatArray:
    return _array(value, key, (n,))


def _read_only(array: FloatArray) -> FloatArray:
    array.flags.writeable = False
    return array
