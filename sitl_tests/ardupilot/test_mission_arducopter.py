"""The packaged paper_sweep mission flown by the daemon on the real ArduCopter SITL.

One flight checks, on what ArduPilot itself reports: the EKF origin is set and HOME_POSITION
follows; ArduPilot's EKF uses the external navigation; the daemon arms through its take-off gate
once ArduPilot's pre-arm checks pass, takes off in GUIDED, flies every waypoint within 10 cm of
the SITL's truth (SIM_STATE), lands in LAND and ArduPilot disarms.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import numpy as np

from companion.config import mission_limits
from companion.data import data_path
from companion.mission import State, load_mission
from sitl_tests.ardupilot.harness import sitl_rig

EKF_POS_HORIZ_REL = 8
EKF_POS_HORIZ_ABS = 16
EKF_CONST_POS_MODE = 128


async def test_paper_sweep_on_arducopter(sitl_available: Path, tmp_path: Path) -> None:
    async with sitl_rig(tmp_path) as rig:
        d, ob = rig.daemon, rig.observer
        t0 = time.monotonic()
        await rig.wait_until(lambda: d.counters.poses_sent >= 10, 20.0, "vision poses flowing")
        link = d.link
        assert link is not None
        await rig.wait_until(lambda: link.state.ekf_origin_set, 10.0, "GPS_GLOBAL_ORIGIN confirming the origin")
        await rig.wait_until(lambda: link.state.home_position_stamp_s is not None, 10.0, "HOME_POSITION")
        rig.say(f"origin confirmed and HOME_POSITION received {time.monotonic() - t0:.1f} s after start")

        estimates: list[tuple[float, np.ndarray]] = []  # (stamp of the pose the frame was rendered from, nav)

        def on_frame(fr: object) -> None:
            nav = getattr(fr, "nav", None)
            stamp = getattr(fr, "source_stamp_s", None)
            if nav is not None and bool(nav.ok) and stamp is not None and ob.armed:
                estimates.append((float(stamp), np.asarray(nav.position_ned_m, dtype=float).copy()))

        d.frame_observers.append(on_frame)
        mission = load_mission(data_path("missions/paper_sweep.xml"), limits=mission_limits(rig.config))
        await d.start_mission(mission, "paper_sweep")  # the take-off gate waits for ArduPilot's pre-arm checks
        ex = d.executor
        assert ex is not None
        waypoint_errors: list[tuple[str, float]] = []
        lp_errors: list[float] = []
        vision_errors: list[float] = []
        seen = 0
        t_mission = time.monotonic()
        t_armed: float | None = None
        while ex.state not in (State.COMPLETED, State.FAILED, State.ABORTED):
            await asyncio.sleep(0.1)
            assert time.monotonic() - t_mission < 300.0, f"mission still {ex.state} after 300 s"
            if t_armed is None and ob.armed:
                t_armed = time.monotonic() - t_mission
            for r in ex.results[seen:]:
                if r.result == "succeeded" and r.T_ned_body_goal is not None and r.action in (
                        "takeoff", "gotoxy", "gotoz", "servo", "home"):
                    # the truth when the daemon declared the waypoint reached (its clock is time.monotonic, the
                    # observer's too), not when this loop noticed: the next action may already move the vehicle
                    t_truth, p_truth = ob.truth_track(r.ended_s - 1.0)
                    truth = np.array([np.interp(r.ended_s, t_truth, p_truth[:, k]) for k in range(3)])
                    err = float(np.linalg.norm(truth - np.asarray(r.T_ned_body_goal)[:3, 3]))
                    waypoint_errors.append((r.action_id, err))
            seen = len(ex.results)
        texts = ob.statustexts()
        failed = [(r.action_id, r.result, r.message) for r in ex.results if r.result != "succeeded"]
        assert ex.state is State.COMPLETED, f"mission {ex.state}: {failed}; autopilot said {texts[-8:]}"
        assert any("using external nav" in t for t in texts), texts
        ekf = ob.latest("EKF_STATUS_REPORT")
        assert ekf is not None
        flags = int(ekf.fields["flags"])
        rig.say(f"EKF_STATUS_REPORT flags {flags} at the end")
        await rig.wait_until(lambda: not ob.armed, 20.0, "ArduPilot disarming after LAND")
        modes = [m.fields["custom_mode"] for m in ob.messages("HEARTBEAT")]
        assert 4 in modes and 9 in modes  # GUIDED, then LAND

        t_truth, p_truth = ob.truth_track()
        for stamp, p in estimates:
            if t_truth[0] <= stamp <= t_truth[-1]:
                q = np.array([np.interp(stamp, t_truth, p_truth[:, k]) for k in range(3)])
                if -q[2] > 0.5:  # airborne
                    vision_errors.append(float(np.linalg.norm(p - q)))
        # ArduPilot's own estimate against the truth at the same arrival time (both streams come from it)
        for lp in ob.messages("LOCAL_POSITION_NED", t_mission):
            if t_truth[0] <= lp.time_s <= t_truth[-1]:
                q = np.array([np.interp(lp.time_s, t_truth, p_truth[:, k]) for k in range(3)])
                if -q[2] > 0.5:
                    lp_errors.append(float(np.hypot(lp.fields["x"] - q[0], lp.fields["y"] - q[1])))
        worst = max(e for _, e in waypoint_errors)
        figures = {
            "armed_after_s": None if t_armed is None else round(t_armed, 1),
            "mission_s": round(time.monotonic() - t_mission, 1),
            "actions": len(ex.results),
            "waypoints": len(waypoint_errors),
            "waypoint_error_max_m": round(worst, 4),
            "waypoint_errors_m": {k: round(v, 4) for k, v in waypoint_errors},
            "vision_vs_truth_rms_m": round(float(np.sqrt(np.mean(np.square(vision_errors)))), 4),
            "vision_vs_truth_max_m": round(float(np.max(vision_errors)), 4),
            "local_position_ned_vs_truth_horizontal_rms_m": round(float(np.sqrt(np.mean(np.square(lp_errors)))), 4),
            "poses_sent": d.counters.poses_sent,
        }
        rig.say("paper_sweep on ArduCopter: " + json.dumps(figures))
        assert len(waypoint_errors) >= 10
        # #17's bar: every waypoint within 10 cm of the truth. p1-end (pipe 1, y = 8.5 m, past the crossing pipe)
        # was 7.7-11.2 cm with the tracker's texture weight 20 (texture points anchored with the pose error
        # they were born with); with 2 it measures 3.6 cm (docs/rack.md).
        assert worst <= 0.10, waypoint_errors
