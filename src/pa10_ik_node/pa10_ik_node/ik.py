"""Redundant inverse kinematics of the PA-10 at the velocity level (ALGORITHMS.md §6.5).

The problem of every control step is

    min_qdot 1/2 qdot^T W qdot   subject to   J qdot = rdot_d,

with ``J`` the (6, n) geometric Jacobian of the tool in base_link (linear rows first,
then angular), ``W`` an (n, n) symmetric and possibly indefinite weight, and ``rdot_d``
the desired twist (6,) [m/s, rad/s]. Its KKT point satisfies ``W qdot + J^T lam = 0`` and
``J qdot = rdot_d``. It is a minimum only where ``W`` is positive definite on null(J)
(Finsler, A7.3); elsewhere the problem is unbounded and the thesis's primal-dual
dynamics diverge for every gain ``K``.

Solvers here: the direct KKT solve (``kkt_velocity``), the thesis's continuous
primal-dual network integrated exactly (``primal_dual_velocity``), its literal
fixed-step rules (``primal_dual_velocity_fixed_step``, which diverge at the thesis's
values, A7.4) and damped least squares as the reference (``dls_velocity``). No ROS here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.linalg
from scipy.spatial.transform import Rotation

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

TWIST_DIM = 6


@dataclass(frozen=True)
class PrimalDualInfo:
    """How a ``primal_dual_velocity`` solve went.

    Attributes:
        converged: both residuals are at most the requested tolerance.
        constraint_residual: ||J v - rdot_d|| at the end [m/s, rad/s mixed].
        stationarity_residual: ||W_used v + J^T u|| at the end.
        null_space_positive: ``W`` (the one given) is positive definite on null(J).
        min_null_eigenvalue: smallest eigenvalue of N^T W N (``inf`` if null(J) = {0}).
        fallback_used: ``weights_fallback`` replaced ``W`` because the check failed.
        gain: the K actually used (raised from the one given when H was not positive
            definite, see ``primal_dual_velocity``).
        min_h_eigenvalue: smallest eigenvalue of H = W_used + gain J^T J.
        t_final: integrated time of the network [s of network time].
    """

    converged: bool
    constraint_residual: float
    stationarity_residual: float
    null_space_positive: bool
    min_null_eigenvalue: float
    fallback_used: bool
    gain: float
    min_h_eigenvalue: float
    t_final: float


def _check_problem(
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


def _initial(value: npt.ArrayLike | None, size: int, key: str) -> FloatArray:
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
    J, W, rdot_d = _check_problem(J, W, rdot_d)
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
    J, W = _check_problem(J, W)
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


def primal_dual_velocity(
    J: npt.ArrayLike,
    W: npt.ArrayLike,
    rdot_d: npt.ArrayLike,
    K: float = 100.0,
    v0: npt.ArrayLike | None = None,
    u0: npt.ArrayLike | None = None,
    t_final: float = 1e5,
    tol: float = 1e-6,
    weights_fallback: npt.ArrayLike | None = None,
    null_space_tol: float = 1e-9,
    max_gain: float = 1e6,
) -> tuple[FloatArray, FloatArray, PrimalDualInfo]:
    """The thesis's continuous primal-dual network (7.4.9-7.4.12), integrated exactly.

    With ``H = W + K J^T J`` the network is

        vdot = -H v - J^T u + K J^T rdot_d,    udot = J v - rdot_d,

    linear with constant coefficients within a control step, so the state ``(v, u)`` at
    ``t_final`` is the exact solution: the matrix exponential of the affine system's
    augmented matrix applied to ``(v0, u0, 1)``. That is stiff-proof (A7.4) and as cheap
    for long horizons as for short ones. The slowest mode decays at about 1/K, so the
    default horizon is long in network time. Warm-start with the previous step's
    ``(v, u)``.

    Stability needs ``H`` positive definite (the Lyapunov argument of §6.5). If ``W`` is
    not positive definite on null(J) no K achieves that (A7.3); then ``weights_fallback``
    (default ``absolute_weights(W)``) replaces ``W`` and ``info.fallback_used`` says so.
    If ``W`` passes that test but ``H`` is still indefinite at the given K (K = 100 is not
    always enough, notably for the real PA-10's short links), K is doubled until it is, up
    to ``max_gain``; the KKT point does not depend on K. ``info.gain`` reports the K used.

    Args:
        J: (6, n) Jacobian; W: (n, n) symmetric weight; rdot_d: (6,) twist [m/s, rad/s].
        K: penalty gain (> 0).
        v0, u0: initial state (n,) [rad/s] and (6,); zeros when None.
        t_final: network time to integrate (> 0).
        tol: residual tolerance for ``info.converged``.
        weights_fallback: (n, n) weight used when the null-space check fails.
        null_space_tol: margin of the null-space check.
        max_gain: largest K tried when raising it.

    Returns:
        (qdot, lam, info): v (n,) [rad/s], u (6,) and a ``PrimalDualInfo``.

    Raises:
        InvalidInput: on wrong shapes, non-finite input or non-positive K / t_final.
    """
    J, W, rdot_d = _check_problem(J, W, rdot_d)
    n = J.shape[1]
    if not K > 0 or not t_final > 0:
        raise InvalidInput(f'K and t_final must be > 0, got {K}, {t_final}', 'K', K)
    v0 = _initial(v0, n, 'v0')
    u0 = _initial(u0, TWIST_DIM, 'u0')
    positive, min_eig = null_space_positive(J, W, null_space_tol)
    W_used = W
    if not positive:
        W_used = (
            absolute_weights(W)
            if weights_fallback is None
            else _check_problem(J, weights_fallback)[1]
        )
    gain = float(K)
    min_h_eig = np.linalg.eigvalsh(W_used + gain * J.T @ J)[0]
    while positive and min_h_eig <= 0 and 2 * gain <= max_gain:
        gain *= 2
        min_h_eig = np.linalg.eigvalsh(W_used + gain * J.T @ J)[0]
    # Augmented affine system: d/dt (v, u, 1) = M (v, u, 1).
    size = n + TWIST_DIM
    M = np.zeros((size + 1, size + 1))
    M[:n, :n] = -(W_used + gain * J.T @ J)
    M[:n, n:size] = -J.T
    M[n:size, :n] = J
    M[:n, size] = gain * J.T @ rdot_d
    M[n:size, size] = -rdot_d
    state = scipy.linalg.expm(M * t_final) @ np.concatenate([v0, u0, [1.0]])
    v, u = state[:n], state[n:size]
    constraint = float(np.linalg.norm(J @ v - rdot_d))
    stationarity = float(np.linalg.norm(W_used @ v + J.T @ u))
    info = PrimalDualInfo(
        converged=bool(constraint <= tol and stationarity <= tol),
        constraint_residual=constraint,
        stationarity_residual=stationarity,
        null_space_positive=positive,
        min_null_eigenvalue=min_eig,
        fallback_used=not positive,
        gain=gain,
        min_h_eigenvalue=float(min_h_eig),
        t_final=float(t_final),
    )
    return v, u, info


def fixed_step_matrix(
    J: npt.ArrayLike, W: npt.ArrayLike, K: float = 100.0, mu: float = 0.02, eta: float = 0.02
) -> FloatArray:
    """The (n+6, n+6) linear part of the literal learning rules of §6.5 on ``(qdot, lam)``.

    Its spectral radius decides whether ``primal_dual_velocity_fixed_step`` converges
    (< 1) or diverges (> 1); at the thesis's Gamma1 start it is about 108 (A7.4).
    """
    J, W = _check_problem(J, W)
    n = J.shape[1]
    return np.block(
        [[np.eye(n) - mu * (W + K * J.T @ J), -mu * J.T], [eta * J, np.eye(TWIST_DIM)]]
    )


def primal_dual_velocity_fixed_step(
    J: npt.ArrayLike,
    W: npt.ArrayLike,
    rdot_d: npt.ArrayLike,
    K: float = 100.0,
    mu: float = 0.02,
    eta: float = 0.02,
    iterations: int = 100,
    v0: npt.ArrayLike | None = None,
    u0: npt.ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The thesis's discrete learning rules of §6.5, taken literally.

        qdot_{k+1} = qdot_k - mu [W qdot_k + J^T lam_k + K J^T (J qdot_k - rdot_d)]
        lam_{k+1}  = lam_k + eta (J qdot_k - rdot_d)

    Kept for the benchmark: at mu = eta = 0.02, K = 100 they diverge on the PA-10 (A7.4).

    Args:
        J: (6, n); W: (n, n); rdot_d: (6,) [m/s, rad/s]; K, mu, eta: gain and step sizes.
        iterations: number of updates.
        v0, u0: initial (n,) and (6,); zeros when None.

    Returns:
        (qdot, lam, norms): the final iterates and ``norms`` (iterations + 1,), the
        Euclidean norm of (qdot_k, lam_k) at every iterate, starting with the initial one.
    """
    J, W, rdot_d = _check_problem(J, W, rdot_d)
    n = J.shape[1]
    qdot = _initial(v0, n, 'v0')
    lam = _initial(u0, TWIST_DIM, 'u0')
    norms = [np.hypot(np.linalg.norm(qdot), np.linalg.norm(lam))]
    for _ in range(int(iterations)):
        residual = J @ qdot - rdot_d
        qdot, lam = (qdot - mu * (W @ qdot + J.T @ lam + K * J.T @ residual), lam + eta * residual)
        norms.append(np.hypot(np.linalg.norm(qdot), np.linalg.norm(lam)))
    return qdot, lam, np.array(norms)


def dls_velocity(J: npt.ArrayLike, twist: npt.ArrayLike, damping: float) -> FloatArray:
    """Damped least squares: qdot = J^T (J J^T + damping^2 I)^-1 twist.

    Args:
        J: (6, n) Jacobian; twist: (6,) [m/s, rad/s]; damping: lambda (>= 0).

    Returns:
        qdot (n,) [rad/s]. With ``damping`` 0 and a full-rank J this is the pseudo-inverse
        (minimum-norm) solution.
    """
    J, twist = _check_problem(J, rdot_d=twist)
    if not damping >= 0:
        raise InvalidInput(f'damping must be >= 0, got {damping}', 'damping', damping)
    gram = J @ J.T + damping**2 * np.eye(TWIST_DIM)
    return J.T @ np.linalg.solve(gram, twist)


def pose_error(T_current: npt.ArrayLike, T_desired: npt.ArrayLike) -> FloatArray:
    """Pose error in base_link (A7.7): position and rotation-vector orientation error.

    Args:
        T_current, T_desired: (4, 4) homogeneous transforms base_link -> tool.

    Returns:
        (6,): ``p_desired - p_current`` [m], then the rotation vector of
        ``R_desired R_current^T`` [rad] (expressed in base_link), so that a twist
        proportional to it drives the current pose towards the desired one.
    """
    T_current = np.asarray(T_current, dtype=float)
    T_desired = np.asarray(T_desired, dtype=float)
    for key, T in (('T_current', T_current), ('T_desired', T_desired)):
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InvalidInput(f'{key} must be a finite (4, 4) array, got shape {T.shape}', key, T)
    position_error = T_desired[:3, 3] - T_current[:3, 3]
    R_error = T_desired[:3, :3] @ T_current[:3, :3].T
    orientation_error = Rotation.from_matrix(R_error).as_rotvec()
    return np.concatenate([position_error, orientation_error])


# --- The solver the node uses: "ours" (closed-form KKT), the seed's network, DLS -------

METHODS = ('ours', 'primal_dual', 'dls')


def closed_form_velocity(
    J: FloatArray, W_inverse: FloatArray, twist: FloatArray, damping: float = 0.0
) -> FloatArray:
    """Closed-form KKT point for a positive definite W, with optional damping.

        qdot = W^-1 J^T (J W^-1 J^T + damping^2 I)^-1 twist

    is the minimiser of 1/2 qdot^T W qdot s.t. J qdot = twist (damping 0, full rank J), and
    of 1/2 qdot^T W qdot + 1/(2 damping^2) ||J qdot - twist||^2 otherwise (the weighted
    damped least squares that stays bounded through singularities).

    Args:
        J: (m, n) task Jacobian, m <= 6 (5 rows when the spin is left free).
        W_inverse: (n, n) inverse of a symmetric positive definite weight.
        twist: (m,) task velocity [m/s, rad/s].
        damping: lambda >= 0.

    Returns:
        qdot (n,) [rad/s].
    """
    JWinv = J @ W_inverse
    gram = JWinv @ J.T
    if damping > 0:
        gram = gram + damping**2 * np.eye(len(gram))
    return JWinv.T @ np.linalg.solve(gram, twist)


def adaptive_damping(
    J: FloatArray, W_inverse: FloatArray, sigma_threshold: float, max_damping: float
) -> tuple[float, float]:
    """Damping that is 0 while the smallest singular value of J W^-1/2 exceeds
    ``sigma_threshold`` and grows smoothly to ``max_damping`` at a singularity
    (Nakamura and Hanafusa's rule): lambda^2 = (1 - (sigma/threshold)^2) max_damping^2.

    Returns:
        (damping, sigma_min).
    """
    eigenvalues = np.linalg.eigvalsh(J @ W_inverse @ J.T)
    sigma_min = float(np.sqrt(max(eigenvalues[0], 0.0)))
    if sigma_min >= sigma_threshold:
        return 0.0, sigma_min
    return float(max_damping * np.sqrt(1.0 - (sigma_min / sigma_threshold) ** 2)), sigma_min


def _pad_to_twist(J: FloatArray, twist: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(6, n) and (6,) from an (m, n) task with m <= 6 (zero rows for the free ones)."""
    m, n = J.shape
    if m == TWIST_DIM:
        return J, twist
    J6, twist6 = np.zeros((TWIST_DIM, n)), np.zeros(TWIST_DIM)
    J6[:m], twist6[:m] = J, twist
    return J6, twist6


class RateSolver:
    """Joint velocities for a task twist by one of ``METHODS``, with joint limits.

    - ``ours``: the KKT point of min 1/2 qdot^T W qdot s.t. J qdot = twist in closed form
      (``closed_form_velocity``) when W is positive definite, damped near singularities;
      for an indefinite W the full KKT system where W is positive on null(J) and |W|
      where it is not (A7.3). Joints that would reach a position limit within
      ``limit_horizon`` are clamped and the task is re-solved with the others, so the
      redundancy, not the task, absorbs the limit.
    - ``primal_dual``: the seed's network (``primal_dual_velocity``, integrated exactly,
      warm-started from the previous step), failure detection and |W| fallback.
    - ``dls``: damped least squares with a constant damping (the reference).

    Every method's result is finally scaled uniformly into the velocity limits.

    Args:
        method: one of ``METHODS``.
        weights: (n,) diagonal of W (may be indefinite).
        K: the network's penalty gain; network_time: its horizon per step [network s].
        damping: DLS damping and the largest adaptive damping of ``ours``.
        sigma_threshold: smallest singular value below which ``ours`` damps.
    """

    def __init__(
        self,
        method: str,
        weights: npt.ArrayLike,
        K: float = 100.0,
        damping: float = 0.05,
        sigma_threshold: float = 0.05,
        network_time: float = 1e4,
    ) -> None:
        if method not in METHODS:
            raise InvalidInput(
                f'method must be one of {METHODS}, got {method!r}', 'method', method
            )
        weights = np.array(weights, dtype=float)
        if weights.ndim != 1 or not np.all(np.isfinite(weights)) or np.any(weights == 0):
            raise InvalidInput('weights must be finite and non-zero', 'weights', weights)
        self.method, self.weights = method, weights
        self.W = np.diag(weights)
        self.positive_definite = bool(np.all(weights > 0))
        self.K, self.damping, self.sigma_threshold = K, damping, sigma_threshold
        self.network_time = network_time
        # warm start (v, u) of primal_dual
        self._network_state: tuple[FloatArray, FloatArray] | None = None

    def reset(self) -> None:
        self._network_state = None

    def solve(self, J: FloatArray, twist: FloatArray) -> tuple[FloatArray, dict[str, Any]]:
        """qdot (n,) [rad/s] and an info dict ('sigma_min', 'damping', and for
        primal_dual 'null_space_positive', 'min_null_eigenvalue', 'fallback_used',
        'converged', 'gain') for an (m, n) task J, m <= 6."""
        info: dict[str, Any] = {}  # diagnostics: floats, bools
        if self.method == 'dls':
            J6, twist6 = _pad_to_twist(J, twist)
            info['damping'] = self.damping
            return dls_velocity(J6, twist6, self.damping), info
        if self.method == 'primal_dual':
            J6, twist6 = _pad_to_twist(J, twist)
            v0, u0 = self._network_state or (None, None)
            with np.errstate(over='ignore', invalid='ignore'):
                qdot, lam, result = primal_dual_velocity(
                    J6, self.W, twist6, K=self.K, v0=v0, u0=u0, t_final=self.network_time
                )
            info.update(
                null_space_positive=result.null_space_positive,
                min_null_eigenvalue=result.min_null_eigenvalue,
                fallback_used=result.fallback_used,
                converged=result.converged,
                gain=result.gain,
                diverged=False,
            )
            if result.min_h_eigenvalue <= 0 or not np.all(np.isfinite(qdot)):
                # H = W + K J^T J indefinite even at the largest K (near a singularity):
                # the network is unstable and its state blows up. Restart it cold and
                # use the KKT solution for this step.
                info.update(diverged=True, converged=False)
                self._network_state = None
                return self._ours(J, twist, self.weights, {}), info
            self._network_state = (qdot, lam)
            return qdot, info
        return self._ours(J, twist, self.weights, info), info

    def _ours(
        self, J: FloatArray, twist: FloatArray, weights: FloatArray, info: dict[str, Any]
    ) -> FloatArray:
        if np.all(weights > 0):
            W_inverse = np.diag(1.0 / weights)
            damping, sigma_min = adaptive_damping(J, W_inverse, self.sigma_threshold, self.damping)
            info.update(damping=damping, sigma_min=sigma_min)
            return closed_form_velocity(J, W_inverse, twist, damping)
        J6, twist6 = _pad_to_twist(J, twist)
        W = np.diag(weights)
        positive, _ = null_space_positive(J6[: len(J)], W)
        info['null_space_positive'] = positive
        if not positive:
            return self._ours(J, twist, np.abs(weights), info)
        return kkt_velocity(J6, W, twist6)[0]

    def solve_limited(
        self,
        J: FloatArray,
        twist: FloatArray,
        q: FloatArray,
        lower: FloatArray,
        upper: FloatArray,
        velocity_limits: FloatArray,
        limit_horizon: float = 0.1,
        margin: float = 0.02,
    ) -> tuple[FloatArray, dict[str, Any]]:
        """``solve`` within position limits (``ours``: clamp and re-solve; the others:
        uniform scaling) and velocity limits (uniform scaling).

        Args:
            J: (m, n) task Jacobian; twist: (m,); q: (n,) joints [rad];
            lower, upper: (n,) position limits [rad]; velocity_limits: (n,) [rad/s];
            limit_horizon: [s] a joint may move at most to its limit minus ``margin``
                [rad] within this time.

        Returns:
            (qdot, info); info['locked'] counts the clamped joints.
        """
        n = len(q)
        # Position limits as velocity bounds; the velocity limits are applied by scaling.
        high = (upper - margin - q) / limit_horizon
        low = (lower + margin - q) / limit_horizon
        qdot, info = self.solve(J, twist)
        locked = np.zeros(n, dtype=bool)
        if self.method == 'ours':
            for _ in range(n):
                violating = ~locked & ((qdot > high) | (qdot < low))
                if not violating.any() or locked.sum() + violating.sum() >= n:
                    break
                locked |= violating
                fixed = np.clip(qdot, low, high) * locked
                free = ~locked
                qdot = fixed.copy()
                qdot[free] = self._ours(J[:, free], twist - J @ fixed, self.weights[free], {})
        info['locked'] = int(locked.sum())
        # Uniform scaling into the velocity limits keeps the direction of the task
        # velocity; the position bounds are then enforced joint by joint (for ``ours``
        # they are already met, for the others this is the safety net).
        scale = float(np.max(np.abs(qdot) / velocity_limits))
        if scale > 1.0:
            qdot = qdot / scale
        info['scale'] = max(scale, 1.0)
        return np.clip(qdot, np.minimum(low, 0.0), np.maximum(high, 0.0)), info
