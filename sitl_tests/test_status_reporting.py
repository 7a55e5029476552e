"""Issue #13 item 6: what the daemon reports about itself -- to systemd, `companion status` and the GCS.

READY=1 only once the autopilot is heard, with STATUS= lines saying what it waits for and then
what it does; a readable link health and the capture-to-send latency in the status; no
autopilot-lost error at start; the health summary reaches the GCS only when it changes.
"""

from __future__ import annotations

import asyncio
import dataclasses
import os
import socket
from pathlib import Path

import numpy as np

from companion.clock import ManualClock
from companion.daemon.app import Daemon, DaemonOptions
from companion.sim.autopilot import FakeAutopilot, FakeAutopilotConfig
from companion.sim.run import sim_config
from sitl_tests.daemon_harness import InlineCamera, rig, stop_daemon


def _notify_socket(tmp_path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.setblocking(False)
    return sock


def _drain(sock: socket.socket) -> list[str]:
    out: list[str] = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


async def test_ready_waits_for_the_autopilot_and_status_lines_say_why(tmp_path: Path) -> None:
    sock = _notify_socket(tmp_path)
    os.environ["NOTIFY_SOCKET"] = str(tmp_path / "notify.sock")
    try:
        silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a port where no autopilot answers
        silent.bind(("127.0.0.1", 0))
        port = silent.getsockname()[1]
        config = sim_config(tmp_path, {"camera": {"width": 240, "height": 160}})
        config = dataclasses.replace(config, mavlink=dataclasses.replace(config.mavlink,
                                                                          url=f"udpout:127.0.0.1:{port}"))
        clock = ManualClock(1000.0)
        camera = InlineCamera(clock, lambda T: np.zeros((160, 240), np.uint8), lambda: np.eye(4))
        await camera.__aenter__()
        daemon = Daemon(config, clock=clock, options=DaemonOptions(
            vision_inline=True, camera_source=camera, api=False, sdnotify=True, flight_root=tmp_path / "flights"))
        await daemon.start()
        try:
            for _ in range(100):  # 10 s of clock time without an autopilot
                await clock.advance(0.1)
                await asyncio.sleep(0)
            messages = _drain(sock)
            assert not any("READY=1" in m for m in messages)
            assert any(m.startswith("STATUS=waiting for the autopilot on udpout:127.0.0.1") for m in messages)
            st = daemon.status()
            assert st["link"]["health"] == "no-autopilot-heard"
            # not a lost link: no error event for the GCS or the log at start
            assert not [e for e in daemon._safety_view.events if e["kind"] == "autopilot-lost"]
            silent.close()  # the autopilot is powered: READY=1 once its heartbeat arrives
            ap_cfg = FakeAutopilotConfig(listen=f"udpin:127.0.0.1:{port}", seed=1)
            async with FakeAutopilot(ap_cfg, clock=clock):
                for _ in range(150):
                    await clock.advance(0.1)
                    messages += _drain(sock)
                    if any("READY=1" in m for m in messages):
                        break
                assert any("READY=1" in m for m in messages)
                assert any(m.startswith("STATUS=ardupilot") for m in messages + _drain(sock)) or \
                    daemon.status_line().startswith("ardupilot")
        finally:
            await stop_daemon(daemon, clock)
            await camera.__aexit__(None, None, None)
            silent.close()
    finally:
        del os.environ["NOTIFY_SOCKET"]
        sock.close()


async def test_status_once_flying_and_the_gcs_is_not_flooded(tmp_path: Path) -> None:
    async with rig(tmp_path, overrides={"logging": {"health_period_s": 1.0}}) as r:
        await r.advance(1.0)  # poses flow (the rig waited for them), then 20 health periods
        t0 = r.clock.now()
        await r.advance(20.0)
        st = r.daemon.status()
        assert st["link"]["health"] == "autopilot-ok" and "LinkHealth" not in str(st)
        assert st["estimator"]["capture_to_send_ms_p50"] is not None
        assert 0.0 <= st["estimator"]["capture_to_send_ms_p50"] < 100.0
        texts = [m.fields["text"] for m in r.received("STATUSTEXT", t0) if "cam " in str(m.fields["text"])]
        assert len(texts) <= 2, texts  # the summary only when it changes, not every period
        assert not [m for m in r.received("STATUSTEXT") if "no autopilot heartbeat" in str(m.fields["text"])]
        line = r.daemon.status_line()
        assert "ardupilot" in line and "camera streaming" in line and "vision rack" in line
