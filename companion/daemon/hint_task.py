"""The daemon's side of the start-hint lock check (`companion.daemon.hint_check`, docs/acquire.md).

While the rack tracker's lock comes from the configured start (a hint) and has not been checked against the image,
the vision task asks here for the prior of a check (disarmed on the deck only: the prior is then independent of the
lock being checked -- the configured start's height, along-pipe position and heading, never the filter's estimate,
which the lock itself feeds), reports each check (flight log `rack-hint-check`, STATUSTEXT, the status), and, with
``vision.rack_verify_start = "withhold"`` (the default), holds back the rack poses of an unverified lock while the
vehicle is disarmed: ArduPilot then does not arm on them (a safe refusal). "report" sends them and says they are
unverified; "off" does not check (the behaviour before issue #16's check).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from companion.daemon.state import DaemonState

__all__ = ["HintCheckTask"]

UNVERIFIED_TEXT_EVERY_S = 10.0  # at most one "not verified" STATUSTEXT per this many seconds (clock s)


class HintCheckTask(DaemonState):
    """Prior, reports and pose gate of the start-hint lock check (see the module docstring)."""

    _last_hint_text_s = float("-inf")
    _hint_armed_warned = False

    def _hint_checker(self) -> Any | None:
        return None if self.pipeline is None else self.pipeline.hint_checker

    def _disarmed(self) -> bool:
        state = self.link.state if self.link is not None else None
        return state is not None and not bool(state.armed)

    def _hint_check_inputs(self, roll_rad: float, pitch_rad: float) -> Any | None:
        """`AcquisitionInputs` for a check of the start-hint lock when one is due (locked, disarmed), else None."""
        checker = self._hint_checker()
        acq = None if self.pipeline is None else self.pipeline.acquirer
        if checker is None or acq is None or not checker.due or not acq.locked or not self._disarmed():
            return None
        from companion.daemon.acquisition import AcquisitionInputs

        hint = self.options.initial_T_ned_body
        T_start = np.eye(4) if hint is None else np.asarray(hint, dtype=np.float64)
        # on the deck the camera is where the configured start puts the deck (3 cm: surveyed); the autopilot's
        # own height may already carry the lock's error (it fuses the poses), so it is not used here
        z_cam_ned_m = float(T_start[2, 3]) + float(self.T_body_cam[2, 3])
        height_m = float(self.T_ned_rack[2, 3]) - z_cam_ned_m
        return AcquisitionInputs(roll_rad=roll_rad, pitch_rad=pitch_rad, height_above_rack_m=height_m,
                                 height_std_m=0.03, T_ned_body_hint=T_start, y_std_m=1.0, from_start_hint=True)

    def rack_lock_state(self) -> str:
        """How the rack tracker's lock was established: "verified" (the start-hint lock agreed with the image),
        "re-acquired" (it did not: moved to the acquired pose), "acquired" (found in the image), "unverified"
        (from the start hint, not checked yet), "unchecked" (checks off)."""
        checker = self._hint_checker()
        return "unchecked" if checker is None else str(checker.verdict)

    def _withhold_unverified(self, nav: Any) -> bool:
        """True when this pose must not go to the autopilot: it comes from the rack tracker's unverified start-hint
        lock, the vehicle is disarmed and ``vision.rack_verify_start`` is "withhold"."""
        checker = self._hint_checker()
        return (checker is not None and checker.pending and str(nav.source) == "rack" and self._disarmed()
                and str(self.config.vision.rack_verify_start) == "withhold")

    def _report_hint_check(self, m: Any) -> None:
        """One check of the start-hint lock to the flight log and the GCS."""
        check = m.hint_check
        fields = {"outcome": check.outcome, "dx_m": round(check.dx_m, 3), "dz_m": round(check.dz_m, 3),
                  "dyaw_deg": round(math.degrees(check.dyaw_rad), 2), "limit_x_m": round(check.limit_x_m, 3),
                  "limit_z_m": round(check.limit_z_m, 3), "limit_yaw_deg": round(math.degrees(check.limit_yaw_rad), 2),
                  "status": check.status}
        self._event("rack-hint-check", level=logging.INFO if check.outcome != "re-acquire" else logging.WARNING,
                    **fields)
        diff = (f"across {100.0 * check.dx_m:+.1f} cm, height {100.0 * check.dz_m:+.1f} cm, "
                f"heading {math.degrees(check.dyaw_rad):+.1f} deg")
        if check.outcome == "agrees":
            self._gcs_text(f"rack lock from the start verified ({diff})", "info")
        elif check.outcome == "re-acquire":
            res = None if self.pipeline is None or self.pipeline.acquirer is None else self.pipeline.acquirer.last
            pipes = [] if res is None or res.best is None else list(res.best.pipes)
            self._event("rack-acquired", level=logging.WARNING, reason="hint lock one pipe off: re-acquired",
                        pipes=pipes, **{k: fields[k] for k in ("dx_m", "dz_m", "dyaw_deg")})
            self._gcs_text(f"hint lock one pipe off: re-acquired ({diff})", "warning")
        elif check.outcome == "disagrees":
            self._gcs_text(f"rack lock from the start disagrees with the image ({diff}): checking again", "warning")
        else:
            now = self.clock.now()
            if now - self._last_hint_text_s >= UNVERIFIED_TEXT_EVERY_S:
                self._last_hint_text_s = now
                withhold = str(self.config.vision.rack_verify_start) == "withhold"
                then = "rack poses withheld, no arming" if withhold else "rack poses sent unverified"
                self._gcs_text(f"rack lock from the start not verified ({check.status or 'no confident pose'}): "
                               f"{then}", "warning")

    def _hint_lock_update(self) -> None:
        """After each frame: mirror `rack_lock_state` for the status; once, a warning when armed while the rack
        lock is still the start hint's (the checks need the deck prior: they stop)."""
        self.rack_lock = self.rack_lock_state()
        checker = self._hint_checker()
        if checker is None or not checker.pending or self._hint_armed_warned or self._disarmed() or self.link is None:
            return
        self._hint_armed_warned = True
        self._event("rack-hint-unverified-armed", level=logging.WARNING)
        self._gcs_text("armed with the rack lock from the start hint unverified", "warning")
