"""The joint commands of a control loop, as pa10_ik_node sends them: a trajectory point
``positions`` at ``horizon`` moving at ``velocities`` (joint_trajectory_controller's
convention), each continuing the previous command's set point (if asked, sent as a first
point at time 0, so the arm's set point does not restart from where a lagging arm is)
and, if asked, led by the arm's measured lag. ``TrackingSession`` sends them; the offline closed
loop of the tests and benches (vgm_evaluation.task_generator.run_closed_loop) sends the
same.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vgm_common.geometry import FloatArray

# [s] A moving command's set point continues the previous one's, leading the measured
# joints by at most this much of the commanded joint motion (see SetPointCommands.anchor).
MAX_COMMAND_LEAD_S = 0.1
# [s] The lag compensated at most: beyond it an arm is not lagging but failing to follow
# (the task's cannot-follow check judges that), and a lead that large on a path's bend
# would cut it.
MAX_LAG_S = 0.1
LAG_WINDOW_S = 1.0  # [s] forgetting time of the lag estimate
# [s] of measured motion before the estimate is used (a start's transient is no lag)
MIN_LAG_EVIDENCE_S = 0.2
# [rad/s] commands slower than this (every joint's speed, summed squared) tell no lag
MIN_MEASURED_SPEED = 1e-3


class JointCommand(NamedTuple):
    """A trajectory to ``positions`` (n,) [rad] at ``horizon`` [s] from now, moving at
    ``velocities`` (n,) [rad/s] (horizon 0: a hold, at once), from ``set_point`` (n,)
    [rad] at once (a first point at time 0, moving at ``velocities`` too) or, None, from
    wherever the arm is (joint_trajectory_controller interpolates from its state)."""

    positions: FloatArray
    velocities: FloatArray
    horizon: float
    set_point: FloatArray | None = None

    def points(self) -> list[tuple[float, FloatArray, FloatArray]]:
        """The trajectory's points: (time_from_start [s], positions (n,), velocities (n,))."""
        end = (self.horizon, self.positions, self.velocities)
        if self.set_point is None:
            return [end]
        return [(0.0, self.set_point, self.velocities), end]


class SetPointCommands:
    """The moving commands of one task and the arm's lag behind them.

    An arm's position loop (joint_trajectory_controller with a limited bandwidth; the
    simulated half-speed arm) trails its set point: on a path at joint speed qdot it is
    ``lag`` x qdot behind. ``measure`` estimates that lag from the measured joints
    against the set point in force when they were measured (a least-squares fit of the
    gap on the commanded velocity, forgetting over LAG_WINDOW_S, within [0, MAX_LAG_S]);
    ``command`` sends the point one lag ahead (q_cmd = q_set + lag * qdot, qdot smoothed
    over the lag: the lead on every step's corrections made the set point jump, over
    topics an xArm 7 figure eight at half speed once went 9.5 mm off), so the arm is
    where the path is. ``compensate_lag`` false (pa10_ik_node's default,
    ``lead_arm_lag``) measures the lag without leading; ``covered_lag`` [s] of it the
    controller compensates already (its command_latency:
    the Smith predictor acts on the joints the commands on their way will give; leading
    by that too overshot, in process 0.0073 -> 0.0111 mm RMS with 50 ms of delay).
    """

    def __init__(
        self, compensate_lag: bool = False, covered_lag: float = 0.0, send_set_point: bool = True
    ) -> None:
        self.compensate_lag = compensate_lag
        # The set point continued as a first point at time 0 (pa10_ik_node's parameter
        # send_set_point, on by default): joint_trajectory_controller then does not restart
        # each command from where a lagging arm is (a half-speed arm trailed a ramp 44 ms,
        # with it one arm step, 5 ms; over topics 54-84 -> 7-9 ms).
        self.send_set_point = send_set_point
        self.covered_lag = covered_lag
        # (time sent [s], the command without the lead): the set point continued
        self.nominal: tuple[float, JointCommand] | None = None
        # (time sent [s], the command as sent): the set point the arm follows
        self.sent: tuple[float, JointCommand] | None = None
        self.lag = 0.0  # [s] estimated
        self._sums = np.zeros(2)  # forgetting sums of (gap . qdot, qdot . qdot)
        self._evidence = 0.0  # [s] of motion measured, forgetting alike
        self._measured_at: float | None = None
        self._smoothed: FloatArray | None = None  # [rad/s] qdot over the last lag

    def restart(self) -> None:
        """The next command starts from the measured joints (after a hold, a new task);
        the lag estimate, the arm's, stays."""
        self.nominal = self.sent = None
        self._smoothed = None

    def measure(self, q: FloatArray, measured_at: float) -> None:
        """Update the lag estimate with the joints ``q`` (n,) [rad] the arm had at
        ``measured_at`` [s] (the loop's clock), against the command in force then."""
        if self.sent is None or (
            self._measured_at is not None and measured_at <= self._measured_at
        ):
            return  # nothing sent, or this reading measured already
        sent_at, command = self.sent
        since = measured_at - sent_at
        if not 0.0 <= since <= command.horizon:
            return
        elapsed = since if self._measured_at is None else measured_at - self._measured_at
        self._measured_at = measured_at
        forget = float(np.exp(-elapsed / LAG_WINDOW_S))
        self._sums *= forget
        self._evidence *= forget
        velocity = command.velocities
        speed2 = float(velocity @ velocity)
        if speed2 < MIN_MEASURED_SPEED**2:
            return
        set_point = command.positions - velocity * (command.horizon - since)
        self._sums += elapsed * np.array([float((set_point - q) @ velocity), speed2])
        self._evidence += elapsed
        if self._evidence >= MIN_LAG_EVIDENCE_S:
            self.lag = float(np.clip(self._sums[0] / self._sums[1], 0.0, MAX_LAG_S))

    def anchor(self, q: FloatArray, now: float) -> FloatArray:
        """(n,) [rad] Where the command sent at ``now`` starts: the previous moving
        command's set point at ``now`` (its point moved back along its velocity by the
        time still to go), within MAX_COMMAND_LEAD_S of its joint speeds of the measured
        joints ``q``; ``q`` itself for the first command after a restart.

        Started from the measured joints instead, every command threw away what the
        previous ones had not yet moved the arm: the measured state is older than the
        arm's (a joint state's age, the command's way), and an arm slower than its set
        point (a position loop with a lag) restarted from its own lagging position every
        control step made a fraction of the motion: over topics the half-speed arm
        0.16-0.24 of it, below what the response estimate compensates (MIN_RESPONSE)."""
        if self.nominal is None:
            return q
        sent, previous = self.nominal
        to_go = max(previous.horizon - (now - sent), 0.0)
        set_point = previous.positions - previous.velocities * to_go
        lead = np.abs(previous.velocities) * MAX_COMMAND_LEAD_S
        return q + np.clip(set_point - q, -lead, lead)

    def command(self, q: FloatArray, qdot: FloatArray, now: float, horizon: float) -> JointCommand:
        """The moving command at ``now`` [s]: joint velocities ``qdot`` (n,) [rad/s]
        from the continued set point, its point ``horizon`` [s] ahead plus the lag."""
        previous = self.nominal
        start = self.anchor(q, now)
        nominal = JointCommand(
            start + qdot * horizon,
            qdot,
            horizon,
            start if self.send_set_point and previous is not None else None,
        )
        if self._smoothed is None or previous is None or self.lag <= 0:
            self._smoothed = qdot.copy()
        else:
            self._smoothed += (qdot - self._smoothed) * (
                1.0 - float(np.exp(-max(now - previous[0], 0.0) / self.lag))
            )
        lead = max(self.lag - self.covered_lag, 0.0) if self.compensate_lag else 0.0
        shift = self._smoothed * lead
        sent = nominal._replace(
            positions=nominal.positions + shift,
            set_point=None if nominal.set_point is None else nominal.set_point + shift,
        )
        self.nominal, self.sent = (now, nominal), (now, sent)
        return sent
