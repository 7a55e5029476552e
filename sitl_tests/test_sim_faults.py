"""Issue #13 item 4: `companion sim --fault` accepts every fault the fake autopilot knows (and the camera
faults), and its report ends with one line saying why the mission ended and what the safety manager
and the autopilot did, with times."""

from __future__ import annotations

import pytest

from companion.errors import InputError
from companion.sim.autopilot.faults import FAULT_KINDS as AUTOPILOT_FAULTS
from companion.sim.report import SafetyEventRecord, SimRecord, build_report
from companion.sim.run import CAMERA_FAULTS, FAULT_KINDS, parse_fault_spec


def test_every_fake_autopilot_fault_is_a_sim_fault() -> None:
    assert set(AUTOPILOT_FAULTS) <= set(FAULT_KINDS)
    assert set(FAULT_KINDS) == set(AUTOPILOT_FAULTS) | set(CAMERA_FAULTS)
    for kind in FAULT_KINDS:
        assert parse_fault_spec(f"{kind}@3:2").kind == kind
    with pytest.raises(InputError, match="unknown kind"):
        parse_fault_spec("solar-flare@3")


def test_outcome_line_names_the_reason_the_safety_actions_and_the_autopilot_modes() -> None:
    rec = SimRecord(mission_name="m", mission_state="aborted", start_s=0.0, end_s=60.0,
                    failed_action="action 9 servo 'p3-start' aborted: safety: land")
    rec.safety_events = [
        SafetyEventRecord(-3.0, "action", "stop-commands", "safety action none -> stop-commands (x)"),
        SafetyEventRecord(41.4, "vision-lost", "none", "no fresh pose for 500 ms"),
        SafetyEventRecord(41.4, "action", "hover", "safety action none -> hover (vision lost)"),
        SafetyEventRecord(51.4, "action", "land", "safety action hover -> land (vision lost too long)"),
        SafetyEventRecord(52.0, "ceiling-clearance", "land", "ceiling clearance 0.69 m below 1.0 m: climb clamped"),
    ]
    rec.autopilot_modes = [(0.0, "GUIDED", True), (41.5, "BRAKE", True), (51.5, "LAND", True),
                           (58.0, "LAND", False)]
    line = build_report(rec)["outcome"]
    assert line.startswith("NOT completed (aborted): action 9 servo 'p3-start' aborted: safety: land")
    assert "hover at 41.4 s (vision lost)" in line and "land at 51.4 s (vision lost too long)" in line
    assert "stop-commands" not in line  # before the mission start
    assert "ceiling-clearance clamp from 52.0 s" in line
    assert "BRAKE at 41.5 s" in line and "LAND at 51.5 s" in line and "disarmed at 58.0 s" in line
    assert "\n" not in line


def test_a_completed_mission_says_so() -> None:
    rec = SimRecord(mission_name="m", mission_completed=True, mission_state="completed")
    rec.autopilot_modes = [(0.0, "STABILIZE", False), (20.0, "GUIDED", True)]
    assert build_report(rec)["outcome"].startswith("completed; safety: no action; autopilot: STABILIZE at 0.0 s")
