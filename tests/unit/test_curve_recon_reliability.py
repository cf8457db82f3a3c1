"""Issue 18 for curve_recon_node's cores: implausible depth intrinsics and depth values
are refused with a reason (never an OverflowError or a normal made from them), and any
spacing in the parameter's range gives waypoints with proper rotations."""
import numpy as np
import pytest

from curve_recon_node.waypoints import (
    check_depth_intrinsics,
    normals_from_depth,
    resample,
    usable_depth,
    waypoint_frames,
)
from vgm_common.conversions import matrices_to_path
from vgm_common.errors import InvalidInput

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
W, H = 640, 480


def tilted_plane_depth(K, normal_cam, distance):
    """Depth (H, W) [m] of the plane n . x = distance seen by the pinhole K."""
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], 2)
    return distance / (rays @ normal_cam)


def points_on_plane(normal_cam, distance, n=20):
    """Points of the plane in view (camera frame = base here)."""
    t = np.linspace(-0.05, 0.05, n)
    a = np.cross(normal_cam, [0, 1, 0])
    a /= np.linalg.norm(a)
    b = np.cross(normal_cam, a)
    return distance * normal_cam + t[:, None] * a + 0.5 * t[:, None] * b


def test_huge_intrinsics_are_refused_with_a_reason():
    depth = np.full((H, W), 0.5)
    huge = np.full((3, 3), 1e308)
    with pytest.raises(InvalidInput, match='finite|focal'):
        normals_from_depth(np.array([[0.0, 0.0, 0.5]]), depth, huge, np.eye(4))
    for bad in (np.diag([1e308, 1e308, 1.0]), np.diag([0.0, 500.0, 1.0]),
                np.array([[500.0, 0, 1e9], [0, 500, 240], [0, 0, 1]]),
                np.array([[500.0, 0, 320], [3, 500, 240], [0, 0, 1]])):
        with pytest.raises(InvalidInput):
            check_depth_intrinsics(bad, W, H)
    check_depth_intrinsics(K, W, H)


def test_negative_zero_and_huge_depths_give_no_normals():
    normal = np.array([0.3, -0.2, -1.0])
    normal /= np.linalg.norm(normal)
    distance = -0.5  # the plane faces the camera: n . x = -0.5 for x in front
    depth = tilted_plane_depth(K, normal, distance)
    points = points_on_plane(normal, distance)
    good = normals_from_depth(points, depth, K, np.eye(4), 9)
    # the true normal faces the camera (toward -z here), within a fraction of a degree
    assert np.all(np.isfinite(good))
    assert np.degrees(np.arccos(np.clip(good @ normal, -1, 1))).max() < 0.5
    for bad_value in (-0.5, 0.0, 1e30, np.inf):
        bad = np.full((H, W), bad_value)
        cleaned, removed = usable_depth(bad)
        assert np.isnan(cleaned).all() and sum(removed.values()) == H * W
        assert np.isnan(normals_from_depth(points, bad, K, np.eye(4), 9)).all()
    # a depth of some other surface (2 m, the waypoints at ~0.5 m) gives no normal either
    assert np.isnan(normals_from_depth(points, np.full((H, W), 2.0), K, np.eye(4))).all()
    # half the image unusable: the rest still gives the normals where it is valid
    mixed = depth.copy()
    mixed[:, :W // 2] = -1.0
    normals = normals_from_depth(points, mixed, K, np.eye(4), 9)
    u = K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2]
    right = u > W // 2 + 8
    assert np.all(np.isfinite(normals[right])) and np.all(np.isnan(normals[u < W // 2 - 8]))


@pytest.mark.parametrize('spacing', [1e-4, 0.005, 0.2, 0.5, 1.0])
@pytest.mark.parametrize('closed', [True, False])
def test_any_spacing_gives_proper_rotations(spacing, closed):
    t = np.linspace(0, 2 * np.pi if closed else np.pi, 400, endpoint=not closed)
    loop = np.column_stack([0.6 + 0.08 * np.cos(t), 0.05 * np.sin(t), 0.3 + 0.01 * np.sin(2 * t)])
    waypoints = resample(loop, closed, spacing)
    assert len(waypoints) >= (3 if closed else 2)
    frames = waypoint_frames(waypoints, closed)
    R = frames[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (len(R), 1, 1)),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    assert len(matrices_to_path(frames, 1, 'base_link').poses) == len(waypoints)
