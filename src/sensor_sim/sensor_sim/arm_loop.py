"""sensor_sim's arm thread without ROS: the settings that are the one source of the
simulated arm's parameters, the step that moves the arm and reads the pressure sensor,
and the absolute tick schedule the thread keeps."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sensor_sim.arm_sim import ARM_MODES, SimulatedArm
from sensor_sim.contact import contact_force
from sensor_sim.scenario import Scenario
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.settings import setting

if TYPE_CHECKING:  # pinocchio, imported only for the type
    from vgm_common.robot_model import RobotModel

PRESSURE_SEED = 1_000_003  # the pressure noise's stream: [scenario seed, this]


@dataclass(frozen=True)
class ArmSettings:
    """How the simulated arm follows its commands: the one source of these parameters."""

    arm_mode: str = setting(
        'position',
        "The simulated arm follows the commanded 'position' (set points) or only the "
        "commanded 'velocity'.",
        choices=ARM_MODES,
        read_only=True,
    )
    arm_speed_scale: float = setting(
        1.0,
        'Fraction of the commanded motion the arm makes (< 1: an arm slower than commanded).',
        range=(0.01, 1.0),
        read_only=True,
    )
    arm_command_delay: float = setting(
        0.0,
        "Each joint trajectory's times count from its stamp (0: its arrival) plus this "
        'delay, the previous one in force until then: an arm behind a controller or network '
        'with this command latency (0: none).',
        unit='s',
        range=(0.0, 1.0),
        read_only=True,
    )


@dataclass(frozen=True)
class ArmSample:
    """The arm and its pressure sensor at one tick."""

    stamp_ns: int  # [ns] the tick's time
    q: FloatArray  # (n,) joint positions [rad]
    qdot: FloatArray  # (n,) joint velocities [rad/s]
    force: float  # [N] >= 0, contact force along the approach axis with the sensor's noise


class ArmLoop:
    """The simulated arm of ``scenario`` (joints of ``robot``) and the pressure sensor at
    its tool tip, stepped at every tick. Not thread-safe: the caller serialises
    ``command``/``hold`` with ``step``.

    Raises:
        InvalidInput: settings the arm refuses, an initial joint vector outside the limits.
    """

    def __init__(
        self, robot: RobotModel, scenario: Scenario, settings: ArmSettings, period: float
    ) -> None:
        self.robot = robot
        self.arm = SimulatedArm.from_robot_model(
            robot,
            scenario.robot.initial_joints,
            settings.arm_mode,
            settings.arm_speed_scale,
            settings.arm_command_delay,
        )
        self._surface = scenario.surface
        self._stiffness = scenario.contact_stiffness  # [N/m]
        self._pressure_sigma = scenario.noise.pressure_sigma  # [N]
        self._rng = np.random.default_rng([scenario.seed, PRESSURE_SEED])
        self._period = period  # [s] the first step's
        self._last_time: float | None = None  # [s]

    def command(
        self,
        joint_names: Sequence[str],
        times: Sequence[float],
        positions: Sequence[Sequence[float]],
        velocities: Sequence[Sequence[float]],
        start_time: float,
    ) -> None:
        """Follow a joint trajectory: ``times`` [s] from ``start_time`` [s], one
        ``positions`` row per point and one ``velocities`` row (all empty: none given).
        A refused trajectory makes the arm hold where it is.

        Raises:
            InvalidInput, ValueError: a malformed trajectory (the arm then holds).
        """
        try:
            if any(len(v) != len(p) for v, p in zip(velocities, positions) if v):
                raise InvalidInput('velocities and positions differ in length')
            has_velocities = bool(positions) and all(velocities)
            self.arm.set_trajectory(
                list(joint_names),
                np.array(times),
                np.array(positions, dtype=float),
                np.array(velocities, dtype=float) if has_velocities else None,
                start_time,
            )
        except (InvalidInput, ValueError):
            self.arm.hold()
            raise

    def step(self, now: float) -> ArmSample:
        """Move the arm to ``now`` [s] (by the time since the last step; the period at the
        first) and read the pressure sensor."""
        dt = self._period if self._last_time is None else now - self._last_time
        self._last_time = now
        q, qdot = self.arm.step(now, max(dt, 0.0))
        T_base_tool = self.robot.forward_kinematics(q)
        force = contact_force(T_base_tool[:3, 3], self._surface, self._stiffness).force
        if force > 0:  # the sensor's noise while in contact, never a pull
            force = max(0.0, force + self._rng.normal(0.0, self._pressure_sigma))
        return ArmSample(int(now * 1e9), q, qdot, float(force))


class TickSchedule:
    """Ticks every ``period`` [s] on an absolute schedule of ``clock`` (monotonic [s]): no
    drift accumulates; a tick that is late is not caught up with a burst, the schedule
    restarts from it."""

    def __init__(self, period: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.period = period
        self._clock = clock
        self._next = clock()  # [s] the next tick's time

    def wait_after_tick(self) -> float:
        """[s] to wait after a tick until the next one is due (0: due now, running late)."""
        self._next += self.period
        delay = self._next - self._clock()
        if delay > 0:
            return delay
        self._next = self._clock()
        return 0.0
