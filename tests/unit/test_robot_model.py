"""PA-10 kinematics on Pinocchio against an independent Denavit-Hartenberg model."""

import importlib.metadata
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from vgm_common.errors import InvalidInput
from vgm_common.robot_model import (
    JOINT_NAMES,
    PA10_LOWER_LIMITS_RAD,
    PA10_UPPER_LIMITS_RAD,
    PA10_VELOCITY_LIMITS_RAD_S,
    PARAMETER_SETS,
    load_robot,
    own_tool_length,
    pa10_urdf,
    workspace_reach,
)

URDF_DIR = Path(__file__).resolve().parents[2] / 'src' / 'vgm_common' / 'urdf'
CASES = [(name, tool_m) for name in PARAMETER_SETS for tool_m in (0.0, 0.15)]


def dh_transform(theta, d, a, alpha):
    """Standard DH link transform Rz(theta) Tz(d) Tx(a) Rx(alpha)."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def pa10_dh_fk(q, params, tool_m):
    """T_base_tool of the PA-10 from its standard DH table (a = 0 for every link)."""
    d = [params.d1, 0.0, params.d3, 0.0, params.d5, 0.0, params.d7 + tool_m]
    alpha = [-np.pi / 2, np.pi / 2] * 3 + [0.0]
    T = np.eye(4)
    for i in range(7):
        T = T @ dh_transform(q[i], d[i], 0.0, alpha[i])
    return T


def random_configurations(count, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(PA10_LOWER_LIMITS_RAD, PA10_UPPER_LIMITS_RAD, size=(count, 7))


@pytest.mark.parametrize('name, tool_m', CASES)
def test_zero_pose_points_straight_up(name, tool_m):
    p = PARAMETER_SETS[name]
    T_base_tool = load_robot(name, tool_m).forward_kinematics(np.zeros(7))
    np.testing.assert_allclose(T_base_tool[:3, :3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(
        T_base_tool[:3, 3], [0, 0, p.d1 + p.d3 + p.d5 + p.d7 + tool_m], atol=1e-15
    )


@pytest.mark.parametrize('name, tool_m', CASES)
def test_forward_kinematics_matches_dh_table(name, tool_m):
    robot = load_robot(name, tool_m)
    for q in [np.zeros(7), *random_configurations(50)]:
        np.testing.assert_allclose(
            robot.forward_kinematics(q), pa10_dh_fk(q, PARAMETER_SETS[name], tool_m), atol=1e-12
        )


@pytest.mark.parametrize('name, tool_m', CASES)
def test_jacobian_matches_finite_differences(name, tool_m):
    robot = load_robot(name, tool_m)
    h = 1e-6  # [rad]
    for q in random_configurations(10, seed=1):
        J_fd = np.empty((6, 7))
        for i in range(7):
            T_plus = robot.forward_kinematics(q + h * np.eye(7)[i])
            T_minus = robot.forward_kinematics(q - h * np.eye(7)[i])
            J_fd[:3, i] = (T_plus[:3, 3] - T_minus[:3, 3]) / (2 * h)
            # R+ R-^T = exp(2h [w]x) with w in base axes: the angular rows' convention.
            J_fd[3:, i] = pin.log3(T_plus[:3, :3] @ T_minus[:3, :3].T) / (2 * h)
        np.testing.assert_allclose(robot.jacobian(q), J_fd, atol=1e-6)


@pytest.mark.parametrize('name', PARAMETER_SETS)
def test_committed_urdf_is_generated_text(name):
    assert (URDF_DIR / f'{name}.urdf').read_text() == pa10_urdf(name), (
        'regenerate with `python -m vgm_common.robot_model`'
    )


@pytest.mark.parametrize('name', PARAMETER_SETS)
def test_limits_and_names_match_parameter_set(name):
    robot = load_robot(name)
    assert robot.joint_names == JOINT_NAMES
    np.testing.assert_array_equal(robot.lower_limits, PA10_LOWER_LIMITS_RAD)
    np.testing.assert_array_equal(robot.upper_limits, PA10_UPPER_LIMITS_RAD)
    np.testing.assert_array_equal(robot.velocity_limits, PA10_VELOCITY_LIMITS_RAD_S)
    np.testing.assert_allclose(np.rad2deg(robot.upper_limits), [177, 94, 174, 137, 255, 165, 255])
    assert not robot.upper_limits.flags.writeable


def test_urdf_file_loads_like_named_model(tmp_path):
    path = tmp_path / 'pa10.urdf'
    path.write_text(pa10_urdf('pa10'))
    q = random_configurations(1)[0]
    np.testing.assert_allclose(
        load_robot(str(path), 0.2).forward_kinematics(q),
        load_robot('pa10', 0.2).forward_kinematics(q),
        atol=1e-15,
    )


def test_panda_from_example_robot_data_goes_through_same_code_path():
    # example-robot-data ships as a data-only cmeel wheel: locate its URDF, not a module.
    try:
        urdf = importlib.metadata.distribution('example-robot-data').locate_file(
            'cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf'
        )
    except importlib.metadata.PackageNotFoundError:
        pytest.skip('example-robot-data is not installed')
    with pytest.raises(InvalidInput, match='set tip_frame to one of its frames') as info:
        load_robot(str(urdf))  # the default tool0: the Panda has none
    assert info.value.key == 'tip_frame' and 'panda_hand_tcp' in str(info.value)
    assert own_tool_length(str(urdf)) == 0.0 and own_tool_length('pa10') == 0.1
    robot = load_robot(str(urdf), tip_frame='panda_hand_tcp')
    # The two finger joints do not move the tip, so they are locked away.
    assert robot.joint_names == tuple(f'panda_joint{i}' for i in range(1, 8))
    full = pin.buildModelFromUrdf(str(urdf))
    full_data = full.createData()
    for q in np.random.default_rng(2).uniform(robot.lower_limits, robot.upper_limits, (5, 7)):
        pin.framesForwardKinematics(full, full_data, np.concatenate([q, [0.0, 0.0]]))
        expected = full_data.oMf[full.getFrameId('panda_hand_tcp')].homogeneous
        np.testing.assert_allclose(robot.forward_kinematics(q), expected, atol=1e-12)
        assert robot.jacobian(q).shape == (6, 7)


@pytest.mark.parametrize(
    'q', [np.zeros(6), np.zeros((7, 1)), [0, 0, 0, np.nan, 0, 0, 0], ['a'] * 7, None]
)
def test_bad_joint_vector_is_rejected(q):
    robot = load_robot('pa10')
    with pytest.raises(InvalidInput):
        robot.forward_kinematics(q)
    with pytest.raises(InvalidInput):
        robot.jacobian(q)


@pytest.mark.parametrize(
    'robot, kwargs',
    [
        ('pa11', {}),
        ('/no/such/file.urdf', {}),
        (None, {}),
        ('pa10', {'tool_length': float('nan')}),
        ('pa10', {'tip_frame': 'flange'}),
    ],
)
def test_bad_model_request_is_rejected(robot, kwargs):
    with pytest.raises(InvalidInput):
        load_robot(robot, **kwargs)


def _edited_pa10(tmp_path, old, new, count=1):
    text = pa10_urdf('pa10', 0.1)
    assert old in text
    path = tmp_path / 'arm.urdf'
    path.write_text(text.replace(old, new, count))
    return str(path)


@pytest.mark.parametrize(
    'edit, message',
    [
        # No tool0: the tip link renamed.
        (('tool0', 'flange', 2), "no frame 'tool0'"),
        # 6 joints: the last revolute joint made fixed.
        (
            ('name="pa10_joint7" type="revolute"', 'name="pa10_joint7" type="fixed"'),
            '6 joints move',
        ),
        # 8 joints: the tool joint made revolute, with limits.
        (
            (
                'name="pa10_joint_tool" type="fixed">',
                'name="pa10_joint_tool" type="revolute"><axis xyz="0 0 1"/>'
                '<limit lower="-1" upper="1" velocity="1" effort="1"/>',
            ),
            '8 joints move',
        ),
        # A joint lacking limits.
        (
            (
                '<limit lower="-1.6406094968746698" upper="1.6406094968746698" velocity="1.0" '
                'effort="232.0"/>',
                '',
            ),
            'pa10_joint2 lacks limits',
        ),
        # Limits without velocity.
        (('velocity="2.0" effort="100.0"', 'effort="100.0"'), 'lacks limits (velocity'),
        # A continuous joint.
        (
            ('name="pa10_joint1" type="revolute"', 'name="pa10_joint1" type="continuous"'),
            'pa10_joint1 is continuous',
        ),
        # Position limits that leave no motion.
        (
            ('lower="-3.0892327760299634" upper="3.0892327760299634"', 'lower="0.5" upper="0.5"'),
            'no usable position limits',
        ),
    ],
)
def test_urdf_that_is_no_7_dof_arm_with_tool0_is_refused_clearly(tmp_path, edit, message):
    path = _edited_pa10(tmp_path, *edit)
    with pytest.raises(InvalidInput) as raised:
        load_robot(path)
    assert message in str(raised.value)
    assert '\n' not in str(raised.value)  # one line


def test_panda_as_it_ships_is_a_7_dof_arm_at_its_tip_frame(tmp_path):
    from vgm_evaluation.task_generator import panda_arm  # fails (not skips) without the data

    arm = panda_arm()
    full_urdf = importlib.metadata.distribution('example-robot-data').locate_file(
        'cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf'
    )
    reference = load_robot(str(full_urdf), tip_frame='panda_hand_tcp')
    assert arm.urdf == full_urdf.read_text() and arm.tip_frame == 'panda_hand_tcp'
    path = tmp_path / 'panda.urdf'
    path.write_text(arm.urdf)
    robot = load_robot(str(path), tip_frame=arm.tip_frame)
    assert robot.n_joints == 7
    q = arm.start_joints
    np.testing.assert_allclose(
        robot.forward_kinematics(q), reference.forward_kinematics(q), atol=1e-12
    )


def test_an_arm_from_a_torso_is_its_chain_from_the_base_frame_placed_in_base_link():
    """TIAGo's arm from torso_lift_link: the lift, wheels (continuous) and head locked,
    poses relative to the torso frame, moved by base_placement."""
    from vgm_evaluation.task_generator import ROBOT_DATA_DIR

    urdf = importlib.metadata.distribution('example-robot-data').locate_file(
        f'{ROBOT_DATA_DIR}/tiago_description/robots/tiago.urdf'
    )
    with pytest.raises(InvalidInput, match='8 joints move'):
        load_robot(str(urdf), tip_frame='arm_tool_link')  # the lift joint too
    robot = load_robot(str(urdf), tip_frame='arm_tool_link', base_frame='torso_lift_link')
    assert robot.joint_names == tuple(f'arm_{i}_joint' for i in range(1, 8))
    full = pin.buildModelFromUrdf(str(urdf))
    data = full.createData()
    q = np.random.default_rng(3).uniform(robot.lower_limits, robot.upper_limits)
    q_full = pin.neutral(full)
    for name, value in zip(robot.joint_names, q):
        q_full[full.idx_qs[full.getJointId(name)]] = value
    pin.framesForwardKinematics(full, data, q_full)
    T_torso_tip = data.oMf[full.getFrameId('torso_lift_link')].actInv(
        data.oMf[full.getFrameId('arm_tool_link')]
    )
    np.testing.assert_allclose(robot.forward_kinematics(q), T_torso_tip.homogeneous, atol=1e-12)
    placement = [0.1, -0.2, 0.3, 0.0, 0.0, np.pi / 2]
    placed = load_robot(
        str(urdf),
        tip_frame='arm_tool_link',
        base_frame='torso_lift_link',
        base_placement=placement,
    )
    T_link_base = np.eye(4)
    T_link_base[:3, :3] = pin.rpy.rpyToMatrix(*placement[3:])
    T_link_base[:3, 3] = placement[:3]
    np.testing.assert_allclose(
        placed.forward_kinematics(q), T_link_base @ T_torso_tip.homogeneous, atol=1e-12
    )
    J, J_placed = robot.jacobian(q), placed.jacobian(q)
    np.testing.assert_allclose(J_placed[:3], T_link_base[:3, :3] @ J[:3], atol=1e-12)
    with pytest.raises(InvalidInput, match='set base_frame to one of its frames'):
        load_robot(str(urdf), tip_frame='arm_tool_link', base_frame='torso')


def test_random_pa10_like_arms_are_7_dof_with_their_tool(tmp_path):
    from vgm_evaluation.task_generator import random_pa10_like_arm

    rng = np.random.default_rng(13)
    for i in range(5):
        arm = random_pa10_like_arm(rng)
        path = tmp_path / f'arm{i}.urdf'
        path.write_text(arm.urdf)
        robot = load_robot(str(path))
        assert robot.n_joints == 7
        assert np.all(robot.lower_limits < arm.start_joints - 0.49)
        assert np.all(robot.upper_limits > arm.start_joints + 0.49)
        # Zero pose straight up: the tip at the sum of the offsets and the tool.
        tip = robot.forward_kinematics(np.zeros(7))[:3, 3]
        np.testing.assert_allclose(
            tip, [0, 0, sum(arm.link_offsets_m) + arm.tool_length_m], atol=1e-12
        )
        real = np.array([0.317, 0.45, 0.48, 0.07])
        assert np.all(np.abs(np.array(arm.link_offsets_m) / real - 1) <= 0.4)
        assert 0.05 <= arm.tool_length_m <= 0.2


@pytest.mark.parametrize('name, tool_m', CASES)
def test_the_pa10s_shoulder_is_on_its_s2_axis_and_its_reach_the_offsets_beyond(name, tool_m):
    """The PA-10's first two axes cross d1 above the base; straight up, the tip is d3 +
    d5 + d7 + the tool from there, its farthest."""
    params = PARAMETER_SETS[name]
    shoulder, reach = workspace_reach(load_robot(name, tool_m))
    np.testing.assert_allclose(shoulder, [0.0, 0.0, params.d1], atol=1e-12)
    assert reach == pytest.approx(params.d3 + params.d5 + params.d7 + tool_m, abs=1e-12)


@pytest.mark.parametrize('name', ['tiago', 'talos_left'])
def test_the_reach_bounds_an_arm_whose_second_joint_is_off_its_first_joints_axis(tmp_path, name):
    """TIAGo's and Talos's arms (example-robot-data, from the torso, placed off the origin):
    the second joint's origin is 0.13 / 0.14 m off the first joint's axis (taken as the
    shoulder it gave TIAGo a reach of 0.675 m where its tip gets 0.906 m away, and a
    path near the reach was refused). The shoulder is on the first joint's axis (turning
    that joint alone keeps every tip's distance from it, to 1e-12 m); 5000 seeded
    configurations within the limits all have the tip within the reach, the farthest
    within 2 % of it (measured 0.99 of it: the bound is nearly tight)."""
    from vgm_evaluation.task_generator import robot_data_arm

    arm = robot_data_arm(name)
    urdf = tmp_path / f'{name}.urdf'
    urdf.write_text(arm.urdf)
    robot = load_robot(
        str(urdf),
        tip_frame=arm.tip_frame,
        base_frame=arm.base_frame,
        base_placement=[0.15, -0.485, 0.39, 0.0, 0.0, 0.3],
    )
    shoulder, reach = workspace_reach(robot)
    rng = np.random.default_rng(7)
    q = rng.uniform(robot.lower_limits, robot.upper_limits, (5000, robot.n_joints))
    distances = np.array(
        [np.linalg.norm(robot.forward_kinematics(x)[:3, 3] - shoulder) for x in q]
    )
    turned = q.copy()
    turned[:, 0] = rng.uniform(robot.lower_limits[0], robot.upper_limits[0], len(q))
    turned_distances = np.array(
        [np.linalg.norm(robot.forward_kinematics(x)[:3, 3] - shoulder) for x in turned[:200]]
    )
    np.testing.assert_allclose(turned_distances, distances[:200], atol=1e-12)
    print(f'{name}: reach {reach:.4f} m, farthest sampled tip {distances.max():.4f} m')
    assert distances.max() <= reach + 1e-12
    assert distances.max() > 0.98 * reach
