"""The daemon refuses to arm / take off while the safety manager forbids it or vision is stale.

Faults are injected at the fake autopilot (battery, GCS heartbeats) or the camera; every assertion
on "did not arm" is on what the fake autopilot received (no MAV_CMD_COMPONENT_ARM_DISARM with
param1 = 1) and on its true state.
"""

from __future__ import annotations

from pathlib import Path

import aiohttp
import pytest

from companion.errors import MissionError
from companion.mission import State
from sitl_tests.daemon_harness import Rig, mission, rig

ARM_DISARM = 400
HOVER = """
  <takeoff id="takeoff" height="1.0"/>
  <hover seconds="2"/>
  <land id="land"/>
"""


def arm_commands(r: Rig) -> list[float]:
    """Times of every ARM request (MAV_CMD_COMPONENT_ARM_DISARM, param1 = 1) the autopilot received."""
    return [float(m.time_s) for m in r.received("COMMAND_LONG")
            if int(m.fields["command"]) == ARM_DISARM and float(m.fields["param1"]) == 1.0]


async def test_battery_critical_before_start_refuses_the_mission_and_never_arms(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        r.schedule("battery-critical", in_s=0.0)
        await r.advance(0.5)  # the watchdog sees it (no debounce needed to forbid a take-off)
        out = r.daemon.safety_output
        assert out is not None and not out.allow_takeoff
        with pytest.raises(MissionError, match=r"refused.*battery"):
            await r.start_mission(mission(HOVER, name="refused"))
        await r.advance(2.0)
        assert r.daemon.executor is None
        status = r.daemon.status()["mission"]
        assert status["state"] == "refused" and "battery" in status["refused"]
        assert arm_commands(r) == [] and not r.ap.armed and r.ap.truth.height_m < 0.05
        assert any("mission refused" in t and "battery" in t for t in r.statustexts())
        assert r.logged("mission-refused")


async def test_stale_vision_refuses_the_start(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        r.camera.featureless = True  # the tracker loses the rack: no fresh pose is sent any more
        await r.advance(1.0)
        with pytest.raises(MissionError, match="no fresh vision pose"):
            await r.start_mission(mission(HOVER, name="blind"))
        await r.advance(1.0)
        assert arm_commands(r) == [] and not r.ap.armed
        r.camera.featureless = False  # vision back: the same mission starts and arms
        await r.advance(1.0)
        await r.start_mission(mission(HOVER, name="seeing"))
        await r.advance_until(lambda: bool(arm_commands(r)), max_s=3.0)
        assert r.daemon.status()["mission"].get("refused") is None


async def test_arm_request_refused_when_the_battery_fails_after_the_start(tmp_path: Path) -> None:
    """The executor's ARM request is checked too: a fault between the start and the take-off stops it."""
    async with rig(tmp_path) as r:
        ground_first = mission('<hover seconds="1.0" timeout="10"/>' + HOVER, name="late-fault")
        await r.start_mission(ground_first)
        ex = r.daemon.executor
        assert ex is not None
        r.schedule("battery-critical", in_s=0.2)
        await r.advance_until(lambda: ex.state is State.FAILED, max_s=8.0)
        await r.advance(1.0)
        assert arm_commands(r) == [] and not r.ap.armed
        assert any("refused" in res.message and "battery" in res.message for res in ex.results)
        assert "battery" in r.daemon.status()["mission"]["refused"]


GOOD = b"""<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="api-hover" frame="ned" timeout="30" speed="0.5" threshold="0.1" yaw-threshold="5">
  <takeoff id="takeoff" height="1.0"/>
  <hover seconds="1"/>
  <land id="land"/>
</mission>
"""


async def test_api_start_refused_while_the_gcs_is_lost_and_limits_follow_the_config(tmp_path: Path) -> None:
    async with rig(tmp_path, api=True, overrides={"safety": {"gcs_loss_hover_s": 0.5, "gcs_loss_land_s": 5.0,
                                                             "ceiling_m": 3.0}}) as r:
        server = r.daemon.api_server
        assert server is not None
        base = server.url + "/api/v1"
        async with aiohttp.ClientSession() as http:
            # issue 2: the configured ceiling (3 m, below the parser's default 10 m) applies to uploads
            high = GOOD.replace(b'height="1.0"', b'height="4.0"')
            async with http.post(f"{base}/missions?name=high.xml", data=high) as resp:
                assert resp.status == 422
                assert "ceiling" in (await resp.json())["error"] or "3" in (await resp.json())["error"]
            async with http.post(f"{base}/missions?name=hover.xml", data=GOOD) as resp:
                assert resp.status == 201
                stored = await resp.json()
            mission_id = stored.get("id") or stored.get("mission", {}).get("id")
            assert mission_id
            r.schedule("gcs-loss", in_s=0.0)
            await r.advance(1.5)
            async with http.post(f"{base}/missions/{mission_id}/start") as resp:  # what `mission start` calls
                assert resp.status == 409
                text = await resp.text()
                assert "refused" in text and "gcs" in text.lower()
        assert arm_commands(r) == [] and not r.ap.armed
        assert r.daemon.status()["mission"]["state"] == "refused"
