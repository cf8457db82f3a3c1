"""Tracking-control core (ALGORITHMS.md §6.4, 7.3.15, A7.10) in a simulated contact loop."""
from pathlib import Path

import numpy as np
import pytest

from pa10_ik_node.tracking import (
    TrackingController,
    approach_correction,
    force_tilt_angle,
    next_target_on_tangent_plane,
)
from sensor_sim.contact import contact_force
from sensor_sim.surfaces import normal_base, surface_points_base
from vgm_common.robot_model import load_robot
from vgm_common.scenario import load_scenario

DESIRED_FORCE = 5.0  # [N]
DT = 0.01  # [s]
SCENARIOS = Path(__file__).resolve().parents[2] / 'src' / 'sensor_sim' / 'scenarios'


@pytest.fixture(scope='module')
def scenario():
    return load_scenario(SCENARIOS / 'default.yaml')


@pytest.fixture(scope='module')
def robot(scenario):
    return load_robot(scenario.robot.model, scenario.robot.tool_length)


def surface_path(surface, start, end, count=40):
    """Waypoints on the surface along the surface-unit segment start -> end."""
    xy = np.linspace(start, end, count)
    points = surface_points_base(surface, xy)
    normals = normal_base(surface, points)
    poses = [next_target_on_tangent_plane(p, n, q)[1]
             for p, n, q in zip(points[:-1], normals[:-1], points[1:])]
    last = poses[-1].copy()
    last[:3, 3] = points[-1]
    return np.array(poses + [last])


def distance_to_polyline(point, vertices):
    a, b = vertices[:-1], vertices[1:]
    t = np.clip(np.einsum('ij,ij->i', point - a, b - a) / np.sum((b - a) ** 2, axis=1), 0, 1)
    return np.min(np.linalg.norm(a + t[:, None] * (b - a) - point, axis=1))


def simulate(robot, scenario, waypoints, stiffness_estimate, max_steps=3000, **kwargs):
    """Closed loop q += qdot dt against the spring contact; the log of (index, T, force)
    and the largest |qdot| / limit."""
    k = scenario.contact_stiffness
    controller = TrackingController(robot, waypoints, DESIRED_FORCE, stiffness_estimate,
                                    **kwargs)
    q = np.array(scenario.robot.initial_joints, dtype=float)
    log = []
    force, peak = 0.0, 0.0
    for _ in range(max_steps):
        qdot, info = controller.step(q, force, DT)
        peak = max(peak, np.max(np.abs(qdot) / controller.velocity_limits))
        if info['done']:
            break
        q = q + qdot * DT
        T = robot.forward_kinematics(q)
        force = contact_force(T[:3, 3], scenario.surface, k).force
        log.append((info['index'], T, force))
    return controller, log, peak


@pytest.mark.parametrize('track_spin, stiffness_ratio', [(False, 1.0), (True, 1.0),
                                                         (False, 0.6)])
def test_tracks_path_with_force(robot, scenario, track_spin, stiffness_ratio):
    waypoints = surface_path(scenario.surface, [0.0, -0.06], [0.1, 0.04])
    controller, log, peak = simulate(
        robot, scenario, waypoints, stiffness_ratio * scenario.contact_stiffness,
        track_spin=track_spin, max_joint_velocity=0.5)
    assert controller.done
    assert peak <= 1 + 1e-9  # |qdot| within the limits at every step
    assert np.all(controller.velocity_limits <= robot.velocity_limits)
    # The ground-truth contact path: the waypoints pressed to the desired depth.
    depth = DESIRED_FORCE / scenario.contact_stiffness
    pressed = waypoints[:, :3, 3] + depth * waypoints[:, :3, 2]
    along = [(T, f) for index, T, f in log if index >= 3]  # after the approach
    rms = np.sqrt(np.mean([distance_to_polyline(T[:3, 3], pressed) ** 2 for T, _ in along]))
    forces = np.array([f for _, f in along])
    tilt = np.degrees(np.arccos(np.clip(
        [-T[:3, 2] @ normal_base(scenario.surface, T[:3, 3])[0] for T, _ in along], -1, 1)))
    print(f'track_spin={track_spin}, k_est/k={stiffness_ratio}: {len(log)} steps, '
          f'{len(along)} on the path, RMS {rms * 1e3:.3f} mm, '
          f'force {forces.min():.3f}..{forces.max():.3f} N, '
          f'max tilt {tilt.max():.3f} deg, peak |qdot|/limit {peak:.3f}, '
          f'final force {forces[-1]:.3f} N')
    assert rms < 1e-3
    # Settled at once with the true stiffness; 1 s into the path with a 40 % low estimate.
    settle = 0 if stiffness_ratio == 1.0 else int(1.0 / DT)
    assert np.all(np.abs(forces[settle:] - DESIRED_FORCE) < 0.1 * DESIRED_FORCE)
    assert np.linalg.norm(log[-1][1][:3, 3] - pressed[-1]) < 1e-3


def test_force_tilt_angle():
    assert force_tilt_angle(5.0, 5.0) == 0.0
    assert force_tilt_angle(10.0, 5.0) == pytest.approx(np.pi / 2)
    assert force_tilt_angle(0.0, 5.0) == pytest.approx(-np.pi / 2)
    assert force_tilt_angle(6.0, 4.0) == pytest.approx(np.pi / 4)


def test_approach_correction_integrates_in_contact_only():
    depth, integral = approach_correction(0.0, 0.0, 5.0, 2000.0, 0.01)
    assert (depth, integral) == (pytest.approx(0.0025), 0.0)  # no contact: no wind-up
    depth, integral = approach_correction(0.0, 4.0, 5.0, 2000.0, 0.1, gain=2.0)
    assert integral == pytest.approx(2.0 * 0.1 * 1.0 / 2000.0)
    assert depth == pytest.approx(0.0025 + integral)
    depth, _ = approach_correction(1.0, 1.0, 5.0, 2000.0, 0.1, max_depth=0.004)
    assert depth == 0.004


def test_tangent_plane_target_and_frame():
    rng = np.random.default_rng(3)
    for _ in range(20):
        P, normal, Q = rng.normal(size=(3, 3))
        Q_plane, T = next_target_on_tangent_plane(P, normal, Q)
        n = normal / np.linalg.norm(normal)
        assert n @ (Q_plane - P) == pytest.approx(0.0, abs=1e-12)
        assert np.cross(Q - Q_plane, n) == pytest.approx(np.zeros(3), abs=1e-12)
        R = T[:3, :3]
        assert R.T @ R == pytest.approx(np.eye(3), abs=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert R[:, 2] == pytest.approx(-n)
        assert R[:, 0] == pytest.approx((Q_plane - P) / np.linalg.norm(Q_plane - P))
        assert T[:3, 3] == pytest.approx(P)


def test_singular_posture_uses_dls_within_limits(robot, scenario):
    waypoints = surface_path(scenario.surface, [0.0, -0.06], [0.1, 0.04])
    controller = TrackingController(robot, waypoints, DESIRED_FORCE, 2000.0, track_spin=True)
    qdot, info = controller.step(np.zeros(7), 0.0, DT)  # upright: J loses rank
    assert info['dls']
    assert np.all(np.isfinite(qdot))
    assert np.all(np.abs(qdot) <= robot.velocity_limits * (1 + 1e-9))
