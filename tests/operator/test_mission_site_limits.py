"""Missions against the configured ceiling and geofence: offline (`mission validate --config`) and at upload."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.config import ApiConfig, load_config, mission_limits, parse_config
from companion.errors import InputError, MissionError
from companion.mission import MissionLimits, parse_mission, validate_cli
from companion.mission.site import limits_T_ned_rack
from drivers.api import ApiClient, ApiError, ApiServer, default_validator

FENCE = """[safety]
ceiling_m = 6.0
geofence_min_ned_m = [-5.0, -2.0, -6.0]
geofence_max_ned_m = [20.0, 10.0, 1.0]
[rack]
translation_m = [1.0, 2.0, 0.0]
yaw_deg = 90.0
"""

NED_MISSION = """<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="ned" frame="ned" timeout="30" speed="0.5">
  <takeoff height="2.0"/>
  <gotoxy x="{x}" y="{y}"/>
  <gotoz z="{z}"/>
  <land/>
</mission>
"""

RACK_MISSION = """<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="rack" frame="rack" timeout="30" speed="0.5">
  <rack length="10.0">
    <pipe radius="0.15" gap="0.10"/>
    <pipe radius="0.20"/>
  </rack>
  <takeoff height="1.5"/>
  <gotoxy x="{x}" y="{y}"/>
  <servo pipe="2" height="{height}" y="{servo_y}" yaw="0"/>
  <land/>
</mission>
"""


@pytest.fixture
def limits() -> MissionLimits:
    return mission_limits(parse_config({"safety": {"ceiling_m": 6.0, "geofence_min_ned_m": [-5.0, -2.0, -6.0],
                                                   "geofence_max_ned_m": [20.0, 10.0, 1.0]},
                                        "rack": {"translation_m": [1.0, 2.0, 0.0], "yaw_deg": 90.0}}))


def test_config_limits_carry_ceiling_fence_and_rack_placement(limits: MissionLimits) -> None:
    assert limits.ceiling_m == 6.0
    assert limits.geofence_min_ned_m == (-5.0, -2.0, -6.0) and limits.geofence_max_ned_m == (20.0, 10.0, 1.0)
    T = limits_T_ned_rack(limits)
    # yaw 90 deg: the pipes (rack +y) point east; rack +x points south; rack z is up
    np.testing.assert_allclose(T[:3, :3] @ [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], atol=1e-12)
    with pytest.raises(InputError, match="both or neither"):
        MissionLimits(geofence_min_ned_m=(0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="below"):
        MissionLimits(geofence_min_ned_m=(0.0, 0.0, 0.0), geofence_max_ned_m=(1.0, 0.0, 1.0))


def test_ned_goals_inside_pass_and_outside_are_refused(limits: MissionLimits) -> None:
    parse_mission(NED_MISSION.format(x=19.5, y=-1.5, z=-4.0), "m.xml", limits)
    with pytest.raises(MissionError) as north:
        parse_mission(NED_MISSION.format(x=25.0, y=0.0, z=-4.0), "m.xml", limits)
    assert str(north.value) == (
        "m.xml:4: gotoxy.x/y: goal (north 25, east 0) m is outside the geofence "
        "(north -5..20 m, safety.geofence_min_ned_m/geofence_max_ned_m)"
    )
    with pytest.raises(MissionError, match=r"^m\.xml:4: gotoxy\.x/y: .*east -2\.\.10 m"):
        parse_mission(NED_MISSION.format(x=0.0, y=-3.0, z=-4.0), "m.xml", limits)
    # z -5.5 (5.5 m up) is under the 6 m ceiling but above the fence's top (down -6 .. 1): fine;
    # the fence top is checked when it is lower than the ceiling
    low_top = mission_limits(parse_config({"safety": {"ceiling_m": 6.0, "geofence_min_ned_m": [-5.0, -2.0, -4.0],
                                                      "geofence_max_ned_m": [20.0, 10.0, 1.0]}}))
    parse_mission(NED_MISSION.format(x=0.0, y=0.0, z=-3.9), "m.xml", low_top)
    with pytest.raises(MissionError, match=r"^m\.xml:5: gotoz\.z: goal \(down -5\.5\) m is outside .*down -4\.\.1 m"):
        parse_mission(NED_MISSION.format(x=0.0, y=0.0, z=-5.5), "m.xml", low_top)


def test_ceiling_from_the_config(limits: MissionLimits) -> None:
    parse_mission(NED_MISSION.format(x=0.0, y=0.0, z=-7.0), "m.xml")  # the built-in 10 m ceiling
    with pytest.raises(MissionError, match=r"^m\.xml:5: gotoz\.z: .* is above the ceiling 6 m"):
        parse_mission(NED_MISSION.format(x=0.0, y=0.0, z=-7.0), "m.xml", limits)


def test_rack_goals_are_placed_by_the_rack_config(limits: MissionLimits) -> None:
    # rack (x, y) -> NED (1 - x, 2 + y): rack y 7.5 is east 9.5, inside; rack x -20 is north 21, outside
    parse_mission(RACK_MISSION.format(x=0.5, y=7.5, height=1.0, servo_y=5.0), "r.xml", limits)
    with pytest.raises(MissionError, match=r"^r\.xml:8: gotoxy\.x/y: goal in NED \(north 21, east 3\) m"):
        parse_mission(RACK_MISSION.format(x=-20.0, y=1.0, height=1.0, servo_y=5.0), "r.xml", limits)
    # servo at rack y 9 -> east 11 > 10: refused, naming the servo line
    with pytest.raises(MissionError, match=r"^r\.xml:9: servo\.y/height: goal in NED \(north 0\.4, east 11"):
        parse_mission(RACK_MISSION.format(x=0.5, y=1.0, height=1.0, servo_y=9.0), "r.xml", limits)
    # without a geofence (the defaults) the same mission is valid
    parse_mission(RACK_MISSION.format(x=0.5, y=1.0, height=1.0, servo_y=9.0), "r.xml")


def test_tilted_rack_gotoxy_checks_every_reachable_height() -> None:
    # rack rolled 90 deg: rack z (up) is NED east, so the horizontal goal depends on the height flown
    limits = MissionLimits(ceiling_m=6.0, geofence_min_ned_m=(-50.0, -3.0, -10.0),
                           geofence_max_ned_m=(50.0, 3.0, 1.0),
                           T_ned_rack=(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    mission = RACK_MISSION.replace('  <servo pipe="2" height="{height}" y="{servo_y}" yaw="0"/>\n', "")
    with pytest.raises(MissionError, match=r"gotoxy\.x/y: goal in NED \(north 0, east 6\) m .*east -3\.\.3 m"):
        parse_mission(mission.format(x=0.0, y=0.0), "t.xml", limits)
    assert math.isclose(limits_T_ned_rack(limits)[1, 2], 1.0)


def _validate(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion.cli", "mission", "validate", *args],
                          capture_output=True, text=True, timeout=120, check=False)


def test_mission_validate_cli_with_and_without_config(tmp_path: Path) -> None:
    config = tmp_path / "companion.toml"
    config.write_text(FENCE)
    mission = tmp_path / "far.xml"
    mission.write_text(NED_MISSION.format(x=25.0, y=0.0, z=-4.0))
    plain = _validate(str(mission))
    assert plain.returncode == 0 and plain.stdout.startswith(f"{mission}: valid:")
    fenced = _validate(str(mission), "--config", str(config))
    assert fenced.returncode == 2 and fenced.stdout == ""
    assert fenced.stderr.splitlines() == [
        f"{mission}:4: gotoxy.x/y: goal (north 25, east 0) m is outside the geofence "
        "(north -5..20 m, safety.geofence_min_ned_m/geofence_max_ned_m)"
    ]
    high = tmp_path / "high.xml"
    high.write_text(NED_MISSION.format(x=0.0, y=0.0, z=-7.0))
    assert _validate(str(high)).returncode == 0
    refused = _validate(str(high), "--config", str(config))
    assert refused.returncode == 2 and "gotoz.z: z -7 m (ned frame, a height of 7 m) is above the ceiling 6 m" in (
        refused.stderr
    )
    bad_config = tmp_path / "bad.toml"
    bad_config.write_text("[safety]\nceiling_m = -1\n")
    broken = _validate(str(high), "--config", str(bad_config))
    assert broken.returncode == 2 and broken.stderr.strip() == "companion: error: safety.ceiling_m: must be > 0, got -1"


class _Controller:
    async def start(self, mission_id: str) -> None: ...

    async def pause(self, mission_id: str | None) -> None: ...

    async def resume(self, mission_id: str | None) -> None: ...

    async def abort(self, mission_id: str | None) -> None: ...


async def test_upload_is_refused_with_the_offline_message(tmp_path: Path) -> None:
    config_path = tmp_path / "companion.toml"
    config_path.write_text(FENCE)
    limits = mission_limits(load_config(config_path))  # what the daemon hands the API (Daemon.start)
    far = tmp_path / "far.xml"
    far.write_text(NED_MISSION.format(x=25.0, y=0.0, z=-4.0))
    code, offline = validate_cli(far, limits)
    assert code == 2
    server = ApiServer(ApiConfig(port=0), store_dir=tmp_path / "missions", validate=default_validator(limits),
                       controller=_Controller(), status_provider=dict)
    async with server, ApiClient(server.url) as client:
        with pytest.raises(ApiError) as refused:
            await client.upload(far.read_bytes(), "far.xml")
        assert refused.value.status == 422
        assert refused.value.message == offline.replace(str(far), "far.xml")
        near = NED_MISSION.format(x=10.0, y=0.0, z=-4.0).encode()
        info = await client.upload(near, "near.xml")
        assert info["id"] == "near"
        assert [m["id"] for m in await client.list_missions()] == ["near"]
