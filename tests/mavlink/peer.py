"""A tiny scripted MAVLink peer on a loopback UDP socket (pymavlink on bytes), for the link's unit tests.

It plays the autopilot side only as far as a test needs: heartbeats on request, COMMAND_ACK with a
scripted result (or silence), TIMESYNC answers in its own time base, and it records what it got.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from drivers.mavlink.wire import FrameParser


@dataclass
class Received:
    time_s: float
    msg: Any


@dataclass
class Peer:
    """UDP 'autopilot' bound on 127.0.0.1:0; replies to whoever spoke last."""

    now_s: Callable[[], float]
    system_id: int = 1
    component_id: int = 1
    autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    custom_mode: int = 0
    armed: bool = False
    ack_result: dict[int, int | None] = field(default_factory=dict)  # command -> result; None = never answer
    ack_script: dict[int, list[int | None]] = field(default_factory=dict)  # command -> results for the next tries
    time_offset_s: float = 5000.0  # its clock = ours + offset
    answer_timesync: bool = True
    silent: bool = False  # drop everything it would send
    confirm_origin: bool = True  # answer SET_GPS_GLOBAL_ORIGIN with GPS_GLOBAL_ORIGIN
    received: list[Received] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.mav = mavlink.MAVLink(None, self.system_id, self.component_id)
        self.parser = FrameParser()
        self.transport: asyncio.DatagramTransport | None = None
        self.addr: Any = None
        self.port = 0

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        peer = self

        class Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: Any) -> None:
                peer.addr = addr
                for msg in peer.parser.feed(data):
                    peer._handle(msg)

        transport, _ = await loop.create_datagram_endpoint(Proto, local_addr=("127.0.0.1", 0))
        self.transport = transport
        self.port = transport.get_extra_info("sockname")[1]

    @property
    def url(self) -> str:
        return f"udpout:127.0.0.1:{self.port}"

    def start_heartbeats(self, clock: Any, period_s: float = 0.5) -> None:
        """Heartbeat every ``period_s`` of ``clock`` until `stop_heartbeats` (once someone spoke to us)."""

        async def beat() -> None:
            while True:
                if self.addr is not None:
                    self.heartbeat()
                await clock.sleep(period_s)

        self._beat_task = asyncio.ensure_future(beat())

    def stop_heartbeats(self) -> None:
        task = getattr(self, "_beat_task", None)
        if task is not None:
            task.cancel()

    def close(self) -> None:
        self.stop_heartbeats()
        if self.transport is not None:
            self.transport.close()

    def send(self, msg: Any) -> None:
        self.send_bytes(bytes(msg.pack(self.mav)))
        self.mav.seq = (self.mav.seq + 1) % 256

    def send_bytes(self, data: bytes) -> None:
        if self.silent:
            return
        assert self.transport is not None and self.addr is not None, "nobody to talk to yet"
        self.transport.sendto(data, self.addr)

    def heartbeat(self) -> None:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        self.send(
            self.mav.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, self.autopilot, base, self.custom_mode, mavlink.MAV_STATE_STANDBY
            )
        )

    def of_type(self, name: str) -> list[Received]:
        return [r for r in self.received if r.msg.get_type() == name]

    def _handle(self, msg: Any) -> None:
        self.received.append(Received(self.now_s(), msg))
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            script = self.ack_script.get(msg.command)
            if script:
                result = script.pop(0)
            else:
                result = self.ack_result.get(msg.command, mavlink.MAV_RESULT_ACCEPTED)
            if result is not None:
                self.send(self.mav.command_ack_encode(msg.command, result))
                if msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and result == 0:
                    self.armed = msg.param1 > 0.5
                if msg.command == mavlink.MAV_CMD_DO_SET_MODE and result == 0:
                    self.custom_mode = int(msg.param2)
        elif kind == "TIMESYNC" and msg.tc1 == 0 and self.answer_timesync:
            self.send(self.mav.timesync_encode(round((self.now_s() + self.time_offset_s) * 1e9), msg.ts1))
        elif kind == "SET_GPS_GLOBAL_ORIGIN" and self.confirm_origin:
            self.send(self.mav.gps_global_origin_encode(msg.latitude, msg.longitude, msg.altitude, 0))
