"""The navigation filter's read-outs: the posterior as a `NavEstimate`, state copies, counters.

Pose T_ned_body (NED world, body FRD), MAVLink-order pose covariance (x, y, z, roll, pitch, yaw).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from companion.checks import FloatArray
from companion.estimation import model
from companion.estimation.filter_state import _POSE_IX, FilterState
from companion.estimation.types import NavEstimate, NavFilterStats
from companion.geometry import se3


class FilterOutputs(FilterState):
    """`estimate`, `estimate_latest`, state and covariance copies, stamp, source and counters."""

    # ------------------------------------------------------------------ outputs

    def estimate(self) -> NavEstimate:
        """The posterior at the latest applied visual correction (stamp = that frame's capture time).

        Before any visual correction: the current IMU-propagated state with ok False.
        `ok` is also False while the active source is "none" (every visual source
        failed since) or when the position standard deviation exceeds the bound.
        """
        out = self._output
        if out is None:
            est = self.estimate_latest()
            return replace(est, ok=False)
        est = self._make_estimate(out.stamp_s, out.x, out.P_pose, out.P_vel, out.source)
        if self._src.source == "none":
            # Every visual source has failed since: the last correction is not to be trusted as current.
            est = replace(est, ok=False)
        return est

    def estimate_latest(self) -> NavEstimate:
        """The current state, propagated to the latest IMU sample or measurement (whichever is later)."""
        if not self._initialized:
            z3 = np.zeros(3)
            return NavEstimate(
                stamp_s=math.nan, ok=False, T_ned_body=np.eye(4), position_ned_m=z3, velocity_ned_m_s=z3.copy(),
                pose_covariance=np.eye(6) * 1e6, velocity_covariance=np.eye(3) * 1e6,
                reset_counter=self._reset_counter, source="none", gyro_bias_rad_s=z3.copy(),
                accel_bias_m_s2=z3.copy(),
            )
        P = self._P
        return self._make_estimate(self._t, self._x.copy(), P[_POSE_IX].copy(), P[3:6, 3:6].copy(), self._src.source)

    def _make_estimate(
        self, t: float, x: FloatArray, P_pose: FloatArray, P_vel: FloatArray, source: str
    ) -> NavEstimate:
        R = model.rotation(x).copy()
        p = x[model.P_SL].copy()
        pos_std = math.sqrt(max(float(np.max(np.diag(P_pose)[:3])), 0.0))
        ok = source != "none" and pos_std <= self.config.max_position_std_m
        return NavEstimate(
            stamp_s=t,
            ok=ok,
            T_ned_body=se3.make(R, p),
            position_ned_m=p,
            velocity_ned_m_s=x[model.V_SL].copy(),
            pose_covariance=model.pose_covariance_xyz_rpy(R, P_pose),
            velocity_covariance=P_vel,
            reset_counter=self._reset_counter,
            source=source,
            gyro_bias_rad_s=x[model.BG_SL].copy(),
            accel_bias_m_s2=x[model.BA_SL].copy(),
        )

    def error_state_covariance(self) -> FloatArray:
        """A copy of the current (21, 21) error-state covariance (layout in `companion.estimation.model`)."""
        return self._P.copy()

    def nominal_state(self) -> FloatArray:
        """A copy of the current (33,) nominal state vector (layout in `companion.estimation.model`)."""
        return self._x.copy()

    @property
    def stamp_s(self) -> float:
        """Time (s) of the current state."""
        return self._t

    @property
    def reset_counter(self) -> int:
        """Number of pose discontinuities so far (the link wraps it to MAVLink's uint8)."""
        return self._reset_counter

    @property
    def source(self) -> str:
        """The active visual source: "rack", "ground" or "none"."""
        return self._src.source

    @property
    def stats(self) -> NavFilterStats:
        """Counters of IMU samples, measurement outcomes and rejections."""
        return NavFilterStats(
            imu_samples=self._imu_count, counts=dict(self._counts), reset_counter=self._reset_counter,
            source=self._src.source,
        )
