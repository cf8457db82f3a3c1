"""Redundant inverse kinematics of the PA-10 at the velocity level (ALGORITHMS.md §6.5):
ours (``closed_form_velocity`` with ``adaptive_damping``), damped least squares as the
reference (``dls_velocity``), and ``RateSolver``, which runs the ``method`` a node asks for
(the thesis's network is in ``thesis``; the problem and its KKT solution in ``problem``);
the task-space errors the solvers are given (``pose_error``, ``tilt_error``) and the
spin-free task (``spin_free_task``). No ROS here.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from pa10_ik_node.problem import TWIST_DIM, check_problem, kkt_velocity, null_space_positive
from pa10_ik_node.thesis import primal_dual_velocity
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray


def dls_velocity(J: npt.ArrayLike, twist: npt.ArrayLike, damping: float) -> FloatArray:
    """Damped least squares: qdot = J^T (J J^T + damping^2 I)^-1 twist.

    Args:
        J: (6, n) Jacobian; twist: (6,) [m/s, rad/s]; damping: lambda (>= 0).

    Returns:
        qdot (n,) [rad/s]. With ``damping`` 0 and a full-rank J this is the pseudo-inverse
        (minimum-norm) solution.
    """
    J, twist = check_problem(J, rdot_d=twist)
    if not damping >= 0:
        raise InvalidInput(f'damping must be >= 0, got {damping}', 'damping', damping)
    gram = J @ J.T + damping**2 * np.eye(TWIST_DIM)
    return J.T @ np.linalg.solve(gram, twist)


ORTHONORMAL_TOLERANCE = 1e-9  # |R R^T - I| below this: a rotation as it is


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
    # Rotations as forward kinematics and checked waypoints give them skip scipy's
    # orthogonalisation (the same result on them, a quarter of a control step saved).
    orthonormal = bool(np.abs(R_error @ R_error.T - np.eye(3)).max() < ORTHONORMAL_TOLERANCE)
    orientation_error = Rotation.from_matrix(R_error, assume_valid=orthonormal).as_rotvec()
    return np.concatenate([position_error, orientation_error])


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a x b of two (3,) vectors: np.cross's products and differences (the same bits)
    without its axis handling, which took a sixth of a control step."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def spin_free_task(
    J: FloatArray, twist: FloatArray, T_desired: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The 5 constraints that leave the spin about the desired approach axis free.

    The angular rows are expressed in the desired frame's (x, y, z) and the z row is
    dropped. Returns (J (5, n), twist (5,)).
    """
    R = T_desired[:3, :3]
    J5 = np.vstack([J[:3], R[:, :2].T @ J[3:]])
    return J5, np.concatenate([twist[:3], R[:, :2].T @ twist[3:]])


def tilt_error(R_current: FloatArray, approach_desired: FloatArray) -> FloatArray:
    """Rotation vector (3,) [rad] turning the tool's z axis onto ``approach_desired``."""
    z = R_current[:, 2]
    axis = cross(z, approach_desired)
    norm = np.linalg.norm(axis)
    angle = np.arctan2(norm, np.dot(z, approach_desired))
    if norm < 1e-12:
        return np.zeros(3) if angle < 1.0 else R_current[:, 0] * np.pi
    return axis / norm * angle


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
        """Forget the primal_dual network's warm start: the next solve starts it cold."""
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
