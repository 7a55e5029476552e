"""The navigation filter's EKF correction: the gated Kalman update, the pose reset and the clone reset.

Error state (21,) of `companion.estimation.model`: dp NED (m), dtheta body (rad, right perturbation).
"""

from __future__ import annotations

import math

import numpy as np

from companion.checks import FloatArray
from companion.estimation import model
from companion.estimation.filter_state import _POSE_IX, FilterState, _Output


class FilterCorrection(FilterState):
    """Kalman update, resets of the pose and of the clone, and the record of the corrected posterior."""

    def _kalman(self, r: FloatArray, H: FloatArray, R_noise: FloatArray, gate: float) -> str:
        P = self._P
        PHt = P @ H.T
        S = H @ PHt + R_noise
        try:
            S_inv = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return "invalid"
        d2 = float(r @ S_inv @ r)
        if not math.isfinite(d2) or d2 < 0.0:
            return "invalid"
        if d2 > gate:
            return "gated"
        K = PHt @ S_inv
        # P - K S K^T (= the Joseph form for the optimal gain), symmetrized.
        P_new = P - K @ PHt.T
        self._P = 0.5 * (P_new + P_new.T)
        model.inject_in_place(self._x, K @ r)
        return "applied"

    def _reset_pose(self, R_m: FloatArray, p_m: FloatArray, cov_body: FloatArray) -> None:
        """Move the pose to a disagreeing measurement (a discontinuity).

        First updates (attitude, then position) with the pose prior inflated along
        the disagreement (`_disagreement_inflation`): the pose jumps to the
        measurement along the axes it measures precisely and keeps its prior
        along axes it barely measures (e.g. along the pipes). If the result still disagrees with the measurement
        beyond its own covariance (large rotations: the update is too nonlinear),
        the pose is set to the measurement and its covariance block replaced.
        """
        # Attitude first (so the position residual is then expressed in the right body frame), then position.
        r, H = model.absolute_pose_residual(self._x, R_m, p_m)
        P = self._P.copy()
        P[6:9, 6:9] += self._disagreement_inflation(r[3:], cov_body[3:, 3:])
        self._P = P
        status = self._kalman(r[3:], H[3:], cov_body[3:, 3:], math.inf)
        if status == "applied":
            r, H = model.absolute_pose_residual(self._x, R_m, p_m)
            R = model.rotation(self._x)
            P = self._P.copy()
            P[0:3, 0:3] += self._disagreement_inflation(R @ r[:3], R @ cov_body[:3, :3] @ R.T)
            self._P = P
            status = self._kalman(r[:3], H[:3], cov_body[:3, :3], math.inf)
        if status == "applied":
            r_after, _ = model.absolute_pose_residual(self._x, R_m, p_m)
            try:
                d2 = float(r_after @ np.linalg.solve(cov_body, r_after))
            except np.linalg.LinAlgError:
                d2 = math.inf
            if d2 <= self._gate[6]:
                self._reset_clone()
                return
        self._x[model.P_SL] = p_m
        self._x[model.R_SL] = R_m.ravel()
        P = self._P.copy()
        P[model.POSE_IDX, :] = 0.0
        P[:, model.POSE_IDX] = 0.0
        P[_POSE_IX] = model.body_to_error_pose_covariance(R_m, cov_body)
        self._P = P
        self._reset_clone()

    def _disagreement_inflation(self, e: FloatArray, C: FloatArray) -> FloatArray:
        """Rank-1 prior inflation e_s e_s^T for a reset (3x3).

        e_s is the disagreement `e` projected on the eigenvectors of the
        measurement covariance C that measure precisely compared with |e|
        (gate * eigenvalue < |e|^2): the pose may jump along e_s, not along axes
        the measurement barely constrains.
        """
        w, U = np.linalg.eigh(C)
        precise = self._gate[1] * np.maximum(w, 0.0) < float(e @ e)
        U_s = U[:, precise]
        e_s = U_s @ (U_s.T @ e)
        Q: FloatArray = np.outer(e_s, e_s)
        return Q

    def _reset_clone(self) -> None:
        self._x[model.PC_SL] = self._x[model.P_SL]
        self._x[model.RC_SL] = self._x[model.R_SL]
        self._reset_clone_covariance()

    def _reset_clone_covariance(self) -> None:
        P = self._P.copy()
        P[15:21, :] = P[model.POSE_IDX, :]
        P[:, 15:21] = P[:, model.POSE_IDX]
        self._P = P

    def _record_output(self, t: float) -> None:
        P = self._P
        self._output = _Output(t, self._x.copy(), P[_POSE_IX].copy(), P[3:6, 3:6].copy(), self._src.source)
