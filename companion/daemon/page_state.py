"""What the web status page shows, as one JSON-serializable dict (`page_state()`).

`status()` (health.py) plus: vehicle details (height, EKF flags), the fused pose and the trajectory so far
in the rack frame (x across the pipes, y along them, m), the rack's outline (each pipe as a segment with
its radius), the mission's steps with their results, the safety events, the last log lines (the daemon's
events) and where the video goes. The trajectory keeps one point per `TRAJECTORY_PERIOD_S` of frames,
at most `TRAJECTORY_POINTS` (older points are thinned out, the whole flight stays visible).
"""

from __future__ import annotations

import collections
import json
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.daemon.state import DaemonState, FrameRecord
from companion.geometry import frames, se3

__all__ = ["PageState"]

TRAJECTORY_PERIOD_S = 0.2
TRAJECTORY_POINTS = 2000
LOG_LINES = 40
# ArduPilot/PX4 EKF_STATUS_REPORT flags (MAVLink ESTIMATOR_STATUS_FLAGS), for people
_EKF_FLAGS = ("attitude", "velocity_horiz", "velocity_vert", "pos_horiz_rel", "pos_horiz_abs", "pos_vert_abs",
              "pos_vert_agl", "const_pos_mode", "pred_pos_horiz_rel", "pred_pos_horiz_abs", "uninitialized",
              "accel_error", "gps_glitch")


class PageState(DaemonState):
    """Records the trajectory and the log lines; builds the page's state."""

    _page_trajectory: list[tuple[float, float, float]] | None = None
    _page_last_traj_s: float = -math.inf
    _page_log: collections.deque[str] | None = None

    if TYPE_CHECKING:
        def status(self) -> dict[str, Any]: ...  # health

    def _open_page_state(self) -> None:
        self._page_trajectory = []
        self._page_log = collections.deque(maxlen=LOG_LINES)
        self.frame_observers.append(self._page_on_frame)
        self.event_observers.append(self._page_on_event)

    def _page_on_frame(self, record: FrameRecord) -> None:
        traj = self._page_trajectory
        nav = record.nav
        if traj is None or nav is None or not bool(nav.ok) or record.capture_s - self._page_last_traj_s < \
                TRAJECTORY_PERIOD_S:
            return
        self._page_last_traj_s = record.capture_s
        p_rack = se3.act(se3.inverse(self.T_ned_rack), np.asarray(nav.position_ned_m, dtype=np.float64))
        traj.append((round(float(p_rack[0]), 3), round(float(p_rack[1]), 3), round(float(p_rack[2]), 3)))
        if len(traj) > TRAJECTORY_POINTS:
            del traj[1::2]  # thin out, keep the whole flight

    def _page_on_event(self, name: str, fields: dict[str, Any]) -> None:
        log = self._page_log
        if log is None or name in ("health",):
            return
        text = " ".join(f"{k}={_short(v)}" for k, v in fields.items())
        log.append(f"{time.strftime('%H:%M:%S')} {name} {text}"[:240])

    def page_state(self) -> dict[str, Any]:
        """The status page's JSON (see the module docstring)."""
        out = self.status()
        link = self.link
        state = link.state if link is not None else None
        flags = None if state is None else state.ekf_flags
        out["vehicle"] = {
            "mode": None if state is None else state.mode,
            "armed": None if state is None else bool(state.armed),
            "battery_v": None if state is None or state.battery_voltage_v is None
            else round(float(state.battery_voltage_v), 2),
            "battery_pct": None if state is None else state.battery_remaining_pct,
            "height_m": None if state is None or state.position_ned_m is None
            else round(-float(state.position_ned_m[2]), 2),
            "rangefinder_m": None if state is None or state.rangefinder_m is None
            else round(float(state.rangefinder_m), 2),
            "ekf_flags": flags,
            "ekf": [] if flags is None else [n for k, n in enumerate(_EKF_FLAGS) if int(flags) >> k & 1],
            "landed_state": None if state is None else state.landed_state,
        }
        out["pose"] = self._page_pose()
        out["trajectory_rack_m"] = list(self._page_trajectory or [])
        out["rack"] = self._page_rack()
        out["mission_steps"] = self._page_steps()
        out["safety"]["faults"] = [{k: _short(v) for k, v in ev.items()} for ev in self._safety_view.events[-12:]]
        out["log"] = list(self._page_log or [])
        streamer = getattr(self, "video_streamer", None)
        video: dict[str, Any] = {"enabled": streamer is not None}
        if streamer is not None:
            st = streamer.stats()
            host, port = streamer.destination
            video.update(destination=f"udp://{host}:{port}", size=list(streamer.size), encoded=st.encoded,
                         dropped=st.dropped + st.rate_skipped, sdp=str(getattr(self, "video_sdp_path", "") or ""))
        out["video"] = video
        plain: dict[str, Any] = json.loads(json.dumps(out, default=str))  # plain JSON types only
        return plain

    def _page_pose(self) -> dict[str, Any] | None:
        nav = self.last_nav
        if nav is None:
            return None
        T_ned_body = np.asarray(nav.T_ned_body, dtype=np.float64)
        T_rack_body = se3.inverse(self.T_ned_rack) @ T_ned_body
        x_rack = T_rack_body[:3, 0]  # the nose in the rack frame
        return {
            "ok": bool(nav.ok),
            "source": str(nav.source),
            "ned_m": [round(float(v), 3) for v in T_ned_body[:3, 3]],
            "yaw_deg": round(math.degrees(float(frames.yaw_from_rotation(T_ned_body[:3, :3]))), 1),
            "rack_m": [round(float(v), 3) for v in T_rack_body[:3, 3]],
            "heading_rack_rad": round(math.atan2(float(x_rack[1]), float(x_rack[0])), 3),
        }

    def _page_rack(self) -> list[dict[str, Any]]:
        model = getattr(self, "_video_model", None)
        if model is None and self.pipeline is not None and self.pipeline.rack_tracker is not None:
            model = self.pipeline.rack_tracker.model
        if model is None:
            return []
        pipes = model.pipe_arrays()
        out = []
        for start, d, r, length in zip(pipes.starts, pipes.directions, pipes.radii, pipes.lengths, strict=True):
            end = start + float(length) * d
            out.append({"start": [round(float(v), 3) for v in start[:2]], "end": [round(float(v), 3) for v in end[:2]],
                        "radius": round(float(r), 3)})
        return out

    def _page_steps(self) -> list[dict[str, Any]]:
        ex = self.executor
        if ex is None:
            return []
        results = {r.index: r for r in ex.results}
        active = self._mission_active()
        steps = []
        for i, a in enumerate(ex.mission.actions):
            r = results.get(i)
            status = r.result if r is not None else ("active" if active and i == len(ex.results) else "pending")
            steps.append({"index": i, "action": str(getattr(a, "tag", type(a).__name__.lower())), "id": a.id,
                          "status": status, "seconds": None if r is None else round(float(r.seconds), 1)})
        return steps


def _short(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 3)
    if isinstance(value, int | bool | str) or value is None:
        return value if not isinstance(value, str) else value[:120]
    return str(value)[:120]
