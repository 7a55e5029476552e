"""The rack-end search in the daemon: no along-pipe waypoint while the position along the pipes is a guess.

After an acquisition on the deck the rack tracker's position along the pipes is the configured start's
(docs/acquire.md, "y on the deck"). The mission executor holds `servo` and `gotoxy` actions while
`NavSnapshot.along_pipe_known` is false (`_along_pipe_known`); meanwhile the control task asks
`_along_pipe_goal` for what to fly: the leg of `companion.mission.along_pipe.AlongPipeSearch` toward the
nearest rack end, slowly, at the current height, only while the rack tracker is locked and the safety
manager allows the mission (the goal goes through the same servo law and `SafetyManager.filter` as every
mission goal). The end seen (`rack_end_fix`, vision task): the action goes on with the corrected
estimate. Not seen within the leg, tracker lost, or timed out: the mission is paused (the vehicle holds
in the autopilot's hold mode), the GCS told why; the operator's resume flies on with the start's
along-pipe position (a warning says so), abort ends the mission; a safety hold's automatic resume does
not (the mission is paused again). Every step is in the flight log
(`along-pipe-search`), on the GCS (STATUSTEXT) and, while searching, as NAMED_VALUE_FLOAT `YSEARCH_M`
(distance flown along the leg, m). Config: `mission.along_pipe_search` (on), `..._speed_m_s`, `..._margin_m`.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

import numpy as np

from companion.daemon.state import DaemonState
from companion.errors import MissionError

__all__ = ["AlongPipeTask"]


class AlongPipeTask(DaemonState):
    """The rack-end search leg (see the module docstring); called by the control task."""

    def _along_pipe_known(self) -> bool:
        """`NavSnapshot.along_pipe_known`: false while the along-pipe position is the start's and the search
        is on (and the operator has not chosen to fly on without it after a failed search)."""
        if not bool(self.config.mission.along_pipe_search) or not self.along_pipe_from_start_hint:
            return True
        from companion.mission.along_pipe import SearchState

        search = self._along_pipe_search
        return search is not None and search.state is SearchState.OVERRIDDEN

    def _along_pipe_goal(self, ex: Any, out: Any, snap: Any, now_s: float) -> Any | None:
        """The `Goal` to fly this control step for the search leg, or None (hover, or nothing to do).

        Called every control step while the executor waits for the along-pipe position
        (`out.needs_along_pipe`) or a leg is under way (a pause or a safety hold freezes its clock).
        """
        from companion.mission import Goal, State
        from companion.mission.along_pipe import AlongPipeSearch, SearchLimits, SearchState

        search = self._along_pipe_search
        running = ex.state is State.RUNNING and bool(out.needs_along_pipe)
        if search is None:
            if not running:
                return None
            cfg = self.config.mission
            search = AlongPipeSearch(SearchLimits(speed_m_s=float(cfg.along_pipe_search_speed_m_s),
                                                  margin_m=float(cfg.along_pipe_search_margin_m)))
            self._along_pipe_search = search
        if search.state is SearchState.FAILED and running:
            # resumed by something other than the operator (a safety hold that began before the failure and has
            # cleared): the failure still stands, only the operator may choose to fly on without y
            self._along_pipe_report(search, "along-pipe position still not observed: mission paused again "
                                    "(resume: fly on with the start's along-pipe position; abort: end the mission)",
                                    "warning")
            with contextlib.suppress(MissionError):
                ex.pause(now_s)
            return None
        if search.state in (SearchState.IDLE, SearchState.FOUND) and running:
            if not snap.ok:
                return None  # no fresh pose yet: the control task hovers
            leg = self._along_pipe_leg(np.asarray(snap.T_ned_body))
            step = search.start(now_s, leg, tracker_locked=self._rack_locked())
        elif search.state is SearchState.SEARCHING:
            step = search.step(now_s, np.asarray(snap.T_ned_body), y_known=not self.along_pipe_from_start_hint,
                               tracker_locked=self._rack_locked(),
                               active=running and snap.ok and self._safety_view.allow_mission)
        else:
            return None
        if step.message:
            failed = step.state is SearchState.FAILED
            text = step.message + ("; holding, mission paused (resume: fly on with the start's along-pipe "
                                   "position; abort: end the mission)" if failed else "")
            self._along_pipe_report(search, text, "warning" if failed else "info")
            if failed and ex.state is State.RUNNING:
                with contextlib.suppress(MissionError):
                    ex.pause(now_s)
        if step.state is SearchState.SEARCHING and now_s - self._along_pipe_report_s >= 1.0 and self.link is not None:
            self._along_pipe_report_s = now_s
            with contextlib.suppress(Exception):
                self.link.named_value_float("YSEARCH_M", float(step.flown_m))
        if step.goal is None or not running or out.progress is None:
            return None
        return Goal(T_ned_body_goal=step.goal, max_speed_m_s=search.limits.speed_m_s,
                    threshold_m=search.limits.arrive_m, yaw_threshold_rad=float(np.radians(5.0)),
                    action_index=int(out.progress.index), action_id=f"{out.progress.action_id}:along-pipe-search")

    def _along_pipe_resumed_by_operator(self) -> None:
        """The operator resumed the mission: after a failed search, fly on with the start's y, and say so."""
        from companion.mission.along_pipe import SearchState

        search = self._along_pipe_search
        if search is not None and search.state is SearchState.FAILED:
            search.override()
            self._along_pipe_report(search, "operator resumed: flying on with the configured start's along-pipe "
                                    "position (waypoints off by its error)", "warning")

    def _rack_locked(self) -> bool:
        """The rack tracker is locked (a good pose since its last restart, not lost for `lost_frames`)."""
        acq = None if self.pipeline is None else self.pipeline.acquirer
        return acq is not None and bool(acq.locked) and not bool(acq.acquiring)

    def _along_pipe_leg(self, T_ned_body: Any) -> Any:
        """The leg from the body pose estimate `T_ned_body` (NED), covering the acquisition's along-pipe std."""
        from companion.mission.along_pipe import plan_leg

        assert self.pipeline is not None and self.pipeline.acquirer is not None and self.camera_model is not None
        y_std_m = float(self.pipeline.acquirer.last_y_std_m)
        model = self.pipeline.acquirer.model
        limb_z_m = float(np.mean(model.radii))  # the limbs seen from above lie near the pipes' axes
        search = self._along_pipe_search
        assert search is not None
        return plan_leg(T_ned_body, self.T_ned_rack, self.T_body_cam, self.camera_model, float(model.length),
                        limb_z_m, y_std_m, search.limits)

    def _along_pipe_report(self, search: Any, text: str, severity: str) -> None:
        """One search event to the flight log and the GCS."""
        leg = search.leg
        fields: dict[str, Any] = {"state": str(search.state), "flown_m": round(float(search.flown_m), 3)}
        if leg is not None:
            fields.update(end_y_m=leg.end_y_m, leg_m=round(leg.length_m, 3), reach_m=round(leg.reach_m, 3),
                          y_std_m=round(leg.y_std_m, 3), y_start_m=round(leg.y_start_m, 3))
        self._event("along-pipe-search", level=logging.WARNING if severity == "warning" else logging.INFO,
                    message=text, **fields)
        self._gcs_text(text, severity)
