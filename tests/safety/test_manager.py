"""Safety manager: each behaviour, debounce and hysteresis, priorities, the command filter, events."""

from __future__ import annotations

import dataclasses

import pytest

from companion.control import VelocityCommand
from companion.errors import ConfigError
from companion.safety import (
    Fault,
    SafetyAction,
    SafetyConfig,
    SafetyInputs,
    SafetyManager,
    SafetyOutput,
    SafetyState,
)

CLIMB = VelocityCommand(0.3, 0.0, -0.5, 0.1)  # north 0.3 m/s, climbing 0.5 m/s


def healthy(now_s: float, **changes: object) -> SafetyInputs:
    """A flying vehicle with every link fresh at now_s."""
    base = SafetyInputs(
        battery_v=16.0, battery_pct=80.0, altitude_m=2.0, ceiling_clearance_m=None,
        last_gcs_heartbeat_s=now_s, last_pose_s=now_s, last_autopilot_heartbeat_s=now_s,
        position_ned_m=(0.0, 0.0, -2.0), armed=True, landed=False,
    )
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]


def run(sm: SafetyManager, t0: float, t1: float, make: object, dt: float = 0.1) -> list[SafetyOutput]:
    outs = []
    t = t0
    while t <= t1 + 1e-9:
        outs.append(sm.step(make(t), t))  # type: ignore[operator]
        t = round(t + dt, 9)
    return outs


def kinds(outs: list[SafetyOutput]) -> list[str]:
    return [e.kind for o in outs for e in o.events]


def test_nominal_passes_everything() -> None:
    sm = SafetyManager()
    out = sm.step(healthy(0.0), 0.0)
    assert (out.state, out.action, out.send_poses, out.allow_commands, out.allow_takeoff) == (
        SafetyState.NOMINAL, SafetyAction.NONE, True, True, True)
    assert out.faults == frozenset() and out.events == () and out.message == "nominal"
    assert sm.filter(CLIMB, healthy(0.0), 0.0) == CLIMB


@pytest.mark.parametrize(
    ("changes", "key"),
    [
        ({"ceiling_m": 0.0}, "safety.ceiling_m"),
        ({"battery_low_v": 13.0, "battery_critical_v": 13.5}, "safety.battery_critical_v"),
        ({"gcs_timeout_s": 10.0, "gcs_land_timeout_s": 5.0}, "safety.gcs_land_timeout_s"),
        ({"vision_timeout_s": float("nan")}, "safety.vision_timeout_s"),
        ({"geofence_min_ned_m": (0.0, 0.0, 0.0)}, "geofence"),
        ({"geofence_min_ned_m": (0.0, 0.0, 0.0), "geofence_max_ned_m": (1.0, -1.0, 1.0)}, "geofence_min_ned_m"),
    ],
)
def test_bad_config_names_the_key(changes: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        SafetyConfig(**changes)  # type: ignore[arg-type]


def test_ceiling_clamps_climb_and_pushes_down_above() -> None:
    sm = SafetyManager(SafetyConfig(ceiling_m=5.0, ceiling_gain_per_s=1.0))
    sm.step(healthy(0.0), 0.0)
    far = sm.filter(CLIMB, healthy(0.0, altitude_m=2.0), 0.0)
    assert far == CLIMB
    near = sm.filter(CLIMB, healthy(0.1, altitude_m=4.8), 0.1)
    assert near is not None and near.vz_m_s == pytest.approx(-0.2) and near.vx_m_s == 0.3
    assert near.yaw_rate_rad_s == 0.1
    above = sm.filter(CLIMB, healthy(0.2, altitude_m=5.3), 0.2)
    assert above is not None and above.vz_m_s == pytest.approx(0.3)  # pushed back down
    descend = VelocityCommand(0.0, 0.0, 0.6, 0.0)
    assert sm.filter(descend, healthy(0.3, altitude_m=5.3), 0.3) == descend  # descending is never clamped
    out = sm.step(healthy(0.4, altitude_m=5.3), 0.4)
    assert Fault.CEILING in out.faults and out.action is SafetyAction.NONE
    assert "ceiling" in kinds([out]) and any("command clamped" in e.message for e in out.events)
    # Hysteresis: the fault stays until 0.3 m below the ceiling.
    assert Fault.CEILING in sm.step(healthy(0.5, altitude_m=4.8), 0.5).faults
    assert Fault.CEILING not in sm.step(healthy(0.6, altitude_m=4.6), 0.6).faults


def test_upward_rangefinder_clearance_clamps_climb() -> None:
    sm = SafetyManager(SafetyConfig(min_ceiling_clearance_m=1.0))
    sm.step(healthy(0.0), 0.0)
    cmd = sm.filter(CLIMB, healthy(0.0, ceiling_clearance_m=1.25), 0.0)
    assert cmd is not None and cmd.vz_m_s == pytest.approx(-0.25)
    cmd = sm.filter(CLIMB, healthy(0.1, ceiling_clearance_m=0.8), 0.1)
    assert cmd is not None and cmd.vz_m_s == pytest.approx(0.2)
    assert Fault.CEILING_CLEARANCE in sm.step(healthy(0.2, ceiling_clearance_m=0.9), 0.2).faults
    assert sm.filter(CLIMB, healthy(0.3, ceiling_clearance_m=None), 0.3) == CLIMB  # no rangefinder: no limit


def test_geofence_clamps_outward_velocity_only() -> None:
    cfg = SafetyConfig(geofence_min_ned_m=(-5.0, -5.0, -8.0), geofence_max_ned_m=(5.0, 5.0, 1.0))
    sm = SafetyManager(cfg)
    sm.step(healthy(0.0), 0.0)
    cmd = VelocityCommand(0.5, -0.5, 0.0, 0.0)
    near_north = sm.filter(cmd, healthy(0.0, position_ned_m=(4.8, 0.0, -2.0)), 0.0)
    assert near_north is not None and near_north.vx_m_s == pytest.approx(0.2) and near_north.vy_m_s == -0.5
    outside = sm.filter(cmd, healthy(0.1, position_ned_m=(5.5, 0.0, -2.0)), 0.1)
    assert outside is not None and outside.vx_m_s == pytest.approx(-0.5)  # pushed back in
    inward = VelocityCommand(-0.5, 0.0, 0.0, 0.0)
    assert sm.filter(inward, healthy(0.2, position_ned_m=(4.9, 0.0, -2.0)), 0.2) == inward
    out = sm.step(healthy(0.3, position_ned_m=(5.5, 0.0, -2.0)), 0.3)
    assert Fault.GEOFENCE in out.faults and "geofence" in kinds([out])


def test_battery_low_is_debounced_with_hysteresis_then_lands() -> None:
    cfg = SafetyConfig(battery_low_v=14.0, battery_low_debounce_s=3.0, battery_hysteresis_v=0.2)
    sm = SafetyManager(cfg)
    # 2 s below, then a recovery above threshold + hysteresis restarts the debounce.
    outs = run(sm, 0.0, 2.0, lambda t: healthy(t, battery_v=13.9))
    outs += run(sm, 2.1, 2.5, lambda t: healthy(t, battery_v=14.3))
    assert all(o.action is SafetyAction.NONE for o in outs)
    # Oscillating inside the hysteresis band (14.0..14.2) does not restart it.
    outs = run(sm, 2.6, 5.5, lambda t: healthy(t, battery_v=13.9 if round(t * 10) % 2 == 0 else 14.1))
    assert all(o.action is SafetyAction.NONE for o in outs)
    outs = run(sm, 5.6, 5.7, lambda t: healthy(t, battery_v=13.9))
    assert outs[0].action is SafetyAction.LAND and outs[0].state is SafetyState.LANDING
    assert outs[0].time_s == pytest.approx(2.6 + 3.0, abs=0.11)
    assert "battery-low" in kinds(outs) and "action" in kinds(outs)
    assert not outs[0].allow_commands
    # Latched: a sag that recovers under lighter load does not cancel the landing.
    assert sm.step(healthy(6.0, battery_v=15.0), 6.0).action is SafetyAction.LAND
    assert sm.filter(CLIMB, healthy(6.0, battery_v=15.0), 6.0) is None
    assert not sm.operator_resume(6.1)
    # Cleared once disarmed on a healthy battery.
    out = sm.step(healthy(7.0, battery_v=15.0, armed=False, landed=True), 7.0)
    assert Fault.BATTERY_LOW not in out.faults and out.action is SafetyAction.NONE


def test_battery_percent_also_triggers_and_ground_blocks_takeoff() -> None:
    sm = SafetyManager(SafetyConfig(battery_low_pct=20.0, battery_low_debounce_s=1.0))
    outs = run(sm, 0.0, 1.0, lambda t: healthy(t, battery_pct=15.0, armed=False, landed=True))
    assert outs[-1].action is SafetyAction.NONE  # on the ground: nothing to override
    assert Fault.BATTERY_LOW in outs[-1].faults and not outs[-1].allow_takeoff
    out = sm.step(healthy(1.1, battery_pct=15.0), 1.1)
    assert out.action is SafetyAction.LAND


def test_battery_critical_lands_now() -> None:
    sm = SafetyManager(SafetyConfig(battery_critical_v=13.2, battery_critical_debounce_s=1.0))
    outs = run(sm, 0.0, 1.2, lambda t: healthy(t, battery_v=13.0))
    first = next(o for o in outs if o.action is not SafetyAction.NONE)
    assert first.action is SafetyAction.LAND_NOW and first.state is SafetyState.EMERGENCY_LANDING
    assert first.time_s == pytest.approx(1.0)
    assert any(e.kind == "battery-critical" and e.severity == "critical" for e in first.events)


def test_gcs_loss_hovers_then_lands_and_resumes_only_by_operator() -> None:
    cfg = SafetyConfig(gcs_timeout_s=5.0, gcs_land_timeout_s=20.0)
    sm = SafetyManager(cfg)
    outs = run(sm, 0.0, 10.0, lambda t: healthy(t, last_gcs_heartbeat_s=min(t, 2.0)))
    hover = next(o for o in outs if o.action is SafetyAction.HOVER)
    assert hover.time_s == pytest.approx(7.1) and hover.state is SafetyState.HOLD
    assert Fault.GCS_LOST in hover.faults and "gcs-lost" in kinds([hover])
    assert hover.send_poses and not hover.allow_commands
    assert sm.filter(CLIMB, healthy(10.0, last_gcs_heartbeat_s=2.0), 10.0) is None
    assert not sm.operator_resume(10.0)  # still lost
    # GCS heartbeats come back: the vehicle keeps hovering until the operator resumes.
    outs = run(sm, 10.1, 12.0, lambda t: healthy(t))
    assert all(o.action is SafetyAction.HOVER for o in outs) and Fault.GCS_LOST not in outs[-1].faults
    assert sm.operator_resume(12.0)
    out = sm.step(healthy(12.1), 12.1)
    assert out.action is SafetyAction.NONE and out.allow_commands
    assert {"resume", "action"} <= set(kinds([out]))
    # A longer loss goes on to land.
    outs = run(sm, 12.2, 40.0, lambda t: healthy(t, last_gcs_heartbeat_s=12.2))
    land = next(o for o in outs if o.action is SafetyAction.LAND)
    assert land.time_s == pytest.approx(12.2 + 20.0 + 0.1, abs=0.11) and Fault.GCS_LOST_LAND in land.faults


def test_no_gcs_ever_is_not_a_loss() -> None:
    sm = SafetyManager()
    outs = run(sm, 0.0, 20.0, lambda t: healthy(t, last_gcs_heartbeat_s=None), dt=1.0)
    assert all(o.action is SafetyAction.NONE and not o.faults for o in outs)


def test_vision_loss_stops_poses_hovers_then_lands() -> None:
    sm = SafetyManager(SafetyConfig(vision_timeout_s=0.5, vision_land_timeout_s=5.0))
    outs = run(sm, 0.0, 8.0, lambda t: healthy(t, last_pose_s=min(t, 1.0)))
    lost = next(o for o in outs if not o.send_poses)
    assert lost.time_s == pytest.approx(1.6) and lost.action is SafetyAction.HOVER
    assert Fault.VISION_LOST in lost.faults and "pose stream stopped" in " ".join(e.message for e in lost.events)
    land = next(o for o in outs if o.action is SafetyAction.LAND)
    assert land.time_s == pytest.approx(6.1) and Fault.VISION_LOST_LAND in land.faults
    # Vision back: poses flow again at once, the landing stays until the operator resumes.
    out = sm.step(healthy(8.1), 8.1)
    assert out.send_poses and out.action is SafetyAction.LAND
    assert sm.operator_resume(8.2)
    assert sm.step(healthy(8.3), 8.3).action is SafetyAction.NONE


def test_vision_auto_resume_option() -> None:
    sm = SafetyManager(SafetyConfig(vision_timeout_s=0.5, vision_auto_resume_s=1.0))
    run(sm, 0.0, 2.0, lambda t: healthy(t, last_pose_s=0.0))
    assert sm.action is SafetyAction.HOVER
    outs = run(sm, 2.1, 3.5, lambda t: healthy(t))
    back = next(o for o in outs if o.action is SafetyAction.NONE)
    assert back.time_s == pytest.approx(3.1)


def test_autopilot_link_loss_stops_commands_until_it_returns() -> None:
    sm = SafetyManager(SafetyConfig(autopilot_timeout_s=3.0))
    outs = run(sm, 0.0, 5.0, lambda t: healthy(t, last_autopilot_heartbeat_s=min(t, 1.0)))
    lost = next(o for o in outs if o.action is SafetyAction.STOP_COMMANDS)
    assert lost.time_s == pytest.approx(4.1) and lost.state is SafetyState.NO_AUTOPILOT
    assert not lost.allow_commands and "autopilot-lost" in kinds([lost])
    assert sm.filter(CLIMB, healthy(5.0, last_autopilot_heartbeat_s=1.0), 5.0) is None
    out = sm.step(healthy(5.1), 5.1)
    assert out.action is SafetyAction.NONE and out.allow_commands
    assert sm.filter(CLIMB, healthy(5.1), 5.1) == CLIMB
    # No autopilot heard yet (the daemon starts first): nothing may be commanded, but it is not a lost
    # link either -- no fault, no event for the GCS (issue #13: no ERROR at every start)
    fresh = SafetyManager()
    never = fresh.step(SafetyInputs(), 0.0)
    assert not never.allow_commands and not never.allow_takeoff
    assert Fault.AUTOPILOT_LOST not in never.faults and never.events == ()
    assert fresh.filter(CLIMB, SafetyInputs(), 0.0) is None


def test_critical_battery_beats_everything() -> None:
    cfg = SafetyConfig(battery_critical_debounce_s=0.5, battery_low_debounce_s=0.5, gcs_timeout_s=1.0,
                       gcs_land_timeout_s=2.0, vision_timeout_s=0.2, vision_land_timeout_s=1.0,
                       autopilot_timeout_s=1.0)
    sm = SafetyManager(cfg)
    outs = run(sm, 0.0, 3.0, lambda t: healthy(
        t, battery_v=12.0, battery_pct=3.0, altitude_m=11.0, last_gcs_heartbeat_s=0.0, last_pose_s=0.0,
        last_autopilot_heartbeat_s=0.0, position_ned_m=(500.0, 0.0, -11.0)))
    last = outs[-1]
    assert last.action is SafetyAction.LAND_NOW and last.state is SafetyState.EMERGENCY_LANDING
    assert {Fault.BATTERY_CRITICAL, Fault.BATTERY_LOW, Fault.GCS_LOST, Fault.VISION_LOST,
            Fault.AUTOPILOT_LOST, Fault.CEILING} <= last.faults
    assert not last.allow_commands and not last.send_poses
    assert all(o.action is not SafetyAction.LAND or o.time_s < 0.5 for o in outs)  # never downgraded


def test_priority_order_of_the_other_behaviours() -> None:
    cfg = SafetyConfig(battery_low_debounce_s=1.0, gcs_timeout_s=1.0, gcs_land_timeout_s=50.0)
    sm = SafetyManager(cfg)
    outs = run(sm, 0.0, 0.9, lambda t: healthy(t, last_gcs_heartbeat_s=-1.0))
    assert outs[-1].action is SafetyAction.HOVER  # GCS lost only
    outs = run(sm, 1.0, 2.5, lambda t: healthy(t, last_gcs_heartbeat_s=-1.0, battery_v=13.5))
    assert outs[-1].action is SafetyAction.LAND  # battery low beats the GCS hover
    assert outs[-1].state is SafetyState.LANDING


def test_every_decision_emits_an_event() -> None:
    sm = SafetyManager(SafetyConfig(vision_timeout_s=0.5))
    sm.step(healthy(0.0), 0.0)
    outs = run(sm, 0.1, 1.0, lambda t: healthy(t, last_pose_s=0.0))
    events = [e for o in outs for e in o.events]
    assert [e.kind for e in events] == ["vision-lost", "action"]
    assert events[1].action is SafetyAction.HOVER and "vision lost" in events[1].message
    assert all(e.time_s == pytest.approx(0.6) for e in events)
    assert sm.filter(CLIMB, healthy(1.0, last_pose_s=0.0), 1.0) is None
    out = sm.step(healthy(1.1, last_pose_s=0.0), 1.1)
    assert [e.kind for e in out.events] == ["commands"] and "blocked" in out.events[0].message


def test_unknown_or_impossible_height_never_allows_a_climb() -> None:
    sm = SafetyManager(SafetyConfig(ceiling_m=5.0))
    sm.step(healthy(0.0), 0.0)
    for t, altitude in ((0.1, None), (0.2, float("nan")), (0.3, float("inf"))):
        cmd = sm.filter(CLIMB, healthy(t, altitude_m=altitude), t)
        assert cmd is not None and cmd.vz_m_s == 0.0 and cmd.vx_m_s == 0.3
    descend = VelocityCommand(0.0, 0.0, 0.4, 0.0)
    assert sm.filter(descend, healthy(0.4, altitude_m=None), 0.4) == descend
    assert "ceiling" in kinds([sm.step(healthy(0.5), 0.5)])


def test_geofence_with_unknown_or_nan_position_stops_translation() -> None:
    sm = SafetyManager(SafetyConfig(geofence_min_ned_m=(-5.0, -5.0, -8.0), geofence_max_ned_m=(5.0, 5.0, 1.0)))
    sm.step(healthy(0.0), 0.0)
    for t, pos in ((0.1, None), (0.2, (float("nan"), 0.0, -2.0))):
        cmd = sm.filter(CLIMB, healthy(t, position_ned_m=pos), t)
        assert cmd is not None
        assert (cmd.vx_m_s, cmd.vy_m_s, cmd.vz_m_s, cmd.yaw_rate_rad_s) == (0.0, 0.0, 0.0, 0.1)


def test_ceiling_wins_over_a_geofence_that_pushes_up() -> None:
    # Below the fence floor (z > max down) right under the ceiling: the fence asks to climb, the ceiling refuses.
    cfg = SafetyConfig(ceiling_m=5.0, geofence_min_ned_m=(-5.0, -5.0, -8.0), geofence_max_ned_m=(5.0, 5.0, -6.0))
    sm = SafetyManager(cfg)
    sm.step(healthy(0.0), 0.0)
    cmd = sm.filter(VelocityCommand(0.0, 0.0, 0.0, 0.0), healthy(0.1, altitude_m=5.2, position_ned_m=(0.0, 0.0, -5.2)),
                    0.1)
    assert cmd is not None and cmd.vz_m_s >= 0.0


def test_impossible_battery_readings_are_unknown_not_critical() -> None:
    sm = SafetyManager(SafetyConfig(battery_critical_debounce_s=0.5, battery_low_debounce_s=0.5))
    outs = run(sm, 0.0, 2.0, lambda t: healthy(t, battery_v=0.0, battery_pct=float("nan")))
    assert all(o.action is SafetyAction.NONE and not o.faults for o in outs)
    outs = run(sm, 2.1, 4.0, lambda t: healthy(t, battery_v=-1.0, battery_pct=101.0))
    assert all(o.action is SafetyAction.NONE and not o.faults for o in outs)


def test_critical_battery_upgrades_a_landing_and_stays_latched() -> None:
    cfg = SafetyConfig(battery_low_debounce_s=1.0, battery_critical_debounce_s=2.0, gcs_timeout_s=1.0,
                       gcs_land_timeout_s=1.5)
    sm = SafetyManager(cfg)
    outs = run(sm, 0.0, 1.9, lambda t: healthy(t, battery_v=13.8, last_gcs_heartbeat_s=0.0))
    assert outs[-1].action is SafetyAction.LAND  # battery low and GCS land, not yet critical
    outs = run(sm, 2.0, 4.5, lambda t: healthy(t, battery_v=13.0, last_gcs_heartbeat_s=0.0))
    critical = next(o for o in outs if o.action is SafetyAction.LAND_NOW)
    assert critical.time_s == pytest.approx(4.0)
    # The sag recovers under lighter load and the GCS comes back: still landing now, resume refused.
    outs = run(sm, 4.6, 6.0, lambda t: healthy(t, battery_v=15.5))
    assert all(o.action is SafetyAction.LAND_NOW for o in outs)
    assert not sm.operator_resume(6.0)
    assert sm.step(healthy(6.1, battery_v=15.5), 6.1).action is SafetyAction.LAND_NOW


def test_commands_pass_only_while_the_watchdog_runs() -> None:
    sm = SafetyManager(SafetyConfig(watchdog_stale_s=1.0))
    assert sm.filter(CLIMB, healthy(0.0), 0.0) is None  # step never ran: battery, GCS... unchecked
    sm.step(healthy(0.0), 0.0)
    assert sm.filter(CLIMB, healthy(0.9), 0.9) == CLIMB
    assert sm.filter(CLIMB, healthy(1.5), 1.5) is None  # watchdog stalled
    out = sm.step(healthy(1.6), 1.6)
    assert any("watchdog not running" in e.message for e in out.events)
    assert sm.filter(CLIMB, healthy(1.6), 1.6) == CLIMB
