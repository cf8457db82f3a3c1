"""Contact of the tool tip with the surface: a frictionless linear spring.

The surface pushes back along its normal with force = stiffness * penetration, where the
penetration is the tip's depth below the surface along the normal
(``surfaces.signed_height_base``: first order in the distance, exact for planes). The
pressure sensor's noise is added by the caller.
"""
from dataclasses import dataclass

import numpy as np

from sensor_sim import surfaces


@dataclass(frozen=True)
class ContactState:
    force: float  # [N] >= 0, along the surface normal
    penetration: float  # [m] >= 0: depth of the tip below the surface, 0 when not in contact
    normal_base: np.ndarray  # (3,) unit surface normal under the tip (+z side); NaN off the domain


def contact_force(tip_base, surface, stiffness):
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
    return ContactState(force=float(stiffness * penetration), penetration=float(penetration),
                        normal_base=normal)
