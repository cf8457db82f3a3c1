"""The thesis's fusion of SFS with stereo depth (ALGORITHMS.md §4.4, ``fusion: mlp_rows``):
one small network per image row maps the SFS depth to the stereo depth, trained by
back-propagation on the row's stereo points. Ours is in ``fusion``. No ROS here.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, cast

import numpy as np
import numpy.typing as npt

from sfs_stereo_node.fusion import BoolArray, check_pair
from vgm_common.geometry import FloatArray


class RowFusion(NamedTuple):
    """What :func:`fuse_mlp_rows` made: the fused depth, the rows that were trained and
    each row's loss before and after training."""

    depth: FloatArray  # (H, W) fused depth, in the stereo depth's unit
    trained_rows: BoolArray  # (H,) rows with at least one stereo point
    loss_initial: FloatArray  # (H,) scaled mean squared error before training, NaN if untrained
    loss_final: FloatArray  # (H,) the same after training


def _sigmoid(a: FloatArray) -> FloatArray:
    return 1.0 / (1.0 + np.exp(-a))


def _forward(
    params: Sequence[FloatArray], x: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Batched 1-6-3-1 network: x (R, N) -> output (R, N) and the hidden activations."""
    W1, b1, W2, b2, W3, b3 = params  # (R,6), (R,6), (R,3,6), (R,3), (R,3), (R,)
    h1 = _sigmoid(x[..., None] * W1[:, None, :] + b1[:, None, :])  # (R, N, 6)
    h2 = _sigmoid(np.einsum('rnj,rkj->rnk', h1, W2) + b2[:, None, :])  # (R, N, 3)
    return np.einsum('rnk,rk->rn', h2, W3) + b3[:, None], h1, h2


def train_row_networks(
    x: FloatArray,
    t: FloatArray,
    mask: BoolArray,
    rng: np.random.Generator,
    hidden: tuple[int, int] = (6, 3),
    learning_rate: float = 0.5,
    epochs: int = 2000,
) -> tuple[list[FloatArray], FloatArray, FloatArray]:
    """Train one network per row at once by full-batch back-propagation (§4.4).

    ``x``, ``t`` (R, N) scaled inputs and targets, ``mask`` (R, N) bool training points
    (each row's loss is the mean squared error over its own points). Weights start from
    N(0, 1/fan_in) drawn from ``rng``. Returns (params, loss_initial (R,), loss_final (R,)).
    """
    R = x.shape[0]
    n1, n2 = hidden
    params = [
        rng.normal(0, 1.0, (R, n1)),
        np.zeros((R, n1)),
        rng.normal(0, n1**-0.5, (R, n2, n1)),
        np.zeros((R, n2)),
        rng.normal(0, n2**-0.5, (R, n2)),
        np.zeros(R),
    ]
    weight = mask / np.maximum(mask.sum(axis=1, keepdims=True), 1)  # per-row mean
    losses: list[FloatArray] = []
    for _ in range(epochs + 1):
        y, h1, h2 = _forward(params, x)
        err = np.where(mask, y - t, 0.0)
        losses.append(np.sum(weight * err**2, axis=1))
        if len(losses) > epochs:
            break
        g_y = 2 * weight * err  # (R, N) dLoss/dy
        g_a2 = g_y[..., None] * params[4][:, None, :] * h2 * (1 - h2)  # (R, N, 3)
        g_a1 = np.einsum('rnk,rkj->rnj', g_a2, params[2]) * h1 * (1 - h1)  # (R, N, 6)
        grads = [
            np.einsum('rnj,rn->rj', g_a1, x),
            g_a1.sum(axis=1),
            np.einsum('rnk,rnj->rkj', g_a2, h1),
            g_a2.sum(axis=1),
            np.einsum('rn,rnk->rk', g_y, h2),
            g_y.sum(axis=1),
        ]
        params = [w - learning_rate * g for w, g in zip(params, grads)]
    return params, losses[0], losses[-1]


def fuse_mlp_rows(
    Z_sfs: npt.ArrayLike,
    Z_stereo: npt.ArrayLike,
    rng: np.random.Generator,
    hidden: tuple[int, int] = (6, 3),
    learning_rate: float = 0.5,
    epochs: int = 2000,
) -> RowFusion:
    """The seed's ``mlp_rows`` fusion: per image row, a network maps Z_sfs to Z_stereo.

    Each row is min-max scaled to [0, 1] (inputs over the whole row of ``Z_sfs``, targets
    over its stereo points), trained on its stereo points and applied to the whole row.
    Rows without stereo points borrow the nearest trained row's network with that row's
    scaling. ``rng`` a numpy Generator (deterministic for a seed). Returns ``RowFusion``.
    """
    Z_sfs, Z_stereo, mask = check_pair(Z_sfs, Z_stereo)
    trained = cast(BoolArray, mask.any(axis=1))  # (H,); numpy's stubs also allow a scalar
    rows = np.flatnonzero(trained)
    x_lo, x_hi = Z_sfs.min(axis=1), Z_sfs.max(axis=1)
    masked_t = np.where(mask, Z_stereo, np.nan)[rows]
    t_lo, t_hi = np.nanmin(masked_t, axis=1), np.nanmax(masked_t, axis=1)
    x_lo, x_span = x_lo[rows, None], np.maximum(x_hi - x_lo, 1e-12)[rows, None]
    t_span = np.maximum(t_hi - t_lo, 1e-12)[:, None]
    t = np.where(mask[rows], (Z_stereo[rows] - t_lo[:, None]) / t_span, 0.0)
    params, loss0, loss1 = train_row_networks(
        (Z_sfs[rows] - x_lo) / x_span, t, mask[rows], rng, hidden, learning_rate, epochs
    )
    # nearest trained row (index into ``rows``) for every image row
    source = np.argmin(np.abs(np.arange(Z_sfs.shape[0])[:, None] - rows[None, :]), axis=1)
    y, _, _ = _forward([w[source] for w in params], (Z_sfs - x_lo[source]) / x_span[source])
    loss_initial, loss_final = np.full(len(trained), np.nan), np.full(len(trained), np.nan)
    loss_initial[rows], loss_final[rows] = loss0, loss1
    return RowFusion(y * t_span[source] + t_lo[source, None], trained, loss_initial, loss_final)
