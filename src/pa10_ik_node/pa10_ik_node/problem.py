"""The velocity-level redundancy problem every IK solver of this package solves
(ALGORITHMS.md §6.5), its checks and its reference solution.

    min_qdot 1/2 qdot^T W qdot   subject to   J qdot = rdot_d,

with ``J`` the (6, n) geometric Jacobian of the tool in base_link (linear rows first,
then angular), ``W`` an (n, n) symmetric and possibly indefinite weight, and ``rdot_d``
the desired twist (6,) [m/s, rad/s]. Its KKT point satisfies ``W qdot + J^T lam = 0`` and
``J qdot = rdot_d``. It is a minimum only where ``W`` is positive definite on null(J)
(Finsler, A7.3); elsewhere the problem is unbounded and the thesis's primal-dual
dynamics diverge for every gain ``K``. No ROS here.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import scipy.linalg

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

TWIST_DIM = 6


def check_problem(
    J: npt.ArrayLike, W: npt.ArrayLike | None = None, rdot_d: npt.ArrayLike | None = None
) -> list[FloatArray]:
    """Float copies of the problem data; raises ``InvalidInput`` naming the expected shape."""
    J = np.array(J, dtype=float)
    if J.ndim != 2 or J.shape[0] != TWIST_DIM:
        raise InvalidInput(f'J must have shape (6, n), got {J.shape}', 'J', J)
    n = J.shape[1]
    arrays = [J]
    if W is not None:
        W = np.array(W, dtype=float)
        if W.shape != (n, n):
            raise InvalidInput(f'W must have shape ({n}, {n}), got {W.shape}', 'W', W)
        arrays.append(0.5 * (W + W.T))
    if rdot_d is not None:
        rdot_d = np.array(rdot_d, dtype=float)
        if rdot_d.shape != (TWIST_DIM,):
            raise InvalidInput(
                f'rdot_d must have shape (6,), got {rdot_d.shape}', 'rdot_d', rdot_d
            )
        arrays.append(rdot_d)
    for array in arrays:
        if not np.all(np.isfinite(array)):
            raise InvalidInput('J, W and rdot_d must be finite', 'J', J)
    return arrays


def initial_vector(value: npt.ArrayLike | None, size: int, key: str) -> FloatArray:
    """A start vector (size,): zeros for None, else a float copy of ``value``; raises
    ``InvalidInput`` (under ``key``) naming the expected shape."""
    if value is None:
        return np.zeros(size)
    value = np.array(value, dtype=float)
    if value.shape != (size,):
        raise InvalidInput(f'{key} must have shape ({size},), got {value.shape}', key, value)
    return value


def kkt_velocity(
    J: npt.ArrayLike, W: npt.ArrayLike, rdot_d: npt.ArrayLike, rcond: float = 1e-10
) -> tuple[FloatArray, FloatArray]:
    """Solve the KKT system of min 1/2 qdot^T W qdot s.t. J qdot = rdot_d directly.

    Solves ``[[W, J^T], [J, 0]] [qdot; lam] = [0; rdot_d]`` in the minimum-norm least-
    squares sense (SVD), so a rank-deficient ``J`` (A7.14) still gives a finite answer: the
    exact KKT point when ``rdot_d`` is in range(J), the least-squares one otherwise. If
    ``W`` is indefinite on null(J) the point is a saddle, not a minimum (A7.3).

    Args:
        J: (6, n) geometric Jacobian in base_link, linear rows first.
        W: (n, n) symmetric weight (only its symmetric part is used).
        rdot_d: (6,) desired twist [m/s, rad/s].
        rcond: singular values below ``rcond * sigma_max`` of the KKT matrix count as 0.

    Returns:
        (qdot, lam): joint velocities (n,) [rad/s] and multipliers (6,).

    Raises:
        InvalidInput: on wrong shapes or non-finite input.
    """
    J, W, rdot_d = check_problem(J, W, rdot_d)
    n = J.shape[1]
    kkt = np.block([[W, J.T], [J, np.zeros((TWIST_DIM, TWIST_DIM))]])
    rhs = np.concatenate([np.zeros(n), rdot_d])
    solution = np.linalg.lstsq(kkt, rhs, rcond=rcond)[0]
    return solution[:n], solution[n:]


def null_space_positive(
    J: npt.ArrayLike, W: npt.ArrayLike, tol: float = 1e-9, rcond: float | None = None
) -> tuple[bool, float]:
    """Whether ``W`` is positive definite on null(J) (Finsler's condition, A7.3).

    Args:
        J: (6, n) Jacobian.
        W: (n, n) symmetric weight.
        tol: the smallest eigenvalue of N^T W N must exceed this.
        rcond: relative singular-value cut-off for the null space
            (``scipy.linalg.null_space``'s default when None).

    Returns:
        (positive, min_eig): the verdict and the smallest eigenvalue of N^T W N, where N
        is an orthonormal basis of null(J); ``(True, inf)`` when null(J) = {0}.
    """
    J, W = check_problem(J, W)
    N = scipy.linalg.null_space(J, rcond=rcond)
    if N.shape[1] == 0:
        return True, float('inf')
    min_eig = float(np.linalg.eigvalsh(N.T @ W @ N)[0])
    return min_eig > tol, min_eig


def absolute_weights(W: FloatArray) -> FloatArray:
    """The matrix absolute value |W| = V |Lambda| V^T of a symmetric (n, n) ``W``.

    For the thesis's diagonal W this is the elementwise absolute value; unlike that, it
    is positive semidefinite for any symmetric W.
    """
    eigenvalues, V = np.linalg.eigh(0.5 * (W + W.T))
    return (V * np.abs(eigenvalues)) @ V.T
