"""Contact: force = stiffness * penetration along the surface normal, 0 off the surface."""

from pathlib import Path

import numpy as np
import pytest

from sensor_sim import surfaces
from sensor_sim.contact import contact_force
from sensor_sim.scenario import Surface, load_scenario
from vgm_common.geometry import make_transform, rpy_to_matrix

SCENARIOS = Path(__file__).resolve().parents[2] / 'src' / 'sensor_sim' / 'scenarios'
STIFFNESS = 2000.0  # [N/m]


@pytest.fixture(scope='module')
def tilted_plane():
    return Surface(
        kind='plane',
        T_base_surface=make_transform(rpy_to_matrix(0.3, -0.2, 1.0), [0.6, 0.1, 0.2]),
        scale=0.5,
        extent=((-0.4, 0.4), (-0.3, 0.3)),
        albedo=0.8,
        roughness=0.0,
    )


def test_plane_force_is_stiffness_times_depth(tilted_plane):
    normal = tilted_plane.T_base_surface[:3, 2]
    on_plane = (
        tilted_plane.T_base_surface[:3, :3] @ [0.05, -0.1, 0.0]
        + tilted_plane.T_base_surface[:3, 3]
    )
    state = contact_force(on_plane - 0.004 * normal, tilted_plane, STIFFNESS)
    assert state.penetration == pytest.approx(0.004, abs=1e-15)
    assert state.force == pytest.approx(STIFFNESS * 0.004, abs=1e-10)
    np.testing.assert_allclose(state.normal_base, normal, atol=1e-15)
    above = contact_force(on_plane + 0.004 * normal, tilted_plane, STIFFNESS)
    assert above.force == 0.0 and above.penetration == 0.0


def test_s3_force_matches_an_independent_computation():
    surface = load_scenario(SCENARIOS / 'default.yaml').surface
    assert surface.kind == 'S3'
    R, origin = surface.T_base_surface[:3, :3], surface.T_base_surface[:3, 3]
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, y = rng.uniform(-0.4, 0.4, 2)
        z = x * y + 0.5 * x - 0.6 - rng.uniform(0.0, 0.01)  # below the surface [units]
        tip = R @ (surface.scale * np.array([x, y, z])) + origin
        # Independent: first-order distance below z = xy + 0.5x - 0.6 along its normal.
        h_x, h_y = y + 0.5, x
        depth = (x * y + 0.5 * x - 0.6 - z) * surface.scale / np.sqrt(1 + h_x**2 + h_y**2)
        normal = R @ (np.array([-h_x, -h_y, 1.0]) / np.sqrt(1 + h_x**2 + h_y**2))
        state = contact_force(tip, surface, STIFFNESS)
        assert state.penetration == pytest.approx(depth, rel=1e-9, abs=1e-15)
        assert state.force == pytest.approx(STIFFNESS * depth, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(state.normal_base, normal, atol=1e-12)


def test_s3_penetration_is_close_to_the_true_distance():
    """First order in the depth: a tip 2 mm below the surface along its normal."""
    surface = load_scenario(SCENARIOS / 'default.yaml').surface
    on_surface = surfaces.surface_points_base(surface, [[0.2, -0.1]])
    normal = surfaces.normal_base(surface, on_surface)[0]
    state = contact_force(on_surface[0] - 0.002 * normal, surface, STIFFNESS)
    assert state.penetration == pytest.approx(0.002, abs=2e-6)


def test_no_contact_above_the_surface_or_outside_its_domain(tilted_plane):
    normal = tilted_plane.T_base_surface[:3, 2]
    centre = tilted_plane.T_base_surface[:3, 3]
    assert contact_force(centre + 0.05 * normal, tilted_plane, STIFFNESS).force == 0.0
    outside = tilted_plane.T_base_surface[:3, :3] @ [0.5, 0.0, -0.01] + centre  # x > 0.4 * 0.5
    state = contact_force(outside, tilted_plane, STIFFNESS)
    assert state.force == 0.0 and state.penetration == 0.0
    assert np.all(np.isnan(state.normal_base))
