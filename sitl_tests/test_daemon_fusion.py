"""The navigation filter inside the daemon, in the simulator (issue 8 acceptance).

- vision dropped for 1 s mid-flight: the IMU-propagated fused position stays within 10 cm of the
  truth at the end of the gap, and fused poses flow again within 0.5 s after the frames return.
- rack tracker -> ground odometer -> rack tracker in flight (vision "auto"): the vehicle flies along
  the rack, off its north end (the pipes leave the view, the rack tracker fails, the ground odometer
  carries the estimate over the bare ground) and back over the rack (the tracker, re-initialised from
  the fused estimate, re-acquires it). At each switch the step of the pose stream the autopilot
  receives is no larger than the two sources' disagreement (plus an ordinary frame's correction), a
  step larger than the filter's switch-reset threshold comes with a reset_counter increment in
  VISION_POSITION_ESTIMATE (and nothing else does), and the mission completes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.daemon.app import FrameRecord
from companion.geometry import so3
from companion.mission import State
from companion.sim.autopilot import FakeAutopilotConfig, FlightParams
from sitl_tests.daemon_harness import mission, rig

# The fake's own EKF failsafe must not end the flight during the 1 s gap (this tests the filter).
TOLERANT = FlightParams(takeoff_speed_m_s=0.5, vision_failsafe_s=3.0)
NO_HOVER = {"vision_loss_hover_ms": 2500}


async def test_vision_gap_of_1s_mid_flight(tmp_path: Path) -> None:
    async with rig(tmp_path, fps=15.0, flight=TOLERANT, overrides={"safety": NO_HOVER}) as r:
        move = mission("""
  <takeoff id="takeoff" height="1.0"/>
  <servo id="along" pipe="3" height="2.0" y="4.0" yaw="0" timeout="60"/>
""", name="move")
        await r.start_mission(move)
        ex = r.daemon.executor
        nf = r.daemon.nav_filter
        assert ex is not None and nf is not None
        await r.advance_until(lambda: bool(ex.results) and ex.results[0].result == "succeeded", max_s=20.0)
        await r.advance(2.5)  # moving along the rack
        assert float(np.linalg.norm(r.ap.truth.velocity_ned_m_s)) > 0.2
        r.camera.unplugged = True
        await r.advance(1.0)
        t_end_gap = r.clock.now()
        est = nf.estimate_latest()
        err_gap = float(np.linalg.norm(np.asarray(est.position_ned_m) - r.ap.truth.position_ned_m))
        r.camera.unplugged = False
        assert err_gap <= 0.10, err_gap
        await r.advance_until(lambda: bool(r.received("VISION_POSITION_ESTIMATE", since_s=t_end_gap)), max_s=0.5)
        t_back = r.received("VISION_POSITION_ESTIMATE", since_s=t_end_gap)[0].time_s
        assert t_back - t_end_gap <= 0.5
        await r.advance(0.3)
        nav = r.daemon.last_nav
        assert nav is not None and nav.ok
        assert float(np.linalg.norm(np.asarray(nav.position_ned_m) - r.ap.truth.position_ned_m)) <= 0.10
        assert ex.state is State.RUNNING


# -------------------------------------------------------------------------------- source switches

# The ground odometer's roll/pitch input is the autopilot's ATTITUDE: tell it the simulator's noise on
# it (its 0.5 deg default is for a real vehicle; at 5 m over the ground it would make every increment
# a 6 cm guess, and the filter would dead-reckon on the IMU instead).
SIM_ATTITUDE_STD_RAD = FakeAutopilotConfig().ekf_attitude_noise_rad
AUTO_VISION = {"vision": {"ground_odometer": {"attitude_std_rad": SIM_ATTITUDE_STD_RAD}}}
# What one ordinary frame may move the estimate beyond the constant-velocity prediction: a ground
# increment is about sqrt(2) * 0.002 rad * 5.3 m = 1.5 cm (1 sigma) at this height; this flight's
# non-switch frames: at most 3.3 cm (ground leg), 99th percentile 2.4 cm, median 1.5 mm. A switch
# frame carries that ordinary correction on top of the switch.
FRAME_CORRECTION_TOL_M = 0.04
# The filter judges a switch by its own correction; the pose stream's step differs from it by the
# constant-velocity prediction and the rangefinder updates in between (millimetres).
STEP_BAND_M = 0.01
TURN_BAND_RAD = 0.005

OFF_THE_END_AND_BACK = """
  <takeoff id="takeoff" height="1.0"/>
  <servo id="along" pipe="3" height="2.0" y="7.0" yaw="0" speed="0.8" timeout="40"/>
  <gotoxy id="off-the-end" x="1.1" y="12.0" timeout="40"/>
  <gotoxy id="back-over-the-rack" x="1.1" y="8.0" timeout="40"/>
"""


@dataclass(frozen=True)
class _Sent:
    """A fused pose the daemon sent, with what the vision pipeline measured on that frame."""

    stamp_s: float
    position_ned_m: Any
    velocity_ned_m_s: Any
    R_ned_body: Any
    source: str
    rack_position_ned_m: Any | None  # the rack tracker's body position (NED) on this frame, if ok
    truth_ned_m: Any


async def test_rack_ground_rack_switches_step_no_more_than_the_disagreement(tmp_path: Path) -> None:
    async with rig(tmp_path, vision="auto", fps=15.0, overrides=AUTO_VISION) as r:
        nf = r.daemon.nav_filter
        assert nf is not None
        T_cam_body = np.linalg.inv(r.daemon.T_body_cam)
        sent: list[_Sent] = []

        def observe(rec: FrameRecord) -> None:
            if not rec.sent:
                return
            m = rec.measurement
            p_rack = None
            if m.rack is not None and bool(m.rack.ok):
                p_rack = (r.daemon.T_ned_rack @ np.asarray(m.rack.T_rack_cam) @ T_cam_body)[:3, 3]
            nav = rec.nav
            sent.append(_Sent(float(nav.stamp_s), np.array(nav.position_ned_m), np.array(nav.velocity_ned_m_s),
                              np.array(nav.T_ned_body)[:3, :3], str(nav.source), p_rack,
                              r.ap.truth.position_ned_m.copy()))

        r.daemon.frame_observers.append(observe)
        t_start = r.clock.now()
        plan = mission(OFF_THE_END_AND_BACK, name="switch", timeout_s=120.0)
        await r.start_mission(plan)
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: ex.state is not State.RUNNING, max_s=100.0)

        # (3) The flight goes on normally: every action succeeds, the pose stream never stops for long,
        # the fused estimate stays close to the truth, the vehicle ends at the last goal.
        assert ex.state is State.COMPLETED, [(a.action_id, a.result, a.message) for a in ex.results]
        assert [a.result for a in ex.results] == ["succeeded"] * 4
        goal = ex.results[-1].T_ned_body_goal
        assert goal is not None
        # The end position carries the ground leg's drift along the pipes, which the re-acquired rack keeps
        # (below: 8-23 cm over renderer seeds); 21.5 cm with the texture weighting of 2026-11-24 (was <= 20).
        assert float(np.linalg.norm(r.ap.truth.position_ned_m[:2] - goal[:2, 3])) <= 0.25
        stamps = np.array([s.stamp_s for s in sent])
        assert float(np.max(np.diff(stamps))) < 0.5  # the safety manager's vision-loss limit
        # The largest error is the ground leg's drift, which the re-acquired rack keeps along the pipes
        # (nothing in view fixes that direction): 8 cm here, up to 23 cm with other renderer seeds.
        errors = [float(np.linalg.norm(s.position_ned_m - s.truth_ned_m)) for s in sent]
        assert max(errors) <= 0.3, max(errors)

        # The autopilot received exactly the poses the daemon sent, in order.
        vpe = r.received("VISION_POSITION_ESTIMATE", since_s=t_start)
        assert len(vpe) == len(sent)
        for msg, s in zip(vpe, sent, strict=True):
            p_msg = np.array([msg.fields["x"], msg.fields["y"], msg.fields["z"]])
            np.testing.assert_allclose(p_msg, s.position_ned_m, atol=1e-5)  # float32 on the wire
        counters = [int(msg.fields["reset_counter"]) for msg in vpe]

        # The sources the fused poses came from: the rack, the ground odometer off the end, the rack again.
        switches = [k for k in range(1, len(sent)) if sent[k].source != sent[k - 1].source]
        sources = [sent[0].source] + [sent[k].source for k in switches]
        assert sources[0] == "rack" and sources[-1] == "rack" and "ground" in sources, sources
        assert set(sources) == {"rack", "ground"}, sources

        threshold_m = nf.config.switch_reset_position_m
        threshold_rad = nf.config.switch_reset_angle_rad
        report = []
        for k in range(1, len(sent)):
            a, b = sent[k - 1], sent[k]
            prior = a.position_ned_m + a.velocity_ned_m_s * (b.stamp_s - a.stamp_s)  # what the autopilot expects
            step_m = float(np.linalg.norm(b.position_ned_m - prior))
            turn_rad = float(np.linalg.norm(so3.log(a.R_ned_body.T @ b.R_ned_body)))
            bumped = counters[k] - counters[k - 1]
            if k not in switches:
                assert bumped == 0, ("reset_counter changed without a switch", b.stamp_s - t_start, step_m)
                continue
            if b.source == "rack":
                assert b.rack_position_ned_m is not None
                disagreement_m = float(np.linalg.norm(b.rack_position_ned_m - prior))
            else:
                disagreement_m = 0.0  # the odometer measures increments: it carries the estimate on
            report.append((b.source, round(b.stamp_s - t_start, 2), step_m, disagreement_m, turn_rad, bumped))
            # (1) no step larger than the disagreement (plus one frame's ordinary correction)
            assert step_m <= disagreement_m + FRAME_CORRECTION_TOL_M, report
            # (2) a reset_counter increment when the switch moved the estimate, none otherwise (within the
            # bands around the thresholds either answer is right)
            assert bumped in (0, 1), report
            moved = step_m > threshold_m + STEP_BAND_M or turn_rad > threshold_rad + TURN_BAND_RAD
            still = step_m < threshold_m - STEP_BAND_M and turn_rad < threshold_rad - TURN_BAND_RAD
            if moved:
                assert bumped == 1, ("the switch moved the estimate: reset_counter must increase", report)
            if still:
                assert bumped == 0, ("the switch did not move the estimate: no reset", report)
        # Onto the ground odometer the switch is seamless: a relative source cannot move the estimate.
        for source, _, step_m, _, turn_rad, bumped in report:
            if source == "ground":
                assert step_m < threshold_m - STEP_BAND_M and turn_rad < threshold_rad - TURN_BAND_RAD, report
                assert bumped == 0, report
