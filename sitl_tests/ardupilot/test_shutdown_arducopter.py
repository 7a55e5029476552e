"""`companion run` (what systemd starts) stopped with SIGTERM mid-mission, on the real ArduCopter SITL.

The daemon runs as its own process with the control API; the mission is uploaded and started
through the `companion mission` command line. On SIGTERM the daemon stops the mission and the
setpoints and puts ArduPilot in BRAKE (holding, armed); then it exits 0. What ArduPilot does next
without vision poses is recorded (docs/deploy.md reports it): it is the autopilot's own failsafe.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from companion.sim.ardupilot_sitl import ArduPilotSitl, SitlObserver
from sitl_tests.ardupilot.harness import HOME_LLA, report, run_config

GUIDED, LAND, BRAKE = 4, 9, 17
MISSION = """<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="sigterm" frame="rack" timeout="120" speed="0.5" threshold="0.1" yaw-threshold="5">
  <rack length="10.0">
    <pipe radius="0.15" gap="0.10"/><pipe radius="0.20" gap="0.10"/><pipe radius="0.15" gap="0.10"/>
    <pipe radius="0.175" gap="0.10"/><pipe radius="0.20"/>
  </rack>
  <takeoff id="takeoff" height="1.5"/>
  <hover seconds="120" timeout="150"/>
  <land id="land"/>
</mission>
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion.cli", *args], capture_output=True, text=True, timeout=30)


def _mode(ob: SitlObserver) -> int | None:
    hb = ob.latest("HEARTBEAT")
    return None if hb is None else int(hb.fields["custom_mode"])


async def _wait(pred, timeout_s: float, what: str, ob: SitlObserver) -> float:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"{what}: not within {timeout_s} s (mode {_mode(ob)}, armed {ob.armed}, "
                                 f"texts {ob.statustexts()[-6:]})")
        await asyncio.sleep(0.1)
    return time.monotonic() - t0


async def test_sigterm_mid_mission_leaves_arducopter_holding(sitl_available: Path, tmp_path: Path) -> None:
    lat, lon, alt = HOME_LLA
    with ArduPilotSitl(sitl_available, home=f"{lat},{lon},{alt},0") as sitl:
        port = _free_port()
        config = run_config(tmp_path, sitl.url, port)
        api = ["--url", f"http://127.0.0.1:{port}"]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        with open(tmp_path / "daemon.log", "wb") as log:
            proc = subprocess.Popen([sys.executable, "-m", "companion.cli", "run", "--config", str(config)],
                                    stdout=log, stderr=subprocess.STDOUT, env=env)
        ob = SitlObserver(sitl.observer_url, HOME_LLA)
        try:
            await asyncio.get_running_loop().run_in_executor(None, ob.start)
            (tmp_path / "sigterm.xml").write_text(MISSION)
            up = None
            for _ in range(50):  # the API comes up once the daemon runs
                up = _cli("mission", "upload", str(tmp_path / "sigterm.xml"), *api, "--json")
                if up.returncode == 0:
                    break
                await asyncio.sleep(0.3)
            assert up is not None and up.returncode == 0, up.stdout + up.stderr
            stored = json.loads(up.stdout)
            mission_id = str(stored.get("id") or stored.get("mission", {}).get("id"))
            start = None
            for _ in range(40):  # poses must flow before the take-off gate opens
                start = _cli("mission", "start", mission_id, *api)
                if start.returncode == 0:
                    break
                await asyncio.sleep(0.5)
            assert start is not None and start.returncode == 0, start.stdout + start.stderr
            await _wait(lambda: ob.armed and _mode(ob) == GUIDED and (ob.truth_T_ned_body() is not None and
                                                                     -ob.truth_T_ned_body()[2, 3] > 1.2),
                        70.0, "airborne in GUIDED", ob)
            t_term = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            brake_s = await _wait(lambda: _mode(ob) == BRAKE, 5.0, "BRAKE after SIGTERM", ob)
            code = await asyncio.get_running_loop().run_in_executor(None, proc.wait, 15.0)
            exit_s = time.monotonic() - t_term
            assert code == 0
            assert ob.armed
            h_hold = -float(ob.truth_T_ned_body()[2, 3])
            # what ArduPilot does on its own without the poses (its EKF failsafe), for the docs
            t_after = time.monotonic()
            while time.monotonic() - t_after < 20.0 and ob.armed:
                await asyncio.sleep(0.2)
            modes_after = sorted({int(m.fields["custom_mode"]) for m in ob.messages("HEARTBEAT", t_after)})
            lands = [m.time_s for m in ob.messages("HEARTBEAT", t_term) if int(m.fields["custom_mode"]) == LAND]
            texts_after = [t for t in ob.statustexts(t_term) if not t.startswith("companion")]
            report("SIGTERM mid-mission: " + json.dumps({
                "brake_after_s": round(brake_s, 2), "daemon_exit_after_s": round(exit_s, 2),
                "height_holding_m": round(h_hold, 2), "modes_in_20_s_after": modes_after,
                "arducopter_land_mode_after_s": round(lands[0] - t_term, 1) if lands else None,
                "armed_20_s_after": ob.armed, "autopilot_texts": texts_after[:8]}))
            assert brake_s <= 3.0
        finally:
            ob.stop()
            if proc.poll() is None:
                proc.kill()
                proc.wait(5.0)
