"""RateSolver (ours / primal_dual / dls) against the KKT point, joint limits, Jacobians
against finite differences, and a 7-DOF arm from example-robot-data (panda)."""

from pathlib import Path

import numpy as np
import pytest

from pa10_ik_node.ik import RateSolver, closed_form_velocity, pose_error, spin_free_task
from pa10_ik_node.problem import kkt_velocity, null_space_positive
from vgm_common.errors import InvalidInput
from vgm_common.geometry import make_transform, rot_x
from vgm_common.robot_model import load_robot

W_THESIS = [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0]
PANDA_URDF = next(
    Path(__file__)
    .resolve()
    .parents[2]
    .glob(
        '.venv/lib/python3*/site-packages/cmeel.prefix/share/example-robot-data/robots/'
        'panda_description/urdf/panda.urdf'
    ),
    None,
)


def robots():
    yield 'pa10', load_robot('pa10', 0.1)
    yield 'pa10_thesis', load_robot('pa10_thesis', 0.0)
    if PANDA_URDF is not None:
        yield 'panda', load_robot(str(PANDA_URDF), tip_frame='panda_hand_tcp')


def random_configurations(robot, seed, count):
    rng = np.random.default_rng(seed)
    return [rng.uniform(0.8 * robot.lower_limits, 0.8 * robot.upper_limits) for _ in range(count)]


@pytest.mark.parametrize(
    'name, robot', list(robots()), ids=lambda x: x if isinstance(x, str) else ''
)
def test_jacobian_matches_finite_differences(name, robot):
    step = 1e-6  # [rad]
    for q in random_configurations(robot, 1, 5):
        J = robot.jacobian(q)
        T = robot.forward_kinematics(q)
        numeric = np.zeros_like(J)
        for i in range(robot.n_joints):
            dq = np.zeros(robot.n_joints)
            dq[i] = step
            # pose_error(T, T') = (p' - p, rotvec(R' R^T)): the twist over one step.
            numeric[:, i] = (
                pose_error(T, robot.forward_kinematics(q + dq))
                - pose_error(T, robot.forward_kinematics(q - dq))
            ) / (2 * step)
        np.testing.assert_allclose(J, numeric, atol=1e-7)


@pytest.mark.parametrize('rows', [6, 5])
def test_ours_satisfies_the_task_and_is_the_kkt_point(rows):
    robot = load_robot('pa10', 0.1)
    rng = np.random.default_rng(2)
    weights = np.array([1.0, 2.0, 1.0, 3.0, 1.0, 0.5, 1.0])
    solver = RateSolver('ours', weights, sigma_threshold=1e-3)
    for q in random_configurations(robot, 2, 20):
        J = robot.jacobian(q)
        if np.linalg.svd(J, compute_uv=False)[-1] < 0.02:
            continue
        twist = rng.normal(size=6) * 0.1
        T = make_transform(rot_x(0.3), np.zeros(3))
        J_task, task = (J, twist) if rows == 6 else spin_free_task(J, twist, T)
        qdot, info = solver.solve(J_task, task)
        assert info['damping'] == 0.0
        np.testing.assert_allclose(J_task @ qdot, task, atol=1e-10)
        J6 = np.vstack([J_task, np.zeros((6 - rows, 7))])
        task6 = np.concatenate([task, np.zeros(6 - rows)])
        np.testing.assert_allclose(qdot, kkt_velocity(J6, np.diag(weights), task6)[0], atol=1e-9)


def test_ours_with_an_indefinite_weight_uses_the_kkt_point_or_falls_back():
    robot = load_robot('pa10_thesis', 0.0)
    rng = np.random.default_rng(3)
    solver = RateSolver('ours', W_THESIS)
    verdicts = []
    for q in random_configurations(robot, 3, 40):
        J = robot.jacobian(q)
        if np.linalg.svd(J, compute_uv=False)[-1] < 0.05:
            continue
        twist = rng.normal(size=6)
        qdot, info = solver.solve(J, twist)
        positive = null_space_positive(J, np.diag(W_THESIS))[0]
        assert info['null_space_positive'] == positive
        verdicts.append(positive)
        expected = (
            kkt_velocity(J, np.diag(W_THESIS), twist)[0]
            if positive
            else closed_form_velocity(J, np.eye(7), twist)
        )  # |W| = I
        np.testing.assert_allclose(qdot, expected, atol=1e-8)
        np.testing.assert_allclose(J @ qdot, twist, atol=1e-9)
    assert any(verdicts) and not all(verdicts)  # both cases were exercised


def test_primal_dual_solver_reports_the_failure_condition():
    robot = load_robot('pa10_thesis', 0.0)
    solver = RateSolver('primal_dual', W_THESIS)
    rng = np.random.default_rng(4)
    seen = set()
    for q in random_configurations(robot, 4, 30):
        J = robot.jacobian(q)
        if np.linalg.svd(J, compute_uv=False)[-1] < 0.05:
            continue
        solver.reset()
        twist = rng.normal(size=6)
        qdot, info = solver.solve(J, twist)
        assert info['fallback_used'] == (not info['null_space_positive'])
        assert info['converged']
        np.testing.assert_allclose(J @ qdot, twist, atol=1e-6)
        seen.add(info['null_space_positive'])
    assert seen == {True, False}


def test_joint_at_its_limit_is_clamped_and_the_redundancy_keeps_the_task():
    robot = load_robot('pa10', 0.1)
    q = np.array([0.3, 0.5, 0.2, 1.5, 0.1, 1.0, 0.0])
    J = robot.jacobian(q)
    solver = RateSolver('ours', np.ones(7))
    twist = np.array([0.05, 0.02, -0.03, 0.0, 0.0, 0.0])
    free, _ = solver.solve(J, twist)
    joint = 0  # without it the other six still span the task well (sigma_min 0.22)
    assert abs(free[joint]) > 1e-3
    upper = robot.upper_limits.copy()
    lower = robot.lower_limits.copy()
    # Put that joint 0.02 rad (the margin) from the limit it moves towards.
    if free[joint] > 0:
        upper[joint] = q[joint] + 0.02
    else:
        lower[joint] = q[joint] - 0.02
    qdot, info = solver.solve_limited(J, twist, q, lower, upper, robot.velocity_limits)
    assert info['locked'] >= 1 and abs(qdot[joint]) < 1e-12
    np.testing.assert_allclose(J @ qdot, twist, atol=1e-9)  # the other 6 joints do it
    # DLS has no such re-solve: the limit is enforced by clamping, the task suffers.
    dls = RateSolver('dls', np.ones(7))
    qdot, _ = dls.solve_limited(J, twist, q, lower, upper, robot.velocity_limits)
    assert abs(qdot[joint]) < 1e-12 and np.linalg.norm(J @ qdot - twist) > 1e-4


def test_velocity_limits_scale_uniformly():
    robot = load_robot('pa10', 0.1)
    q = np.array([0.3, 0.5, 0.2, 1.5, 0.1, 1.0, 0.0])
    J = robot.jacobian(q)
    solver = RateSolver('ours', np.ones(7))
    twist = np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # far too fast
    limits = np.full(7, 0.5)
    qdot, info = solver.solve_limited(J, twist, q, robot.lower_limits, robot.upper_limits, limits)
    assert info['scale'] > 1 and np.max(np.abs(qdot)) == pytest.approx(0.5)
    direction = J @ qdot
    np.testing.assert_allclose(
        direction / np.linalg.norm(direction), [1, 0, 0, 0, 0, 0], atol=1e-9
    )


@pytest.mark.skipif(PANDA_URDF is None, reason='example-robot-data not installed')
def test_panda_from_example_robot_data_reaches_a_pose():
    panda = load_robot(str(PANDA_URDF), tip_frame='panda_hand_tcp')
    assert panda.n_joints == 7
    q = np.array([0.0, -0.4, 0.0, -2.2, 0.0, 1.9, 0.8])
    q_goal = q + np.array([0.3, 0.2, -0.2, 0.3, 0.2, -0.2, 0.1])
    T_goal = panda.forward_kinematics(q_goal)
    solver = RateSolver('ours', np.ones(7))
    dt = 0.01  # [s]
    for _ in range(1000):
        error = pose_error(panda.forward_kinematics(q), T_goal)
        if np.linalg.norm(error) < 1e-9:
            break
        qdot, _ = solver.solve_limited(
            panda.jacobian(q),
            20.0 * error,
            q,
            panda.lower_limits,
            panda.upper_limits,
            panda.velocity_limits,
        )
        q = q + qdot * dt
    error = pose_error(panda.forward_kinematics(q), T_goal)
    assert np.linalg.norm(error[:3]) < 1e-8 and np.linalg.norm(error[3:]) < 1e-8
    assert np.all(q >= panda.lower_limits) and np.all(q <= panda.upper_limits)


def test_bad_solver_settings_raise():
    with pytest.raises(InvalidInput, match='method'):
        RateSolver('newton', np.ones(7))
    with pytest.raises(InvalidInput, match='weights'):
        RateSolver('ours', [1.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0])
