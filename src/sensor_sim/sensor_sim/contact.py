"""Contact of the tool tip with the surface: a frictionless linear spring.

The surface pushes back along its normal with force = stiffness * penetration, where the
penetration is the tip's depth below the surface along the normal
(``surfaces.signed_height_base``: first order in the distance, exact for planes). The
pressure sensor's noise is added by the caller.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from sensor_sim import surfaces
from sensor_sim.scenario import Surface
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

if TYPE_CHECKING:  # pinocchio, imported only for the type
    from vgm_common.robot_model import RobotModel


@dataclass(frozen=True)
class ContactState:
    """The tool tip's contact with the surface: spring force, penetration and the surface
    normal under the tip."""

    force: float  # [N] >= 0, along the surface normal
    penetration: float  # [m] >= 0: depth of the tip below the surface, 0 when not in contact
    normal_base: FloatArray  # (3,) unit surface normal under the tip (+z side); NaN off the domain


def contact_force(tip_base: npt.ArrayLike, surface: Surface, stiffness: float) -> ContactState:
    """Contact state of a tool tip.

    Args:
        tip_base: (3,) tool tip position in base_link [m].
        surface: a ``Scenario.surface``.
        stiffness: contact stiffness [N/m].

    Returns:
        ``ContactState``. Above the surface, and outside its domain (where there is no
        surface to press on), the force and penetration are 0.
    """
    tip = np.asarray(tip_base, dtype=float).reshape(1, 3)
    signed_height = surfaces.signed_height_base(surface, tip)[0]
    normal = surfaces.normal_base(surface, tip)[0]
    normal.setflags(write=False)
    penetration = max(0.0, -signed_height) if np.isfinite(signed_height) else 0.0
    return ContactState(
        force=float(stiffness * penetration), penetration=float(penetration), normal_base=normal
    )


def joint_vector_pressing(
    robot: RobotModel,
    surface: Surface,
    q_start: npt.ArrayLike,
    q_end: npt.ArrayLike,
    penetration: float,
    iterations: int = 60,
) -> FloatArray:
    """The joint vector on the straight joint-space line ``q_start -> q_end`` whose tool tip
    is ``penetration`` [m] below the surface (bisection; for demos and tests that need a
    known contact without an IK solver).

    Raises ValueError if ``q_start`` already touches or ``q_end`` does not press that deep.
    """
    q_start, q_end = np.asarray(q_start, dtype=float), np.asarray(q_end, dtype=float)

    def depth(s: float) -> float:
        tip = robot.forward_kinematics(q_start + s * (q_end - q_start))[:3, 3]
        return contact_force(tip, surface, 1.0).penetration

    if depth(0.0) > 0.0 or depth(1.0) < penetration:
        raise InvalidInput('the joint-space line does not reach that penetration from above')
    low, high = 0.0, 1.0
    for _ in range(iterations):
        middle = (low + high) / 2
        low, high = (middle, high) if depth(middle) < penetration else (low, middle)
    return q_start + high * (q_end - q_start)
