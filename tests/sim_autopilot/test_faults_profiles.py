"""Fault scripting, listen URLs and the ArduPilot/PX4 mode encodings."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import ConfigError, InputError
from companion.sim.autopilot.faults import Fault, active_faults
from companion.sim.autopilot.profiles import ARDUPILOT, PX4, Behaviour, profile_by_name, px4_custom_mode
from companion.sim.autopilot.transport import parse_listen_url


def test_fault_defaults_windows_and_validation() -> None:
    f = Fault("message-loss", at_s=5.0, duration_s=2.0, percent=30.0)
    assert f.params == {"percent": 30.0, "direction": "both"}
    assert not f.active(4.99) and f.active(5.0) and f.active(6.99) and not f.active(7.0)
    forever = Fault("gcs-loss", 1.0)
    assert forever.end_s == math.inf and forever.active(1e6)
    assert active_faults([f, forever], 6.0, "gcs-loss") == [forever]
    assert Fault("command-reject", 0.0, commands=[400]).params["commands"] == (400,)
    bad_faults: tuple[Callable[[], Fault], ...] = (
        lambda: Fault("meteor-strike", 1.0),
        lambda: Fault("latency", -1.0),
        lambda: Fault("latency", 1.0, duration_s=0.0),
        lambda: Fault("latency", 1.0, jitter_ms=3.0),
        lambda: Fault("message-loss", 1.0, percent=120.0),
        lambda: Fault("message-loss", 1.0, direction="sideways"),
        lambda: Fault("command-reject", 1.0, result="maybe"),
    )
    for bad in bad_faults:
        with pytest.raises(InputError):
            bad()


def test_fault_spec_parsing() -> None:
    assert Fault.parse("gcs-loss@20:10") == Fault("gcs-loss", 20.0, 10.0)
    assert Fault.parse("battery-critical@30") == Fault("battery-critical", 30.0)
    with pytest.raises(InputError):
        Fault.parse("gcs-loss@soon")


def test_listen_urls() -> None:
    assert parse_listen_url("udpin:127.0.0.1:0").scheme == "udpin"
    assert parse_listen_url("tcpin://0.0.0.0:5760").port == 5760
    assert parse_listen_url("udpout:10.0.0.2:14550").host == "10.0.0.2"
    for bad in ("serial:/dev/ttyS0:57600", "udpin:127.0.0.1", "tcpin:host:http", "udpout:127.0.0.1:0"):
        with pytest.raises(ConfigError):
            parse_listen_url(bad)


def test_ardupilot_mode_numbers() -> None:
    expected = {"STABILIZE": 0, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9, "POSHOLD": 16, "BRAKE": 17}
    for name, number in expected.items():
        assert ARDUPILOT.mode(name).custom_mode == number
        assert ARDUPILOT.mode_from_custom(number) == ARDUPILOT.mode(name)
    flag = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    assert ARDUPILOT.mode_from_do_set_mode(flag, 4.0, 0.0) == ARDUPILOT.mode("GUIDED")
    assert ARDUPILOT.mode_from_do_set_mode(0.0, 4.0, 0.0) is None
    assert ARDUPILOT.mode_from_do_set_mode(flag, 99.0, 0.0) is None
    assert ARDUPILOT.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA


def test_px4_custom_mode_packs_main_and_sub_mode() -> None:
    assert px4_custom_mode(6) == 6 << 16
    assert PX4.mode("OFFBOARD").custom_mode == 0x00060000
    assert PX4.mode("AUTO.LAND").custom_mode == 0x06040000
    assert PX4.mode("AUTO.LOITER").custom_mode == 0x03040000
    assert PX4.mode("AUTO.TAKEOFF").custom_mode == 0x02040000
    assert PX4.mode("POSCTL").custom_mode == 0x00030000
    flag = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    assert PX4.mode_from_do_set_mode(flag, 4.0, 6.0) == PX4.mode("AUTO.LAND")
    assert PX4.mode_from_do_set_mode(flag, 6.0, math.nan) == PX4.mode("OFFBOARD")
    assert PX4.mode("offboard").behaviour is Behaviour.OFFBOARD
    assert PX4.autopilot == mavlink.MAV_AUTOPILOT_PX4
    with pytest.raises(InputError):
        PX4.mode("GUIDED")


def test_profile_by_name() -> None:
    assert profile_by_name("ArduPilot") is ARDUPILOT
    assert profile_by_name("px4") is PX4
    with pytest.raises(InputError):
        profile_by_name("betaflight")
