"""The thesis's neural refinement of a camera (ALGORITHMS.md §3.5), the second stage of
``method: lxpm_ga`` after the GA (``lxpm_ga``): a linear network whose weights are the
projection's matrices, trained on the undistorted chart points. No ROS here.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from calib_node.seed_calibration import check_points, decompose_projection, hartley_normalise
from calib_node.seed_camera import identifiable, project_seed
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray


class NetworkInfo(NamedTuple):
    """How :func:`network_refine` went: the RMS [px] of the start camera and of the
    network's, the loss per epoch and whether the network's camera was returned."""

    rms_before: float  # reprojection RMS [px] of the start camera (full seed model)
    rms_after: float  # and of the network's camera
    loss: np.ndarray  # (epochs,) mean network error 1/2 |d - O|^2 in normalised units
    accepted: bool  # the network's camera was returned (else the start camera)


NETWORK_ACCEPT = ('if_better', 'always')


def undistort_seed_pixels(params: FloatArray, pixels: npt.ArrayLike) -> FloatArray:
    """Remove the seed's division distortion from (N, 2) pixels of camera ``params`` (12,):
    X_u = X_d (1 + k |X_d|^2) with X_d = ((u - u0) / Nx, (v - v0) / Ny) (4.2.3, explicit
    in this direction)."""
    u0, v0, Nx, Ny, k = params[0], params[1], params[2], params[3], params[5]
    xy_d = (np.asarray(pixels, dtype=float) - [u0, v0]) / [Nx, Ny]
    xy_u = xy_d * (1 + k * np.sum(xy_d**2, axis=1, keepdims=True))
    return xy_u * [Nx, Ny] + [u0, v0]


NETWORK_WEIGHTS = ('structured', 'free')


def network_refine(
    params: npt.ArrayLike,
    points_world: npt.ArrayLike,
    pixels: npt.ArrayLike,
    epochs: int = 3000,
    rate_D: float = 0.05,
    rate_B: float = 0.05,
    rate_gamma: float = 0.5,
    weights: str = 'structured',
    accept: str = 'if_better',
) -> tuple[FloatArray, NetworkInfo]:
    """The seed's neural refinement of one camera (ALGORITHMS.md §3.5, 4.5.1-4.5.7).

    A linear network: hidden h_i = B W_i (B 4x4, the extrinsics [R T; 0 1]), output
    O_i = gamma_i D h_i (D 3x4, the intrinsics [A | 0]), target d_i = (u_i, v_i, 1) with the
    GA's distortion removed first (the network cannot model k; f and k keep their start
    values). Full-batch gradient descent on E = 1/2 sum |d_i - O_i|^2 with the thesis's
    updates (dD = eta_D gamma e h^T, dB = eta_B gamma D^T e W^T, dgamma = eta_g e^T D h),
    averaged over the points, on Hartley-normalised inputs and targets, with a
    backtracking factor on the rates (halved when a step would raise E) [C].

    ``weights`` [C] (A4.10):

    - ``'structured'`` (default): the weights *are* the matrices, as §3.5 states: only the
      entries that stand for fx, fy, u0, v0 in D and for [R T] in B's top rows are
      trained (the thesis's updates masked to them; D's zeros, D33 = 1 and B's last row
      (0, 0, 0, 1) stay), which the similarity normalisations preserve. Read-out as §3.5:
      D's entries, B's 3x3 block projected onto SO(3) by SVD (its scale, a gauge shared
      with gamma, divided out of T too).
    - ``'free'``: every entry of D and B trained; read-out by RQ of the product D B (the
      data fix only the product; this moves the principal point freely and can wreck a
      poor start).

    Start [C]: B's top rows are divided by the mean start depth, so that gamma_i = 1 (the
    thesis's start) is consistent (D h has third component about 1).

    ``accept`` [C]: ``'if_better'`` (default) returns the network's camera only if its
    full-model reprojection RMS is lower than the start's (the network fits targets
    undistorted with the GA's k, which it cannot correct, so a poor k can make the
    network's camera worse in the full model); ``'always'`` returns it regardless.

    Args:
        params: (12,) start camera in ``PARAM_NAMES`` order (the GA result).
        points_world: (N, 3) [unit]; pixels: (N, 2) [px].

    Returns:
        (refined params (12,), :class:`NetworkInfo`).
    """
    params = np.asarray(params, dtype=float)
    if params.shape != (12,) or params[4] <= 0:
        raise InvalidInput('params: expected shape (12,) with f > 0', key='params')
    if weights not in NETWORK_WEIGHTS:
        raise InvalidInput(
            f'weights: expected one of {NETWORK_WEIGHTS}, got {weights!r}', key='weights'
        )
    if accept not in NETWORK_ACCEPT:
        raise InvalidInput(
            f'accept: expected one of {NETWORK_ACCEPT}, got {accept!r}', key='accept'
        )
    points_world, (pixels,) = check_points(points_world, pixels)
    targets = undistort_seed_pixels(params, pixels)
    T3, T2 = hartley_normalise(points_world), hartley_normalise(targets)
    W = np.column_stack([points_world, np.ones(len(points_world))]) @ T3.T  # (N, 4)
    d = np.column_stack([targets, np.ones(len(targets))]) @ T2.T  # (N, 3)
    D, B, masks = _network_start(params, W, T2, T3, weights)
    D, B, loss = _train_network(W, d, D, B, masks, epochs, (rate_D, rate_B, rate_gamma))
    refined = _read_out_network(params, D, B, T2, T3, weights)
    rms = [_seed_rms(p, points_world, pixels) for p in (params, refined)]
    accepted = accept == 'always' or rms[1] < rms[0]
    return (refined if accepted else params.copy()), NetworkInfo(rms[0], rms[1], loss, accepted)


def _network_start(
    params: FloatArray, W: FloatArray, T2: FloatArray, T3: FloatArray, weights: str
) -> tuple[FloatArray, FloatArray, tuple[FloatArray, FloatArray]]:
    """(D (3, 4), B (4, 4), (mask_D, mask_B)): the start camera's matrices in the
    normalised units of the inputs W and the targets, and which of their entries train."""
    start = identifiable(params)
    B = np.eye(4)
    B[:3, :3], B[:3, 3] = start.R, start.T
    D = np.array([[start.fx, 0, start.u0, 0], [0, start.fy, start.v0, 0], [0, 0, 1, 0]])
    B = B @ np.linalg.inv(T3)
    D = T2 @ D
    if weights == 'structured':
        mask_D = np.zeros((3, 4))
        mask_D[0, 0] = mask_D[1, 1] = mask_D[0, 2] = mask_D[1, 2] = 1.0
        mask_B = np.zeros((4, 4))
        mask_B[:3] = 1.0
        B[:3] /= np.mean((W @ B.T)[:, 2])  # gauge: mean depth 1, so gamma = 1 fits
    else:
        mask_D, mask_B = np.ones((3, 4)), np.ones((4, 4))
        # Gauge [C]: D B is all the data fix, so balance the two factors (hidden units of
        # order 1, mean output depth 1) for a well-conditioned descent.
        depth = np.mean((W @ B.T)[:, 2])
        B[:3] /= depth
        D[:, :3] *= depth
        D /= np.mean((W @ B.T @ D.T)[:, 2])
    return D, B, (mask_D, mask_B)


def _train_network(
    W: FloatArray,
    d: FloatArray,
    D: FloatArray,
    B: FloatArray,
    masks: tuple[FloatArray, FloatArray],
    epochs: int,
    rates: tuple[float, float, float],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(D, B, loss per epoch): ``epochs`` of full-batch gradient descent with the
    thesis's updates, from gamma = 1, the rates scaled by a backtracking factor."""
    (mask_D, mask_B), (rate_D, rate_B, rate_gamma) = masks, rates
    gamma = np.ones(len(W))
    count = len(W)
    loss = np.empty(epochs)
    rate = 1.0  # backtracking factor on the three rates [C]: halve when a step raises E

    def error(
        D: FloatArray, B: FloatArray, gamma: FloatArray
    ) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        h = W @ B.T
        Dh = h @ D.T
        e = d - gamma[:, None] * Dh
        return 0.5 * np.mean(np.sum(e**2, axis=1)), h, Dh, e

    current, h, Dh, e = error(D, B, gamma)
    for epoch in range(epochs):
        ge = gamma[:, None] * e
        steps = (
            rate * rate_D * mask_D * (ge.T @ h) / count,
            rate * rate_B * mask_B * (D.T @ ge.T @ W) / count,
            rate * rate_gamma * np.sum(e * Dh, axis=1),
        )
        trial = error(D + steps[0], B + steps[1], gamma + steps[2])
        if trial[0] <= current:
            D, B, gamma = D + steps[0], B + steps[1], gamma + steps[2]
            current, h, Dh, e = trial
            rate = min(1.0, 1.5 * rate)
        else:
            rate *= 0.5
        loss[epoch] = current
    return D, B, loss


def _read_out_network(
    params: FloatArray,
    D: FloatArray,
    B: FloatArray,
    T2: FloatArray,
    T3: FloatArray,
    weights: str,
) -> FloatArray:
    """The camera (12,) the trained matrices stand for, back in pixel and world units
    (the normalisations T2, T3 undone); f and k keep the start's values."""
    from scipy.spatial.transform import Rotation

    refined = params.copy()
    if weights == 'structured':
        A = (np.linalg.inv(T2) @ D)[:, :3]
        A = A / A[2, 2]
        extrinsic = B @ T3
        extrinsic = extrinsic / extrinsic[3, 3]
        U, singular, Vt = np.linalg.svd(extrinsic[:3, :3])
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        t = extrinsic[:3, 3] / np.mean(singular)
        refined[0:2] = A[0, 2], A[1, 2]
        refined[2:4] = A[0, 0] / params[4], A[1, 1] / params[4]
    else:
        K, R, t = decompose_projection(np.linalg.inv(T2) @ D @ B @ T3)
        refined[0:2] = K[0, 2], K[1, 2]
        refined[2:4] = K[0, 0] / params[4], K[1, 1] / params[4]
    refined[6:9] = Rotation.from_matrix(R).as_euler('ZYX')  # alpha, beta, gamma
    refined[9:12] = t
    return refined


def _seed_rms(params: FloatArray, points_world: FloatArray, pixels: FloatArray) -> float:
    """Reprojection RMS [px] of seed camera ``params`` (12,) on the points."""
    residuals = project_seed(params[None], points_world)[0] - pixels
    return float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
