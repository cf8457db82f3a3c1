#!/usr/bin/env python3
"""mrcal's side of ``calib_mrcal.py``: run by mrcal's own interpreter (a separate process,
never imported by the project; mrcal is no dependency of calib_node).

Reads the models mrcal-calibrate-cameras wrote and prints JSON: per camera the
intrinsics, the pose of the camera in camera 0 (T_ref_camera, 4 x 4), the reprojection RMS
over its corners (outliers excluded, as mrcal reports them), the number of outliers and
the projection uncertainty of mrcal's own method (``mrcal.projection_uncertainty``,
default 'mean-pcam') at the given pixels and range, as sqrt(trace) of the 2 x 2
covariance (the figure calib_node reports), and the chart poses it solved (each frame
in camera 0's, T_ref_frame, 4 x 4).

With "halves": mrcal's cross-validation of two calibrations of the same cameras on two
halves of the views: per camera ``mrcal.projection_diff`` of the two models at the given
range on a 16 x 12 grid (its implied transform fitted per camera, weighted by the
models' uncertainties: mrcal's defaults), worst and median [px].

    mrcal_peer.py '{"models": [...], "pixels": [[[u, v], ...], ...], "ranges": [...]}'
    mrcal_peer.py '{"halves": [[model a, model b], ...], "ranges": [...]}'
"""

import json
import sys

import mrcal
import numpy as np


def camera_figures(path, pixels, range_m):
    model = mrcal.cameramodel(path)
    lensmodel, intrinsics = model.intrinsics()
    inputs = model.optimization_inputs()
    icam = model.icam_intrinsics()
    residuals = mrcal.measurements_board(inputs, icam_intrinsics=icam).reshape(-1, 2)
    rays = mrcal.unproject(np.asarray(pixels, dtype=float), lensmodel, intrinsics)
    points = rays / rays[:, 2:3] * range_m  # on the pixels' rays at depth range_m
    covariance = mrcal.projection_uncertainty(points, model, what='covariance')
    std = np.sqrt(np.trace(covariance, axis1=-2, axis2=-1))
    observations = inputs['observations_board'][
        inputs['indices_frame_camintrinsics_camextrinsics'][:, 1] == icam
    ]
    return {
        'lensmodel': lensmodel,
        'intrinsics': intrinsics.tolist(),  # fx fy cx cy k1 k2 p1 p2 ...
        'T_ref_camera': model.extrinsics_Rt_toref().tolist(),  # (4, 3): R over t
        'rms_px': float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))),
        'outliers': int(np.sum(observations[..., 2] <= 0)),
        'std_px': std.tolist(),
        'T_ref_frame': [_matrix(rt).tolist() for rt in inputs['rt_ref_frame']],
    }


def _matrix(rt):
    Rt = mrcal.Rt_from_rt(rt)  # (4, 3): R over t
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rt[:3], Rt[3]
    return T


def halves_difference(paths, range_m):
    models = [mrcal.cameramodel(path) for path in paths]
    difference = mrcal.projection_diff(models, gridn_width=16, gridn_height=12, distance=range_m)[
        0
    ]
    return {'worst_px': float(np.max(difference)), 'median_px': float(np.median(difference))}


def main():
    request = json.loads(sys.argv[1])
    if 'halves' in request:
        pairs = zip(request['halves'], request['ranges'])
        print(json.dumps([halves_difference(paths, range_m) for paths, range_m in pairs]))
        return
    print(
        json.dumps(
            [
                camera_figures(path, pixels, range_m)
                for path, pixels, range_m in zip(
                    request['models'], request['pixels'], request['ranges']
                )
            ]
        )
    )


if __name__ == '__main__':
    main()
