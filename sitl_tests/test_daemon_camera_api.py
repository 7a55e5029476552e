"""The daemon's camera-loss handling and its control API, against the fake autopilot.

- camera unplug (the driver's reads fail) -> camera lost, vision-lost safety behaviour (poses stop,
  hold), then recovery: frames return, poses flow to the autopilot again;
- mission upload through the running daemon's API: refused without the token, oversize and malformed
  files rejected and not stored, a valid upload stored and started through the API.
"""

from __future__ import annotations

import os
from pathlib import Path

import aiohttp

from companion.mission import State
from sitl_tests.daemon_harness import mission, rig

BRAKE = 17.0
GOOD = b"""<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="api-hover" frame="ned" timeout="30" speed="0.5" threshold="0.1" yaw-threshold="5">
  <takeoff id="takeoff" height="1.0"/>
  <hover seconds="1"/>
  <land id="land"/>
</mission>
"""


async def test_camera_unplug_vision_lost_then_recovery(tmp_path: Path) -> None:
    async with rig(tmp_path, overrides={"safety": {"vision_loss_hover_ms": 200}}) as r:
        await r.start_mission(mission('<takeoff id="takeoff" height="1.0"/><hover seconds="60"/>', timeout_s=90.0))
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: bool(ex.results) and ex.results[0].result == "succeeded", max_s=20.0)
        t_unplug = r.clock.now()
        r.camera.unplugged = True
        await r.advance(0.7)
        assert not r.daemon.camera_ok  # the driver reported the camera lost
        assert r.daemon.status()["camera"]["state"] == "lost"
        assert r.received("VISION_POSITION_ESTIMATE", since_s=t_unplug + 0.15) == []
        assert any(int(m.fields["command"]) == 176 and float(m.fields["param2"]) == BRAKE
                   for m in r.received("COMMAND_LONG", since_s=t_unplug))
        assert ex.state is State.PAUSED  # a hold pauses the mission; it resumes once vision is back
        t_replug = r.clock.now()
        r.camera.unplugged = False
        await r.advance_until(lambda: bool(r.received("VISION_POSITION_ESTIMATE", since_s=t_replug)), max_s=1.0)
        await r.advance(1.0)
        assert r.daemon.camera_ok
        assert len(r.received("VISION_POSITION_ESTIMATE", since_s=t_replug)) >= 8
        assert r.daemon.status()["estimator"]["ok"] is True
        assert r.ap.armed and r.ap.truth.height_m > 0.7  # still flying, no crash
        await r.advance_until(lambda: ex.state is State.RUNNING, max_s=3.0)  # issue #13: it recovers


async def test_mission_upload_through_the_daemon_api(tmp_path: Path) -> None:
    token = "s3cret-token-0123456789"
    token_file = tmp_path / "token"
    token_file.write_text(token + "\n")
    os.chmod(token_file, 0o600)
    api = {"token_file": str(token_file), "max_upload_bytes": 4096}
    async with rig(tmp_path, api=True, overrides={"api": api}) as r:
        server = r.daemon.api_server
        assert server is not None
        base = server.url + "/api/v1"
        auth = {"Authorization": f"Bearer {token}"}
        async with aiohttp.ClientSession() as http:
            async with http.post(f"{base}/missions?name=hover.xml", data=GOOD) as resp:
                assert resp.status == 401
            async with http.post(f"{base}/missions?name=hover.xml", data=GOOD,
                                 headers={"Authorization": "Bearer wrong-token-0000000000"}) as resp:
                assert resp.status == 401
            big = GOOD.replace(b"</mission>", b"<!--" + b"x" * 5000 + b"--></mission>")
            async with http.post(f"{base}/missions?name=big.xml", data=big, headers=auth) as resp:
                assert resp.status == 413
            bad = GOOD.replace(b'height="1.0"', b'height="lots"')
            async with http.post(f"{base}/missions?name=bad.xml", data=bad, headers=auth) as resp:
                assert resp.status == 422
                assert "height" in (await resp.json())["error"]
            async with http.post(f"{base}/missions?name=hover.xml", data=GOOD, headers=auth) as resp:
                assert resp.status == 201
                stored = await resp.json()
            async with http.get(f"{base}/missions", headers=auth) as resp:
                listing = await resp.json()
            text = str(listing)
            assert "hover" in text and "bad" not in text and "big" not in text
            mission_id = stored.get("id") or stored.get("mission", {}).get("id")
            assert mission_id
            async with http.post(f"{base}/missions/{mission_id}/start", headers=auth) as resp:
                assert resp.status == 200, await resp.text()
            ex = r.daemon.executor
            assert ex is not None and ex.mission.name == "api-hover"
            await r.advance_until(lambda: ex.state is State.COMPLETED, max_s=30.0)
            async with http.get(f"{base}/status", headers=auth) as resp:
                status = await resp.json()
            assert status["mission"]["state"] == "completed"
            assert r.received("VISION_POSITION_ESTIMATE")
