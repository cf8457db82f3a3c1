"""Discrete fractional Fourier transform by the eigenvector method (Candan, Kutay and
Ozaktas 2000; thesis 6.3.3-6.3.6), and the JPEG zig-zag scan used as the thesis's
"degradation".

``S`` (``commuting_matrix``) commutes with the unitary DFT; its orthonormal eigenvectors,
sorted by descending eigenvalue, are discrete Hermite-Gauss vectors of orders 0, 1, ...,
N - 2 and then N - 1 (odd N) or N (even N). ``K_a = sum_j exp(-i o_j a) v_j v_j^T`` is
unitary, ``K_a K_b = K_(a+b)`` and ``K_(pi/2)`` is the unitary DFT.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

ComplexArray = npt.NDArray[np.complex128]


def commuting_matrix(n: int) -> FloatArray:
    """The N x N matrix S of ALGORITHMS.md §5.2 (float64, symmetric)."""
    k = np.arange(n)
    S = np.diag(2.0 * np.cos(2.0 * np.pi * k / n))
    S += np.diag(np.ones(n - 1), 1) + np.diag(np.ones(n - 1), -1)
    S[0, n - 1] += 1.0
    S[n - 1, 0] += 1.0
    return S


@lru_cache(maxsize=16)
def _hermite_basis(n: int) -> tuple[FloatArray, FloatArray]:
    """(eigenvectors (N, N) as columns, orders (N,)); read-only, cached per N.

    S has (near-)degenerate eigenvalues, so a plain ``eigh`` of S mixes an even and an
    odd vector of neighbouring orders. As Candan's ``dis_s`` does, S is diagonalised
    separately on the even (x[k] = x[-k mod N]) and odd subspaces; even vectors take
    orders 0, 2, 4, ... and odd ones 1, 3, 5, ... by descending eigenvalue."""
    if n < 2:
        raise InvalidInput(f'the DFrFT needs N >= 2, got {n}')
    S = commuting_matrix(n)
    half = n // 2
    even_basis = np.zeros((n, half + 1))
    even_basis[0, 0] = 1.0
    for k in range(1, half + 1):
        if 2 * k == n:
            even_basis[k, k] = 1.0
        else:
            even_basis[k, k] = even_basis[n - k, k] = np.sqrt(0.5)
    odd_count = (n - 1) // 2
    odd_basis = np.zeros((n, odd_count))
    for k in range(1, odd_count + 1):
        odd_basis[k, k - 1] = np.sqrt(0.5)
        odd_basis[n - k, k - 1] = -np.sqrt(0.5)
    vectors = np.zeros((n, n))
    orders = np.zeros(n)
    for basis, first_order in ((even_basis, 0), (odd_basis, 1)):
        if basis.shape[1] == 0:
            continue
        values, sub = np.linalg.eigh(basis.T @ S @ basis)
        sub = sub[:, np.argsort(-values, kind='stable')]
        for i in range(basis.shape[1]):
            order = first_order + 2 * i
            column = order if order < n else n - 1  # even N: order N takes slot N - 1
            vectors[:, column] = basis @ sub[:, i]
            orders[column] = order
    vectors.setflags(write=False)
    orders.setflags(write=False)
    return vectors, orders


def dfrft_matrix(n: int, angle: float) -> ComplexArray:
    """K_a: the (N, N) complex128 DFrFT matrix for ``angle`` a [rad] (order 2a/pi)."""
    vectors, orders = _hermite_basis(int(n))
    return (vectors * np.exp(-1j * orders * angle)) @ vectors.T


def dfrft2(image: npt.ArrayLike, angles: Sequence[float]) -> ComplexArray:
    """2-D separable DFrFT ``K_a X K_b^T`` of an (M, N) array; ``angles`` = (a, b) [rad],
    a along the rows' index (M), b along the columns' (N)."""
    a, b = angles
    X = np.asarray(image)
    return dfrft_matrix(X.shape[0], a) @ X @ dfrft_matrix(X.shape[1], b).T


@lru_cache(maxsize=16)
def zigzag_order(rows: int, cols: int) -> npt.NDArray[np.intp]:
    """Flat indices of an (rows, cols) array in JPEG zig-zag order: anti-diagonals from
    (0, 0), alternately up-right and down-left (read-only int64 array)."""
    r, c = np.indices((rows, cols))
    diagonal = r + c
    # On even anti-diagonals go up (row decreasing), on odd ones down, as JPEG does.
    along = np.where(diagonal % 2 == 0, -r, r)
    order = np.lexsort((along.ravel(), diagonal.ravel()))
    order.setflags(write=False)
    return order


def zigzag_degrade(image: npt.ArrayLike) -> np.ndarray:
    """Pi: the pixels read in zig-zag order, written back in row-major order."""
    X = np.asarray(image)
    return X.ravel()[zigzag_order(*X.shape)].reshape(X.shape)


def zigzag_restore(image: npt.ArrayLike) -> np.ndarray:
    """Pi^-1 ("d-ZIG-ZAG"), the inverse of ``zigzag_degrade``."""
    X = np.asarray(image)
    out = np.empty(X.size, dtype=X.dtype)
    out[zigzag_order(*X.shape)] = X.ravel()
    return out.reshape(X.shape)
