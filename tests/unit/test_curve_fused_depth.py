"""curve_recon_node's FusedDepth without ROS: a depth image that comes before its
intrinsics waits for them, bad images are refused with nothing changed, and the approach
directions at points of a plane are its normal, into the surface, through a rectification
that is not the identity."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from curve_recon_node.fused_depth import FusedDepth
from vgm_common.errors import InvalidInput

K = np.array([[300.0, 0, 80], [0, 300, 60], [0, 0, 1]])
WIDTH, HEIGHT = 160, 120


def plane_depth(normal_rect, distance_m):
    """The depth image (rectified frame) of the plane n . x = d."""
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
    return distance_m / (rays @ normal_rect)


def test_a_depth_image_before_its_intrinsics_waits_and_one_it_supersedes_is_refused():
    depth = FusedDepth()
    assert depth.add(np.ones((HEIGHT, WIDTH)), 5) is None  # waits
    with pytest.raises(InvalidInput, match='no valid /depth/camera_info yet'):
        depth.add(np.ones((HEIGHT, WIDTH)), 6)
    waiting = depth.set_intrinsics(K, WIDTH, HEIGHT)
    assert waiting.stamp_ns == 6 and depth.latest is None  # the node adds it if stamps agree
    assert depth.add(waiting.depth_m, waiting.stamp_ns) == {
        'not_positive': 0,
        'too_far': 0,
        'too_near': 0,
    }
    assert depth.latest.stamp_ns == 6


def test_unusable_images_and_intrinsics_are_refused_and_change_nothing():
    depth = FusedDepth()
    depth.set_intrinsics(K, WIDTH, HEIGHT)
    depth.add(np.ones((HEIGHT, WIDTH)), 1)
    with pytest.raises(InvalidInput, match='depth is 80x60 but its camera_info says 160x120'):
        depth.add(np.ones((60, 80)), 2)
    with pytest.raises(InvalidInput, match='no usable depth'):
        depth.add(np.full((HEIGHT, WIDTH), -1.0), 3)
    assert depth.latest.stamp_ns == 1
    partly = np.ones((HEIGHT, WIDTH))
    partly[0, :10] = 0.0
    assert depth.add(partly, 4)['not_positive'] == 10
    with pytest.raises(InvalidInput):
        depth.set_intrinsics(np.zeros((3, 3)), WIDTH, HEIGHT)
    assert depth.add(np.ones((HEIGHT, WIDTH)), 5) is None  # waits for valid intrinsics


def test_approach_directions_are_the_plane_normal_into_the_surface():
    R_rect_left = Rotation.from_euler('xyz', [4, -3, 2], degrees=True).as_matrix()
    T_base_left = np.eye(4)
    T_base_left[:3, :3] = Rotation.from_euler('x', 180, degrees=True).as_matrix()  # looks down
    T_base_left[:3, 3] = [0.1, -0.2, 1.0]
    normal_rect = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    depth = FusedDepth()
    depth.set_intrinsics(K, WIDTH, HEIGHT)
    depth.add(plane_depth(normal_rect, 0.8), 1)
    # points of the plane seen near the image centre, in base
    T_base_rect = T_base_left.copy()
    T_base_rect[:3, :3] = T_base_left[:3, :3] @ R_rect_left.T
    points_rect = np.array([[0.0, 0.0, 0.8], [0.05, 0.02, 0.0], [-0.04, 0.03, 0.0]])
    points_rect[1:, 2] = (0.8 - points_rect[1:, :2] @ normal_rect[:2]) / normal_rect[2]
    points_rect[0, 2] = 0.8 / normal_rect[2]
    points_base = points_rect @ T_base_rect[:3, :3].T + T_base_rect[:3, 3]
    approach = depth.approach_directions(points_base, T_base_left, R_rect_left, 9)
    # the normal out of the surface points toward the camera: the approach is away from it
    into_surface_base = T_base_rect[:3, :3] @ normal_rect
    assert np.abs(approach - into_surface_base).max() < 1e-6
    assert (
        depth.approach_directions(points_base + [0, 0, 50.0], T_base_left, R_rect_left, 9) is None
    )
