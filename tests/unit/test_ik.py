"""Velocity-level IK cores (ALGORITHMS.md §6.5, A7.3, A7.4, A7.14) against the KKT point."""

import numpy as np
import pytest

from pa10_ik_node.ik import dls_velocity, pose_error
from pa10_ik_node.problem import absolute_weights, kkt_velocity, null_space_positive
from pa10_ik_node.thesis import (
    fixed_step_matrix,
    primal_dual_velocity,
    primal_dual_velocity_fixed_step,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import make_transform, rot_x, rot_z
from vgm_common.robot_model import load_robot

W_THESIS = np.diag([1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0])  # §6.6
Q0_GAMMA1 = np.array([0.1288, 0.0, 0.3125, 0.0, 0.0, 0.3241, 0.038])  # [rad], §6.6
K_THESIS = 100.0
ROBOTS = ('pa10', 'pa10_thesis')


def random_jacobians(robot_name, seed, count):
    """``count`` Jacobians at seeded uniform configurations within the joint limits."""
    robot = load_robot(robot_name, 0.0)
    rng = np.random.default_rng(seed)
    return [
        robot.jacobian(rng.uniform(robot.lower_limits, robot.upper_limits)) for _ in range(count)
    ]


def h_positive(J, W, K=K_THESIS):
    return np.linalg.eigvalsh(W + K * J.T @ J)[0] > 0


def well_posed_jacobians(robot_name, W, count, seed=1):
    """Jacobians where W is positive on null(J) with a margin and H = W + 100 J^T J > 0."""
    found = []
    for J in random_jacobians(robot_name, seed, 300):
        positive, min_eig = null_space_positive(J, W)
        if positive and min_eig > 0.05 and h_positive(J, W):
            found.append(J)
        if len(found) == count:
            return found
    raise AssertionError(f'fewer than {count} well-posed configurations')


def assert_kkt_point(J, W, rdot_d, qdot, lam, tol):
    np.testing.assert_allclose(J @ qdot, rdot_d, rtol=0, atol=tol)
    np.testing.assert_allclose(W @ qdot + J.T @ lam, 0.0, rtol=0, atol=tol)


@pytest.mark.parametrize('robot_name', ROBOTS)
def test_kkt_with_identity_weight_is_the_pseudo_inverse(robot_name):
    rng = np.random.default_rng(2)
    for J in random_jacobians(robot_name, 2, 20):
        rdot_d = rng.normal(size=6)
        qdot, lam = kkt_velocity(J, np.eye(7), rdot_d)
        assert_kkt_point(J, np.eye(7), rdot_d, qdot, lam, 1e-10)
        np.testing.assert_allclose(qdot, np.linalg.pinv(J) @ rdot_d, atol=1e-9)


@pytest.mark.parametrize('robot_name', ROBOTS)
def test_kkt_with_the_thesis_weight_where_it_is_positive_on_the_null_space(robot_name):
    rng = np.random.default_rng(3)
    for J in well_posed_jacobians(robot_name, W_THESIS, 10):
        rdot_d = rng.normal(size=6)
        qdot, lam = kkt_velocity(J, W_THESIS, rdot_d)
        assert_kkt_point(J, W_THESIS, rdot_d, qdot, lam, 1e-10)
        # A minimum: moving along null(J) never lowers the cost.
        null_dir = np.linalg.svd(J)[2][-1]
        cost = 0.5 * qdot @ W_THESIS @ qdot
        assert 0.5 * (qdot + 0.1 * null_dir) @ W_THESIS @ (qdot + 0.1 * null_dir) > cost


def test_null_space_positive_verdicts():
    J = random_jacobians('pa10', 4, 1)[0]
    assert null_space_positive(J, np.eye(7))[0]
    positive, min_eig = null_space_positive(J, -np.eye(7))
    assert not positive and min_eig == pytest.approx(-1.0)
    # A7.3: the thesis's W fails in about 77 % of uniform configurations of its model.
    failures = [
        not null_space_positive(J, W_THESIS)[0] for J in random_jacobians('pa10_thesis', 5, 300)
    ]
    assert 0.67 < np.mean(failures) < 0.87


@pytest.mark.parametrize('robot_name', ROBOTS)
@pytest.mark.parametrize('W', [W_THESIS, np.eye(7)], ids=['indefinite', 'identity'])
def test_primal_dual_dynamics_converge_to_the_kkt_point(robot_name, W):
    rng = np.random.default_rng(6)
    for J in well_posed_jacobians(robot_name, W, 5):
        rdot_d = rng.normal(size=6)
        qdot, lam, info = primal_dual_velocity(J, W, rdot_d, K=K_THESIS)
        qdot_kkt, lam_kkt = kkt_velocity(J, W, rdot_d)
        np.testing.assert_allclose(qdot, qdot_kkt, atol=1e-6)
        np.testing.assert_allclose(lam, lam_kkt, atol=1e-6)
        assert info.converged and info.null_space_positive and not info.fallback_used
        assert info.gain == K_THESIS and info.min_h_eigenvalue > 0


def test_primal_dual_warm_start_stays_at_the_kkt_point():
    J = well_posed_jacobians('pa10_thesis', W_THESIS, 1)[0]
    rdot_d = np.random.default_rng(7).normal(size=6)
    qdot_kkt, lam_kkt = kkt_velocity(J, W_THESIS, rdot_d)
    qdot, lam, info = primal_dual_velocity(
        J, W_THESIS, rdot_d, v0=qdot_kkt, u0=lam_kkt, t_final=1e-3
    )
    np.testing.assert_allclose(qdot, qdot_kkt, atol=1e-9)
    assert info.converged


def test_primal_dual_raises_the_gain_when_k_is_too_small():
    # The real PA-10's short links: W positive on null(J), yet W + 100 J^T J indefinite.
    J = next(
        J
        for J in random_jacobians('pa10', 8, 300)
        if null_space_positive(J, W_THESIS)[1] > 0.05 and not h_positive(J, W_THESIS)
    )
    rdot_d = np.random.default_rng(8).normal(size=6)
    qdot, lam, info = primal_dual_velocity(J, W_THESIS, rdot_d, K=K_THESIS)
    assert info.gain > K_THESIS and info.min_h_eigenvalue > 0 and not info.fallback_used
    np.testing.assert_allclose(qdot, kkt_velocity(J, W_THESIS, rdot_d)[0], atol=1e-6)


@pytest.mark.parametrize('robot_name', ROBOTS)
def test_primal_dual_detects_failure_and_falls_back(robot_name):
    rng = np.random.default_rng(9)
    # Away from singularities: near one, the dual mode decays only at about sigma_min^2.
    failing = [
        J
        for J in random_jacobians(robot_name, 9, 30)
        if not null_space_positive(J, W_THESIS)[0]
        and np.linalg.svd(J, compute_uv=False)[-1] > 0.05
    ][:5]
    assert failing
    for J in failing:
        rdot_d = rng.normal(size=6)
        qdot, _, info = primal_dual_velocity(J, W_THESIS, rdot_d)
        assert not info.null_space_positive and info.min_null_eigenvalue <= 0
        assert info.fallback_used and info.converged
        # |W| of the thesis's diagonal W is the identity: the pseudo-inverse solution.
        np.testing.assert_allclose(absolute_weights(W_THESIS), np.eye(7))
        np.testing.assert_allclose(qdot, np.linalg.pinv(J) @ rdot_d, atol=1e-6)
        custom = np.diag(np.arange(1.0, 8.0))
        qdot, _, info = primal_dual_velocity(J, W_THESIS, rdot_d, weights_fallback=custom)
        assert info.fallback_used
        np.testing.assert_allclose(qdot, kkt_velocity(J, custom, rdot_d)[0], atol=1e-6)


def test_fixed_step_rules_diverge_at_the_thesis_values():
    J = load_robot('pa10_thesis', 0.0).jacobian(Q0_GAMMA1)
    spectral_radius = np.max(np.abs(np.linalg.eigvals(fixed_step_matrix(J, W_THESIS))))
    assert spectral_radius == pytest.approx(108, rel=0.02)  # A7.4
    rdot_d = np.random.default_rng(10).normal(size=6)
    _, _, norms = primal_dual_velocity_fixed_step(
        J, W_THESIS, rdot_d, K=K_THESIS, mu=0.02, eta=0.02, iterations=20
    )
    assert norms.shape == (21,) and np.all(np.isfinite(norms))
    assert norms[-1] > 1e20 * norms[1]


def test_gamma1_start_is_rank_deficient_and_kkt_stays_finite():
    J = load_robot('pa10_thesis', 0.0).jacobian(Q0_GAMMA1)
    assert np.linalg.matrix_rank(J) == 5  # A7.14
    rng = np.random.default_rng(11)
    rdot_d = J @ rng.normal(size=7)  # reachable twist
    qdot, lam = kkt_velocity(J, np.eye(7), rdot_d)
    assert_kkt_point(J, np.eye(7), rdot_d, qdot, lam, 1e-10)
    qdot, lam = kkt_velocity(J, W_THESIS, rng.normal(size=6))  # unreachable twist
    assert np.all(np.isfinite(qdot)) and np.all(np.isfinite(lam))
    qdot, _, info = primal_dual_velocity(J, W_THESIS, np.zeros(6))  # rdot_d(0) = 0
    assert info.fallback_used and np.allclose(qdot, 0.0)


def test_dls_tends_to_the_pseudo_inverse_away_from_singularities():
    rng = np.random.default_rng(12)
    for J in random_jacobians('pa10', 12, 10):
        if np.linalg.svd(J, compute_uv=False)[-1] < 0.05:
            continue
        twist = rng.normal(size=6)
        np.testing.assert_allclose(
            dls_velocity(J, twist, 1e-7), np.linalg.pinv(J) @ twist, atol=1e-8
        )
        assert np.linalg.norm(dls_velocity(J, twist, 0.5)) < np.linalg.norm(
            dls_velocity(J, twist, 0.0)
        )


def test_pose_error_is_zero_for_equal_poses_and_matches_a_known_rotation():
    T = load_robot('pa10', 0.0).forward_kinematics(Q0_GAMMA1)
    np.testing.assert_allclose(pose_error(T, T), 0.0, atol=1e-12)
    # Desired = current rotated by 0.01 rad about base z and 0.02 rad about base x,
    # shifted by 1 cm along base y.
    angle_z, offset_m = 0.01, np.array([0.0, 0.01, 0.0])
    T_desired = make_transform(rot_z(angle_z) @ T[:3, :3], T[:3, 3] + offset_m)
    np.testing.assert_allclose(pose_error(T, T_desired), [0, 0.01, 0, 0, 0, angle_z], atol=1e-12)
    T_desired = make_transform(rot_x(0.02) @ T[:3, :3], T[:3, 3])
    np.testing.assert_allclose(pose_error(T, T_desired), [0, 0, 0, 0.02, 0, 0], atol=1e-12)


def test_bad_shapes_raise():
    with pytest.raises(InvalidInput, match=r'\(6, n\)'):
        kkt_velocity(np.zeros((5, 7)), np.eye(7), np.zeros(6))
    with pytest.raises(InvalidInput, match='W'):
        primal_dual_velocity(np.zeros((6, 7)), np.eye(6), np.zeros(6))
    with pytest.raises(InvalidInput, match='rdot_d'):
        dls_velocity(np.zeros((6, 7)), np.zeros(7), 0.1)
    with pytest.raises(InvalidInput, match='T_current'):
        pose_error(np.eye(3), np.eye(4))


def test_the_fast_paths_of_the_control_step_give_the_same_bits():
    """pa10_ik_node.ik.cross is np.cross's arithmetic on (3,) vectors, and
    pose_error on orthonormal rotations skips scipy's orthogonalisation without changing
    a bit; a rotation that is not orthonormal still goes through it."""
    from scipy.spatial.transform import Rotation

    from pa10_ik_node.ik import cross

    rng = np.random.default_rng(3)
    for _ in range(200):
        a, b = rng.normal(size=3), rng.normal(size=3) * 10.0 ** rng.integers(-6, 6)
        assert np.array_equal(cross(a, b), np.cross(a, b))
    for _ in range(200):
        T_current = make_transform(Rotation.random(rng=rng).as_matrix(), rng.normal(size=3))
        T_desired = make_transform(Rotation.random(rng=rng).as_matrix(), rng.normal(size=3))
        R_error = T_desired[:3, :3] @ T_current[:3, :3].T
        expected = Rotation.from_matrix(R_error).as_rotvec()
        assert np.array_equal(pose_error(T_current, T_desired)[3:], expected)
    skewed = np.eye(4)
    skewed[:3, :3] = rot_z(0.3) @ np.diag([1.0, 1.2, 1.0])  # not a rotation
    expected = Rotation.from_matrix(skewed[:3, :3]).as_rotvec()
    assert np.array_equal(pose_error(np.eye(4), skewed)[3:], expected)
