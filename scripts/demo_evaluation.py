"""What the demo measures against the simulator's ground truth. Plain functions on numpy
arrays (no ROS), shared by scripts/demo.py and the closed-loop tests."""

import numpy as np
import yaml
from vgm_evaluation.metrics import curve_agreement, distance_to_polylines

from sensor_sim.surfaces import normal_base, signed_height_base
from vgm_common.calibration_io import read_calibration
from vgm_common.camera_model import PinholeCamera


def true_cameras(ground_truth_dir):
    """sensor_sim's cameras.yaml -> {name: PinholeCamera}."""
    cameras = yaml.safe_load((ground_truth_dir / 'cameras.yaml').read_text())
    return {
        name: PinholeCamera(
            c['width'], c['height'], c['K'], c['D'], c['T_base_camera'], c['distortion_model']
        )
        for name, c in cameras.items()
    }


def true_curve(ground_truth_dir):
    """The true curve's polylines (one (N, 3) array each) in base_link."""
    with np.load(ground_truth_dir / 'curve_base.npz') as pieces:
        return [pieces[key] for key in pieces.files]


def curve_errors(waypoints, polylines):
    """Waypoints (N, 3) against the true curve: RMS and max distance to it [m], and the
    coverage: the largest distance of a true-curve point to the waypoints' polyline."""
    agreement = curve_agreement(waypoints, polylines)
    return {
        'rms_m': agreement.rms_m,
        'max_m': agreement.max_m,
        'coverage_m': agreement.farthest_uncovered_m,
        'count': len(waypoints),
    }


def calibration_errors(calibration_file, cameras_true, depth_true):
    """Calibrated vs true cameras. The headline number is the image-space disagreement:
    points of the true surface seen by each camera are projected with the calibrated and
    the true camera; their pixel distance [px] (RMS, max) is what the pipeline feels.
    Also relative focal errors, camera-centre error [m] and the stereo baseline."""
    calibrated = {
        name: camera for name, (camera, _, _) in read_calibration(calibration_file).items()
    }
    errors = {}
    for name, truth in cameras_true.items():
        camera = calibrated[name]
        points = surface_points_from_depth(truth, depth_true[name], step=8)
        pixels_true, _ = truth.project(points)
        pixels, _ = camera.project(points)
        difference = np.linalg.norm(pixels - pixels_true, axis=1)
        errors[name] = {
            'image_rms_px': float(np.sqrt(np.mean(difference**2))),
            'image_max_px': float(difference.max()),
            'fx_rel': float(camera.K[0, 0] / truth.K[0, 0] - 1),
            'fy_rel': float(camera.K[1, 1] / truth.K[1, 1] - 1),
            'centre_m': float(np.linalg.norm(camera.centre_base - truth.centre_base)),
        }
    baseline = np.linalg.norm(calibrated['left'].centre_base - calibrated['right'].centre_base)
    baseline_true = np.linalg.norm(
        cameras_true['left'].centre_base - cameras_true['right'].centre_base
    )
    errors['baseline_rel'] = float(baseline / baseline_true - 1)
    return errors


def surface_points_from_depth(camera, depth, step=1):
    """base_link points of a raw depth map (metres along the optical axis, NaN = none)."""
    v, u = np.mgrid[0 : depth.shape[0] : step, 0 : depth.shape[1] : step]
    z = depth[v, u].ravel()
    keep = np.isfinite(z)
    pixels = np.column_stack([u.ravel(), v.ravel()])[keep].astype(float)
    xy = camera.undistort_pixels(pixels)
    points_camera = np.column_stack([xy * z[keep, None], z[keep]])
    return points_camera @ camera.T_base_camera[:3, :3].T + camera.T_base_camera[:3, 3]


def depth_heights(depth, P_rect, R_rect, T_base_left, surface):
    """The measure of a depth image in the rectified left frame: each pixel lifted to 3D,
    taken to base_link through the calibrated left pose and rectification, and its
    signed height above the true surface [m] (H, W), NaN where the depth has none."""
    heights = np.full(depth.shape, np.nan)
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(float)
    fx, fy, cx, cy = P_rect[0, 0], P_rect[1, 1], P_rect[0, 2], P_rect[1, 2]
    points_rect = np.column_stack([(u - cx) / fx * z, (v - cy) / fy * z, z])
    points_left = points_rect @ R_rect  # x_rect = R x_left
    points_base = points_left @ T_base_left[:3, :3].T + T_base_left[:3, 3]
    heights[v, u] = signed_height_base(surface, points_base)
    return heights


def depth_errors(depth, P_rect, R_rect, T_base_left, surface):
    """A depth image in the rectified left frame against the true surface: the
    statistics of |depth_heights| [m] (the report's depth rows)."""
    error = np.abs(depth_heights(depth, P_rect, R_rect, T_base_left, surface))
    error = error[np.isfinite(error)]
    return {
        'median_abs_m': float(np.median(error)),
        'rms_m': float(np.sqrt(np.mean(error**2))),
        'p90_abs_m': float(np.percentile(error, 90)),
        'pixels': int(error.size),
        'coverage': float(error.size / depth.size),
    }


def true_rectified_depth(camera, depth_raw, R_rect, P_rect, shape):
    """The true depth [m] on the grid of a depth image of the rectified left frame
    (``shape`` (H, W), intrinsics ``P_rect``): the true raw depth of ``camera`` lifted to
    3D and projected into that grid (nearest pixel; NaN where nothing lands)."""
    H, W = depth_raw.shape
    v, u = np.mgrid[0:H, 0:W]
    xy = camera.undistort_pixels(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    points_rect = (np.column_stack([xy, np.ones(len(xy))]) * depth_raw.reshape(-1, 1)) @ R_rect.T
    ok = np.all(np.isfinite(points_rect), axis=1) & (points_rect[:, 2] > 0)
    points_rect = points_rect[ok]
    uu = np.round(P_rect[0, 0] * points_rect[:, 0] / points_rect[:, 2] + P_rect[0, 2])
    vv = np.round(P_rect[1, 1] * points_rect[:, 1] / points_rect[:, 2] + P_rect[1, 2])
    inside = (uu >= 0) & (uu < shape[1]) & (vv >= 0) & (vv < shape[0])
    out = np.full(shape, np.nan)
    out[vv[inside].astype(int), uu[inside].astype(int)] = points_rect[inside, 2]
    return out


def tool_path_distances(tool_positions, polylines, surface):
    """The two distances of tool tips (N, 3) to the true curve [m]: on the surface (the
    tip taken back onto it along the normal: the tool path the tolerance is about) and
    in 3D (the pressed tip, force / stiffness below the surface)."""
    tool_positions = np.atleast_2d(tool_positions)
    heights = signed_height_base(surface, tool_positions)
    on_surface = tool_positions - heights[:, None] * normal_base(surface, tool_positions)
    return distance_to_polylines(on_surface, polylines), distance_to_polylines(
        tool_positions, polylines
    )


def tracking_errors(tool_positions, polylines, forces, desired_force, surface, band=0.10):
    """Tool path and contact force while tracking [m, N]. The tool tip presses into the
    compliant surface by force / stiffness (2.5 mm at 5 N and 2000 N/m), so the path error
    is measured on the surface: the tip taken back onto it along the normal, to the true
    curve. The 3D distance of the pressed tip and the pressing depth are reported too."""
    tool_positions = np.atleast_2d(tool_positions)
    heights = signed_height_base(surface, tool_positions)
    d, d_3d = tool_path_distances(tool_positions, polylines, surface)
    force_error = np.abs(np.asarray(forces) - desired_force)
    return {
        'path_rms_m': float(np.sqrt(np.mean(d**2))),
        'path_max_m': float(d.max()),
        'path_3d_rms_m': float(np.sqrt(np.mean(d_3d**2))),
        'pressing_depth_mean_m': float(-np.mean(heights)),
        'force_mean_N': float(np.mean(forces)),
        'force_rms_error_N': float(np.sqrt(np.mean(force_error**2))),
        'force_max_error_N': float(force_error.max()),
        'force_in_band': float(np.mean(force_error <= band * desired_force)),
        'samples': len(d),
    }
