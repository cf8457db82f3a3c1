"""Plane algebraic curves g(X, Y) = a^T mu_n(X, Y) = 0 (ALGORITHMS §2.3 step 1).

Coordinates are normalised image coordinates (X, Y) = (x/z, y/z) of one camera's optical
frame (f = 1, after undistortion). Coefficient vectors have unit norm; their sign is
arbitrary.

Monomial order (``monomial_exponents``): by total degree d = 0..n, and within one degree by
decreasing power of X, i.e. for n = 2: 1, X, Y, X^2, XY, Y^2 and for n = 3 then
X^3, X^2 Y, X Y^2, Y^3. The thesis's conic (3.4.1) A X^2 + B Y^2 + C XY + D X + E Y + F is
a = (F, D, E, A, C, B) in this order.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from math import comb

import numpy as np
import numpy.typing as npt

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

IntArray = npt.NDArray[np.int64]  # exponents and index arrays


def monomial_exponents(degree: int) -> IntArray:
    """(M, 2) int exponents (j, l) of X^j Y^l, j + l <= degree, in the module's order;
    M = (degree + 1)(degree + 2) / 2."""
    if int(degree) != degree or degree < 1:
        raise InvalidInput(
            f'degree: expected an integer >= 1, got {degree!r}', key='degree', value=degree
        )
    return _exponents(int(degree))


@lru_cache(maxsize=None)
def _exponents(degree: int) -> IntArray:
    """``monomial_exponents`` built once per degree (read-only: it is shared)."""
    exponents = np.array([(j, d - j) for d in range(degree + 1) for j in range(d, -1, -1)])
    exponents.setflags(write=False)
    return exponents


def _as_xy(xy: npt.ArrayLike) -> FloatArray:
    xy = np.asarray(xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise InvalidInput(f'xy: expected shape (N, 2), got {xy.shape}', key='xy', value=xy.shape)
    return xy


def monomials(xy: npt.ArrayLike, degree: int) -> FloatArray:
    """Monomial matrix (N, M) with rows mu_n(X, Y) for (N, 2) points ``xy``."""
    xy = _as_xy(xy)
    jx, jy = monomial_exponents(degree).T
    return powers(xy[:, 0], degree)[:, jx] * powers(xy[:, 1], degree)[:, jy]


def powers(values: FloatArray, degree: int) -> FloatArray:
    """(N, degree + 1) matrix of values^k, k = 0..degree, by repeated products (faster
    and exact for negative bases, unlike float exponents)."""
    result = np.ones((len(values), int(degree) + 1))
    for k in range(1, int(degree) + 1):
        result[:, k] = result[:, k - 1] * values
    return result


def check_coefficients(a: npt.ArrayLike, degree: int) -> FloatArray:
    """``a`` as a float (M,) array; ``InvalidInput`` if its length does not match degree."""
    a = np.asarray(a, dtype=float)
    size = len(monomial_exponents(degree))
    if a.shape != (size,):
        raise InvalidInput(
            f'coefficients: expected shape ({size},) for degree {degree}, got {a.shape}',
            key='coefficients',
            value=a.shape,
        )
    return a


def monomials_and_gradients(xy: FloatArray, degree: int) -> tuple[FloatArray, FloatArray]:
    """(Q, M) monomials of (Q, 2) points and (Q, M, 2) their derivatives with respect to X
    and Y, from one set of powers."""
    jx, jy = monomial_exponents(degree).T
    px, py = powers(xy[:, 0], degree), powers(xy[:, 1], degree)
    d_dx = jx * px[:, np.maximum(jx - 1, 0)] * py[:, jy]
    d_dy = jy * px[:, jx] * py[:, np.maximum(jy - 1, 0)]
    return px[:, jx] * py[:, jy], np.stack([d_dx, d_dy], axis=2)


def _shift_scale_matrices(mean: FloatArray, scale: FloatArray, degree: int) -> FloatArray:
    """(B, M, M) matrices T_b with mu(scale_b * (p - mean_b)) = T_b mu(p) for every point
    p, for means (B, 2) and scales (B,)."""
    rows, columns, total, binomial, power_x, power_y = _shift_scale_terms(int(degree))
    size = len(monomial_exponents(degree))
    T = np.zeros((len(mean), size, size))
    T[:, rows, columns] = (
        scale[:, None] ** total * binomial * (-mean[:, :1]) ** power_x * (-mean[:, 1:]) ** power_y
    )
    return T


@lru_cache(maxsize=None)
def _shift_scale_terms(degree: int) -> tuple[IntArray, ...]:
    """The binomial expansion of (scale (X - mx))^jx (scale (Y - my))^jy for each monomial
    (row) into monomials X^p Y^q (column), once per degree: arrays of row, column, jx + jy,
    comb(jx, p) comb(jy, q), jx - p and jy - q (one entry per term; each (row, column)
    occurs once)."""
    exponents = monomial_exponents(degree)
    index = {tuple(e): i for i, e in enumerate(exponents)}
    terms = [
        (row, index[p, q], jx + jy, comb(jx, p) * comb(jy, q), jx - p, jy - q)
        for row, (jx, jy) in enumerate(exponents)
        for p in range(jx + 1)
        for q in range(jy + 1)
    ]
    return tuple(np.array(column) for column in zip(*terms))


FITS = ('taubin', 'algebraic')


def fit_implicit_curve(xy: npt.ArrayLike, degree: int, fit: str = 'taubin') -> FloatArray:
    """Fit a degree-n curve to (N, 2) points.

    ``fit='algebraic'`` (the thesis): min ||M a|| subject to ||a|| = 1. ``'taubin'``
    (default): min ||M a||^2 subject to sum_i ||grad g(p_i)||^2 = N, Taubin's first-order
    approximation of the geometric fit. The algebraic fit of a long, gently curved piece
    of a cubic can put a near-singular point of g beside the data (||grad g|| ~ 0 there),
    so its Sampson residuals reach pixels although the points are within 0.05 px of a
    cubic; Taubin's normalisation makes that solution expensive. Both are solved in
    Hartley-normalised coordinates (centroid at 0, mean distance sqrt(2)) and mapped
    back to the original coordinates. Returns the (M,) unit-norm coefficients. Raises
    ``InvalidInput`` with fewer than M - 1 points (the curve is then not determined).
    """
    return fit_implicit_curves(xy, degree, (fit,))[0]


def fit_implicit_curves(
    xy: npt.ArrayLike, degree: int, fits: Sequence[str] = FITS
) -> list[FloatArray]:
    """``fit_implicit_curve`` by each of ``fits`` on the same points, sharing their
    normalisation and monomials."""
    xy = _as_xy(xy)
    return list(fit_implicit_curves_batch(xy[None], np.array([len(xy)]), degree, fits)[:, 0])


def fit_implicit_curves_batch(
    xy: npt.ArrayLike, counts: npt.ArrayLike, degree: int, fits: Sequence[str] = FITS
) -> FloatArray:
    """``fit_implicit_curve`` by each of ``fits`` on each of B point sets at once (a
    piecewise curve's pieces of one level of splitting: one batched SVD and eigenproblem
    instead of two small ones per piece, whose overhead was the cost).

    Args:
        xy: (B, K, 2) point sets; set b is ``xy[b, :counts[b]]``, the rest is padding.
        counts: (B,) number of points of each set.
        degree: n of the curves.
        fits: any of ``FITS``.

    Returns:
        (len(fits), B, M) unit-norm coefficients.
    """
    xy = np.asarray(xy, dtype=float)
    counts = np.asarray(counts, dtype=int)
    size = len(monomial_exponents(degree))
    if xy.ndim != 3 or xy.shape[2] != 2 or counts.shape != (len(xy),):
        raise InvalidInput(
            f'xy: expected shape (B, K, 2) and counts (B,), got {xy.shape} and {counts.shape}',
            key='xy',
            value=xy.shape,
        )
    if len(xy) and (counts.min() < size - 1 or counts.max() > xy.shape[1]):
        raise InvalidInput(
            f'xy: a degree-{degree} curve needs at least {size - 1} points, got '
            f'{counts.min()} (of at most {xy.shape[1]})',
            key='xy',
            value=int(counts.min()),
        )
    for fit in fits:
        if fit not in FITS:
            raise InvalidInput(f'fit: expected one of {FITS}, got {fit!r}', key='fit', value=fit)
    # padding rows of the monomials and their derivatives are zero: they add nothing to
    # any scatter matrix; at least M rows, so the SVD's last right vector is the null
    # vector even for M - 1 points
    rows = max(xy.shape[1], size)
    valid = np.arange(rows)[None, :] < counts[:, None]  # (B, K)
    padded = np.zeros((len(xy), rows, 2))
    padded[:, : xy.shape[1]] = xy
    weight = valid[..., None].astype(float)
    mean = (padded * weight).sum(axis=1) / counts[:, None]
    centred = (padded - mean[:, None]) * weight
    scale = np.sqrt(2.0) / (np.linalg.norm(centred, axis=2).sum(axis=1) / counts)
    normalised = scale[:, None, None] * centred
    mono, gradients = monomials_and_gradients(normalised.reshape(-1, 2), degree)
    M = mono.reshape(len(xy), rows, size) * weight
    gradients = gradients.reshape(len(xy), rows, size, 2) * weight[..., None]
    back = _shift_scale_matrices(mean, scale, degree).transpose(0, 2, 1)
    # the algebraic fit: the right singular vector of M's smallest singular value, as
    # the eigenvector of M^T M's smallest eigenvalue (a batched SVD of the tall M was
    # most of the fitting time of a knot's chains; the splits of the bench's
    # near-straight draws, whose fits are the most ill-conditioned, stay the same)
    algebraic = np.linalg.eigh(M.transpose(0, 2, 1) @ M)[1][:, :, 0]
    coefficients = []
    for fit in fits:
        if fit == 'algebraic':
            solution = algebraic
        else:
            solution = _taubin(M, gradients[:, :, 1:], weight, algebraic)
        a = np.einsum('bij,bj->bi', back, solution)
        coefficients.append(a / np.linalg.norm(a, axis=1, keepdims=True))
    return np.array(coefficients).reshape(len(fits), len(xy), size)


def _taubin(
    M: FloatArray, gradients: FloatArray, weight: FloatArray, fallback: FloatArray
) -> FloatArray:
    """Taubin's fits (B, M): min a^T M^T M a subject to a^T (Dx^T Dx + Dy^T Dy) a = 1,
    for monomials M (B, K, M) and the derivatives of all but the constant one (B, K,
    M - 1, 2), padding rows (``weight`` (B, K, 1) zero) zero. The constant term (no
    gradient) is eliminated first, a_0 = -mean(M_rest) a_rest, which leaves the
    symmetric-definite problem (M_c^T M_c) a = lambda N a with the centred monomials M_c
    and N positive definite; its smallest lambda is the fit. A set whose N is not
    definite (too few distinct points) takes ``fallback`` (B, M), the algebraic fit.

    The small generalised eigenproblems are solved one by one with LAPACK's driver
    (``scipy.linalg.eigh``): on a near-straight piece of a cubic the smallest
    eigenvalues nearly coincide, and a batched Cholesky reduction, equal to rounding,
    gave coefficients 1e-3 apart, other splits and one more bench miss."""
    from scipy.linalg import eigh

    rest = M[:, :, 1:]
    rest_mean = rest.sum(axis=1) / weight.sum(axis=1)
    centred = (rest - rest_mean[:, None]) * weight
    A = centred.transpose(0, 2, 1) @ centred
    Dx, Dy = gradients[..., 0], gradients[..., 1]
    N = Dx.transpose(0, 2, 1) @ Dx + Dy.transpose(0, 2, 1) @ Dy
    solution = fallback.copy()
    for b in range(len(M)):
        try:
            _, vectors = eigh(A[b], N[b], subset_by_index=[0, 0])
        except np.linalg.LinAlgError:  # N not definite
            continue
        solution[b, 1:] = vectors[:, 0]
        solution[b, 0] = -rest_mean[b] @ vectors[:, 0]
    return solution


def evaluate_curve(a: npt.ArrayLike, xy: npt.ArrayLike, degree: int) -> FloatArray:
    """Algebraic value g(X, Y) = a^T mu_n(X, Y), shape (N,)."""
    return monomials(xy, degree) @ check_coefficients(a, degree)


def curve_gradient(a: npt.ArrayLike, xy: npt.ArrayLike, degree: int) -> FloatArray:
    """Gradient (dg/dX, dg/dY) at (N, 2) points, shape (N, 2)."""
    a = check_coefficients(a, degree)
    xy = _as_xy(xy)
    jx, jy = monomial_exponents(degree).T
    x, y = xy[:, None, 0], xy[:, None, 1]
    # terms with a zero exponent are multiplied by 0, so clipping it at 0 is safe
    d_dx = jx * x ** np.maximum(jx - 1, 0) * y**jy
    d_dy = jy * x**jx * y ** np.maximum(jy - 1, 0)
    return np.column_stack([d_dx @ a, d_dy @ a])


def sampson_distance(a: npt.ArrayLike, xy: npt.ArrayLike, degree: int) -> FloatArray:
    """First-order geometric distance |g| / ||grad g|| of (N, 2) points to the curve, (N,),
    in the units of ``xy`` (normalised image units: pixels / f)."""
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.abs(evaluate_curve(a, xy, degree)) / np.linalg.norm(
            curve_gradient(a, xy, degree), axis=1
        )


def project_to_curve(
    a: npt.ArrayLike, xy: npt.ArrayLike, degree: int, iterations: int = 5
) -> FloatArray:
    """Move (N, 2) points onto the curve by repeated first-order (Sampson) steps
    xy <- xy - g grad g / ||grad g||^2; returns (N, 2). Use it on noisy image-1 samples so
    that their rays lie on cone 1. Points where the gradient vanishes are left as they are.
    """
    xy = _as_xy(xy).copy()
    for _ in range(iterations):
        gradient = curve_gradient(a, xy, degree)
        norm2 = np.sum(gradient**2, axis=1)
        step = np.divide(
            evaluate_curve(a, xy, degree), norm2, out=np.zeros(len(xy)), where=norm2 > 0
        )
        xy -= step[:, None] * gradient
    return xy
