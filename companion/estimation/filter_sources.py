"""The navigation filter's visual source selection and the update of each source (rack, ground, range).

Rack: absolute pose T_ned_body; ground: planar NED increment between the clone and now; range: slant
height (m) over flat ground. Stamps in s.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from companion.checks import FloatArray
from companion.estimation import model
from companion.estimation.filter_correction import FilterCorrection
from companion.estimation.filter_state import _Measurement, _SourceState

_CLONE_STAMP_TOL_S = 1e-3


class FilterSources(FilterCorrection):
    """Source selection (switch in / out, re-acquisition, resets) and the measurement update of each source."""

    def _apply_rack(self, m: _Measurement) -> str:
        cfg = self.config
        st = self._src
        t = m.stamp_s
        if not m.ok:
            st = replace(st, rack_good=0, rack_bad=st.rack_bad + 1, rack_unsettled=0)
            if st.source == "rack" and st.rack_bad >= cfg.rack_failures_to_switch_out:
                st = self._switch_away_from_rack(st, t)
            self._src = st
            return "failed"
        R_m, p_m, cov, forced = m.data
        r, H = model.absolute_pose_residual(self._x, R_m, p_m)
        good = st.rack_good + 1
        # Back after a silence longer than the timeout, or a pose found independently of the estimate:
        # re-acquire like a switch (a reset if it disagrees).
        reacquire = (st.source == "rack" and t - st.last_rack_ok_s > cfg.source_timeout_s) or forced
        if (st.source != "rack" or reacquire) and st.rack_unsettled < cfg.rack_unsettled_frames_max:
            if not self._tilt_agrees(r, H, cov):
                # Roll and pitch are held by gravity through any vision outage; a tracker that disagrees
                # with them is still settling (e.g. re-locking at the rack's end): not healthy yet, no reset.
                self._src = replace(st, rack_good=0, rack_bad=0, rack_unsettled=st.rack_unsettled + 1)
                return "unsettled"
            st = replace(st, rack_unsettled=0)
        if st.source == "rack" and not reacquire:
            status = self._kalman(r, H, cov, self._gate[6])
            if status == "applied":
                self._src = replace(st, rack_good=good, rack_bad=0, last_rack_ok_s=t)
                self._record_output(t)
                return status
            st = replace(st, rack_good=0, rack_bad=st.rack_bad + 1)
            if st.rack_bad >= cfg.rack_failures_to_switch_out:
                st = self._switch_away_from_rack(st, t)
            self._src = st
            return status
        if good < cfg.rack_frames_to_switch_in and not reacquire:
            self._src = replace(st, rack_good=good, rack_bad=0)
            return "standby"
        # Switch to the rack: a smooth correction when it agrees with the estimate, a reset otherwise.
        p_before = self._x[model.P_SL].copy()
        R_before = model.rotation(self._x).copy()
        status = self._kalman(r, H, cov, self._gate[6])
        if status != "applied":
            self._reset_pose(R_m, p_m, cov)
            status = "reset"
        elif self._moved(p_before, R_before):
            # Consistent with the (loose) prior, but the estimate jumps: a discontinuity for the autopilot.
            status = "reset"
        if status == "reset" and not m.reset_counted:
            m.reset_counted = True
            self._reset_counter += 1
        self._src = replace(st, source="rack", rack_good=good, rack_bad=0, rack_unsettled=0, last_rack_ok_s=t)
        self._record_output(t)
        return status

    def _tilt_agrees(self, r: FloatArray, H: FloatArray, cov_body: FloatArray) -> bool:
        """Whether the roll/pitch part of an absolute pose residual passes the (2-dof) gate.

        The attitude residual (body frame) is split into the rotation about gravity (yaw, which the
        IMU does not hold) and the two tilt components perpendicular to it.
        """
        u = model.rotation(self._x).T @ np.array([0.0, 0.0, 1.0])  # NED down in the body frame
        a = np.array([1.0, 0.0, 0.0]) if abs(float(u[0])) < 0.9 else np.array([0.0, 1.0, 0.0])
        b1 = np.cross(u, a)
        b1 /= np.linalg.norm(b1)
        B = np.stack([b1, np.cross(u, b1)])
        H_th = H[3:6]
        S = B @ (H_th @ self._P @ H_th.T + cov_body[3:, 3:]) @ B.T
        r_t = B @ r[3:]
        try:
            d2 = float(r_t @ np.linalg.solve(S, r_t))
        except np.linalg.LinAlgError:
            return False
        return math.isfinite(d2) and d2 <= self._gate[2]

    def _moved(self, p_before: FloatArray, R_before: FloatArray) -> bool:
        """Whether the pose moved by more than the configured switch-reset step since (p_before, R_before)."""
        cfg = self.config
        dp = float(np.linalg.norm(self._x[model.P_SL] - p_before))
        c = 0.5 * (float(np.trace(R_before.T @ model.rotation(self._x))) - 1.0)
        dtheta = math.acos(min(1.0, max(-1.0, c)))
        return dp > cfg.switch_reset_position_m or dtheta > cfg.switch_reset_angle_rad

    def _switch_away_from_rack(self, st: _SourceState, t: float) -> _SourceState:
        ground_ok = st.ground_bad == 0 and t - st.last_ground_ok_s <= self.config.source_timeout_s
        return replace(st, source="ground" if ground_ok else "none", rack_good=0, rack_bad=0)

    def _apply_ground(self, m: _Measurement) -> str:
        cfg = self.config
        st = self._src
        t = m.stamp_s
        if not m.ok:
            st = replace(st, ground_bad=st.ground_bad + 1, clone_valid=True, clone_stamp_s=t)
            if st.source == "ground" and st.ground_bad >= cfg.ground_failures_to_switch_out:
                st = replace(st, source="none")
            self._src = st
            self._reset_clone()
            return "failed"
        dx_m, dy_m, dyaw_rad, cov, restart, ref = m.data
        st = replace(st, ground_bad=0, last_ground_ok_s=t)
        if st.source == "rack" and t - st.last_rack_ok_s > cfg.source_timeout_s:
            st = replace(st, source="ground", rack_good=0, rack_bad=0)
        elif st.source == "none":
            st = replace(st, source="ground")
        outcome = "standby"
        if st.source == "ground":
            if not st.clone_valid or restart:
                outcome = "anchor"
            elif not (math.isnan(ref) or abs(ref - st.clone_stamp_s) <= _CLONE_STAMP_TOL_S):
                outcome = "unanchored"
            else:
                r, H = model.relative_pose_residual(self._x, dx_m, dy_m, dyaw_rad)
                outcome = self._kalman(r, H, cov, self._gate[3])
                if outcome == "applied":
                    self._src = st
                    self._record_output(t)
        self._src = replace(st, clone_valid=True, clone_stamp_s=t)
        self._reset_clone()
        return outcome

    def _apply_range(self, m: _Measurement) -> str:
        r, H = model.range_residual(self._x, m.data[0], self.config.ground_z_ned_m)
        return self._kalman(r, H, np.array([[self.config.range_std_m**2]]), self._gate[1])
