"""Flight logic of the fake autopilot as a pure state machine: arming, modes, setpoint rules, failsafes."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.autopilot.flight import (
    FlightLogic,
    FlightParams,
    Setpoint,
    arming_refusal,
    mode_change_refusal,
    offboard_stream_ok,
)
from companion.sim.autopilot.profiles import ARDUPILOT, PX4, Profile
from companion.sim.autopilot.rules import flight_timings
from companion.sim.autopilot.vehicle import VehicleParams, VehicleState, initial_vehicle, step_vehicle

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
DT = 1.0 / 200.0


class Sim:
    """FlightLogic + dynamics stepped at 200 Hz; optional vision at 30 Hz and setpoint streams at 10 Hz."""

    def __init__(self, profile: Profile, **params: object) -> None:
        # The EKF's alignment (11.8 s for ArduPilot) is shortened explicitly: these tests are about the
        # flight rules; test_ardupilot_arms_only_after_the_ekf_aligned checks the alignment itself.
        params.setdefault("ekf_alignment_s", 0.05)
        self.logic = FlightLogic(profile, FlightParams(**params))  # type: ignore[arg-type]
        self.logic.home_set = True  # the autopilot sets home once the origin is set (not modelled here)
        self.vehicle: VehicleState = initial_vehicle()
        self.t = 0.0
        self.vision = True
        self.stream: Setpoint | None = None
        self._next_vision = 0.0
        self._next_setpoint = 0.0

    def run(self, seconds: float) -> None:
        end = self.t + seconds
        while self.t < end - 1e-9:
            self.t += DT
            if self.vision and self.t >= self._next_vision:
                self.logic.on_vision(self.t)
                self._next_vision = self.t + 1.0 / 30.0
            if self.stream is not None and self.t >= self._next_setpoint:
                self.logic.on_setpoint(Setpoint(self.t, self.stream.velocity_ned_m_s, None, None, 0.0))
                self._next_setpoint = self.t + 0.1
            cmd = self.logic.update(self.t, self.vehicle)
            self.vehicle = step_vehicle(self.vehicle, cmd, (0.0, 0.0, 0.0), VehicleParams(), DT)

    def mode(self, name: str) -> int:
        return self.logic.set_mode(self.logic.profile.mode(name), self.t, self.vehicle)[0]


def test_arming_refusal_rules() -> None:
    guided = ARDUPILOT.mode("GUIDED")
    assert arming_refusal(guided, ekf_healthy=False, require_vision=True, battery_critical=False, airborne=False)
    assert (
        arming_refusal(guided, ekf_healthy=False, require_vision=False, battery_critical=False, airborne=False) is None
    )
    assert arming_refusal(ARDUPILOT.mode("LAND"), True, True, False, False) == "Mode not armable"
    assert arming_refusal(guided, True, True, True, False) == "Battery critical"
    assert arming_refusal(guided, True, True, False, False) is None


def test_offboard_stream_rule_needs_more_than_2_hz_and_a_fresh_setpoint() -> None:
    assert not offboard_stream_ok([], 10.0, 2.0, 0.5)
    assert not offboard_stream_ok([9.9], 10.0, 2.0, 0.5)  # one setpoint is not a stream
    assert offboard_stream_ok([9.0, 9.5, 9.9], 10.0, 2.0, 0.5)  # three in the last second: a stream
    assert not offboard_stream_ok([9.5, 9.9], 10.0, 2.0, 0.5)  # 2 Hz is not more than 2 Hz
    assert not offboard_stream_ok([9.0, 9.2, 9.4], 10.0, 2.0, 0.5)  # last one 0.6 s old
    assert mode_change_refusal(PX4.mode("OFFBOARD"), ekf_healthy=True, offboard_ok=False)
    assert mode_change_refusal(PX4.mode("OFFBOARD"), ekf_healthy=True, offboard_ok=True) is None
    assert mode_change_refusal(ARDUPILOT.mode("GUIDED"), ekf_healthy=False, offboard_ok=True)
    assert mode_change_refusal(ARDUPILOT.mode("LAND"), ekf_healthy=False, offboard_ok=True) is None


# ArduCopter SITL: ARM before any vision -> FAILED, "Arm: VisOdom: not healthy"; after a pose stops, its
# EKF keeps a position for 7 s (dead reckoning) but the visual-odometry check fails after 300 ms.
@pytest.mark.parametrize(
    ("profile", "denied", "reason", "stale_s", "healthy_when_stale"),
    [
        (ARDUPILOT, mavlink.MAV_RESULT_FAILED, "VisOdom: not healthy", 0.35, True),
        (PX4, mavlink.MAV_RESULT_DENIED, "Need Position Estimate", 0.35, False),
    ],
)
def test_arming_needs_a_fresh_vision_pose(
    profile: Profile, denied: int, reason: str, stale_s: float, healthy_when_stale: bool
) -> None:
    sim = Sim(profile)
    sim.vision = False
    sim.run(1.0)
    result, why = sim.logic.arm(sim.t, sim.vehicle)
    assert result == denied and why == reason
    assert sim.logic.events[-1][1] == profile.statustext_prefix + reason
    sim.vision = True
    sim.run(0.1)
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == ACCEPTED
    assert sim.logic.armed
    sim.logic.disarm(sim.t, sim.vehicle)
    sim.vision = False
    sim.run(stale_s)
    assert sim.logic.ekf_healthy(sim.t) is healthy_when_stale
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == denied


def test_ardupilot_arms_only_after_the_ekf_aligned() -> None:
    sim = Sim(ARDUPILOT, ekf_alignment_s=None)  # the profile's 11.8 s (ArduCopter SITL: 11.8-13.1 s)
    sim.logic.home_set = False
    sim.vision = False
    sim.run(0.5)
    assert sim.mode("GUIDED") == ACCEPTED  # ArduCopter does not check the mode's needs while disarmed
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == mavlink.MAV_RESULT_FAILED
    assert [t for _, t in sim.logic.events[-2:]] == ["Arm: AHRS: waiting for home", "Arm: VisOdom: not healthy"]
    sim.logic.home_set = True
    sim.vision = True
    sim.run(11.5)
    assert sim.logic.ekf_healthy(sim.t) and sim.logic.prearm_failures(sim.t, sim.vehicle) == ["AHRS: not healthy"]
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == mavlink.MAV_RESULT_FAILED
    sim.run(0.6)
    assert sim.logic.prearm_failures(sim.t, sim.vehicle) == []
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == ACCEPTED


def test_no_vision_needed_in_gps_configuration() -> None:
    sim = Sim(ARDUPILOT, require_vision=False)
    sim.vision = False
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == ACCEPTED


def _ardupilot_airborne(height_m: float = 2.0, **params: object) -> Sim:
    sim = Sim(ARDUPILOT, **params)
    sim.run(0.1)
    assert sim.mode("GUIDED") == ACCEPTED
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == ACCEPTED
    assert sim.logic.takeoff(height_m, sim.t, sim.vehicle)[0] == ACCEPTED
    spool_s = flight_timings(FlightParams(), ARDUPILOT).takeoff_spool_s
    sim.run(spool_s + height_m / flight_timings(FlightParams(), ARDUPILOT).takeoff_speed_m_s + 3.0)
    assert not sim.logic.taking_off()
    return sim


def test_ardupilot_takeoff_in_guided_reaches_the_height_and_holds() -> None:
    sim = _ardupilot_airborne(2.0)
    assert sim.vehicle.height_m == pytest.approx(2.0, abs=0.1)
    assert sim.logic.mode.name == "GUIDED"
    assert "Takeoff complete" in [text for _, text in sim.logic.events]


def test_ardupilot_takeoff_refused_outside_guided_or_disarmed() -> None:
    sim = Sim(ARDUPILOT)
    sim.run(0.1)
    assert sim.logic.takeoff(2.0, sim.t, sim.vehicle)[0] == mavlink.MAV_RESULT_FAILED  # disarmed
    sim.logic.arm(sim.t, sim.vehicle)
    assert sim.logic.takeoff(2.0, sim.t, sim.vehicle)[0] == mavlink.MAV_RESULT_FAILED  # STABILIZE


def test_ardupilot_guided_velocity_times_out_after_3_s() -> None:
    sim = _ardupilot_airborne()
    sim.logic.on_setpoint(Setpoint(sim.t, (1.0, 0.0, 0.0), None, None, 0.0))
    sim.run(2.5)
    assert sim.vehicle.velocity_ned_m_s[0] == pytest.approx(1.0, abs=0.05)
    sim.run(2.5)  # 5 s after the only setpoint (the SITL brakes shaped: half speed 0.46 s after the timeout)
    assert abs(sim.vehicle.velocity_ned_m_s[0]) < 0.05
    stopped_at = sim.vehicle.position_ned_m[0]
    sim.run(2.0)
    assert sim.vehicle.position_ned_m[0] == pytest.approx(stopped_at, abs=0.1)
    assert sim.logic.mode.name == "GUIDED"


def test_ardupilot_ignores_setpoints_outside_guided() -> None:
    sim = Sim(ARDUPILOT)
    sim.run(0.1)
    sim.logic.on_setpoint(Setpoint(sim.t, (1.0, 0.0, 0.0)))
    assert sim.logic.setpoint is None


def test_px4_offboard_needs_a_stream_and_falls_back_to_loiter_when_it_stops() -> None:
    sim = Sim(PX4)
    sim.run(0.1)
    assert sim.logic.arm(sim.t, sim.vehicle)[0] == ACCEPTED
    assert sim.logic.takeoff(float("nan"), sim.t, sim.vehicle)[0] == ACCEPTED
    assert sim.logic.mode.name == "AUTO.TAKEOFF"
    sim.run(6.0)
    assert sim.logic.mode.name == "AUTO.LOITER"
    assert sim.vehicle.height_m == pytest.approx(FlightParams().default_takeoff_height_m, abs=0.1)
    assert sim.mode("OFFBOARD") == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    sim.stream = Setpoint(0.0, (0.0, 1.0, 0.0))
    sim.run(0.5)
    assert sim.mode("OFFBOARD") == ACCEPTED
    sim.run(3.0)
    assert sim.vehicle.velocity_ned_m_s[1] == pytest.approx(1.0, abs=0.05)
    sim.stream = None
    sim.run(0.45)
    assert sim.logic.mode.name == "OFFBOARD"
    sim.run(0.2)
    assert sim.logic.mode.name == "AUTO.LOITER"
    sim.run(3.0)
    assert abs(sim.vehicle.velocity_ned_m_s[1]) < 0.1


def test_land_descends_and_disarms_on_the_ground() -> None:
    sim = _ardupilot_airborne(2.0)
    assert sim.logic.land(sim.t, sim.vehicle)[0] == ACCEPTED
    assert sim.logic.landed_state(sim.vehicle) == mavlink.MAV_LANDED_STATE_LANDING
    sim.run(2.0 / flight_timings(FlightParams(), ARDUPILOT).land_speed_m_s + 3.0)  # SITL: disarm 2.2 s after touchdown
    assert sim.vehicle.on_ground
    assert not sim.logic.armed
    assert sim.logic.landed_state(sim.vehicle) == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_disarm_refused_in_flight_unless_forced() -> None:
    sim = _ardupilot_airborne()
    assert sim.logic.disarm(sim.t, sim.vehicle)[0] == mavlink.MAV_RESULT_FAILED
    assert sim.logic.armed
    assert sim.logic.disarm(sim.t, sim.vehicle, force=True)[0] == ACCEPTED
    sim.run(1.5)
    assert sim.vehicle.on_ground


# ArduCopter SITL, vision stopped at 1 m in GUIDED: flags unchanged for 7.1 s, "EKF variance" and LAND at
# 7.95 s (FS_EKF), a 4 s pause, then the descent; PX4 profile: the fake's own 1 s vision failsafe.
@pytest.mark.parametrize(("profile", "failsafe_s", "land_s"), [(ARDUPILOT, 7.95, 12.0), (PX4, 1.0, 8.0)])
def test_vision_loss_in_flight_lands(profile: Profile, failsafe_s: float, land_s: float) -> None:
    sim = Sim(profile)
    sim.run(0.1)
    if profile is ARDUPILOT:
        sim.mode("GUIDED")
    sim.logic.arm(sim.t, sim.vehicle)
    sim.logic.takeoff(2.0, sim.t, sim.vehicle)
    sim.run(8.0)
    height_m = sim.vehicle.height_m
    sim.vision = False
    sim.run(failsafe_s - 0.1)
    assert sim.logic.mode.name != profile.land_mode and sim.logic.armed
    assert sim.vehicle.height_m == pytest.approx(height_m, abs=0.02)  # dead reckoning holds the height
    sim.run(0.2)
    assert sim.logic.mode.name == profile.land_mode
    sim.run(land_s)
    assert sim.vehicle.on_ground and not sim.logic.armed


def test_ardupilot_ekf_failsafe_pauses_the_landing_and_obeys_fs_ekf_action() -> None:
    sim = _ardupilot_airborne(2.0)
    sim.vision = False
    sim.run(8.0)
    assert sim.logic.mode.name == "LAND"
    texts = [t for _, t in sim.logic.events]
    assert texts[-2:] == ["EKF variance", "EKF Failsafe: changed to LAND Mode"]
    sim.run(3.5)  # set_mode_land_with_pause: 4 s at the same height
    assert sim.vehicle.height_m == pytest.approx(2.0, abs=0.1)
    sim.run(1.5)
    assert sim.vehicle.height_m < 1.8
    sim.vision = True
    sim.run(1.5)
    assert "EKF Failsafe Cleared" in [t for _, t in sim.logic.events] and sim.logic.mode.name == "LAND"
    alt_hold = _ardupilot_airborne(2.0, fs_ekf_action=2)
    alt_hold.vision = False
    alt_hold.run(8.0)
    assert alt_hold.logic.mode.name == "ALT_HOLD"
    disabled = _ardupilot_airborne(2.0, fs_ekf_thresh=0.0)
    disabled.vision = False
    disabled.run(12.0)
    assert disabled.logic.mode.name == "GUIDED" and disabled.logic.armed


def test_battery_critical_in_flight_lands_once() -> None:
    sim = _ardupilot_airborne()
    sim.logic.battery_critical = True
    sim.run(0.1)
    assert sim.logic.mode.name == "LAND"
    assert any("Battery failsafe" in text for _, text in sim.logic.events)


def test_auto_disarm_when_idle_on_the_ground() -> None:
    sim = Sim(ARDUPILOT)
    sim.run(0.1)
    sim.logic.arm(sim.t, sim.vehicle)
    sim.run(9.5)
    assert sim.logic.armed
    sim.run(1.0)
    assert not sim.logic.armed


def test_rtl_flies_home_and_lands() -> None:
    sim = _ardupilot_airborne(3.0)
    sim.logic.on_setpoint(Setpoint(sim.t, (2.0, 1.0, 0.0), None, None, 0.0))
    sim.run(2.5)
    assert sim.vehicle.position_ned_m[0] > 2.5  # shaped acceleration (<= 2 m/s²) to 2 m/s
    assert sim.mode("RTL") == ACCEPTED
    sim.run(20.0)
    assert sim.vehicle.on_ground and not sim.logic.armed
    assert abs(sim.vehicle.position_ned_m[0]) < 0.5 and abs(sim.vehicle.position_ned_m[1]) < 0.5
