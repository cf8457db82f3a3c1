#!/usr/bin/env python3
"""mrcal's side of ``calib_mrcal.py``: run by mrcal's own interpreter (a separate process,
never imported by the project; mrcal is no dependency of calib_node).

Reads the models mrcal-calibrate-cameras wrote and prints JSON: per camera the
intrinsics, the pose of the camera in camera 0 (T_ref_camera, 4 x 4), the reprojection RMS
over its corners (outliers excluded, as mrcal reports them), the number of outliers and
the projection uncertainty of mrcal's own method (``mrcal.projection_uncertainty``,
default 'mean-pcam') at the given pixels and range, as sqrt(trace) of the 2 x 2
covariance (the figure calib_node reports).

    mrcal_peer.py '{"models": [...], "pixels": [[[u, v], ...], ...], "ranges": [...]}'
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
    }


def main():
    request = json.loads(sys.argv[1])
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
