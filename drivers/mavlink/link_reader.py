"""`ReaderMixin`: the receive path of `MavLink`: bytes from the autopilot's transport and from the GCS forwards
through the frame parser into the `StateTracker`, COMMAND_ACK and TIMESYNC handling, the autopilot's
(re)appearance, and the IMU and message callbacks."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from drivers.mavlink.link_commands import CommandsMixin
from drivers.mavlink.link_core import log
from drivers.mavlink.sendqueue import Priority
from drivers.mavlink.transport import Transport
from drivers.mavlink.wire import FrameParser

__all__ = ["ReaderMixin"]


class ReaderMixin(CommandsMixin):
    """Reader of `MavLink`; on `CommandsMixin` because an autopilot that (re)appears gets its message intervals
    requested."""

    # ---------------------------------------------------------------- reader
    def _receive(self, data: bytes) -> None:
        now = self._clock.now()
        msgs = self._parser.feed(data, datagram=self._transport.datagram)
        if not self._warned_mavlink1 and self._parser.counters.mavlink1_rejected:
            self._warned_mavlink1 = True  # a misconfigured port looks like a dead link otherwise
            log.warning(
                "MAVLink 1 frames on %s are ignored: configure the autopilot port for MAVLink 2 "
                "(ArduPilot SERIALn_PROTOCOL=2) or set accept_mavlink1",
                self.config.url,
            )
        from_autopilot = False
        for msg in msgs:
            if self._tlog is not None:
                self._tlog.write(bytes(msg.get_msgbuf()))
            if self._forwards:
                frame = bytes(msg.get_msgbuf())
                for t, _ in self._forwards:
                    if t.write(frame):
                        self._counts["forwarded_to_gcs"] += 1
            self._handle(msg, now)
            from_autopilot = from_autopilot or self._tracker.autopilot_address == (
                msg.get_srcSystem(),
                msg.get_srcComponent(),
            )
        if from_autopilot:  # udpin answers the autopilot's address; another sender cannot take the link
            self._transport.accept_last_source()

    def _forward_receiver(self, transport: Transport, parser: FrameParser) -> Callable[[bytes], None]:
        def receive(data: bytes) -> None:
            now = self._clock.now()
            msgs = parser.feed(data, datagram=transport.datagram)
            if msgs:
                transport.accept_last_source()
            for msg in msgs:
                frame = bytes(msg.get_msgbuf())
                self._enqueue(frame, Priority.CONTROL)
                self._counts["forwarded_to_autopilot"] += 1
                if msg.get_type() == "HEARTBEAT":
                    self._tracker.apply(msg, now)
                elif msg.get_type() == "COMMAND_LONG":  # may be for one of our components (camera discovery)
                    for mcb in list(self._message_callbacks):
                        self._call(mcb, msg)

        return receive

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        address = self._tracker.autopilot_address
        if address is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == address:
            self._last_autopilot_rx_s = now
        try:
            imu = self._tracker.apply(msg, now)
        except Exception:  # a decoder bug must not kill the reader; count and go on
            self._counts["callback_errors"] += 1
            n = self._counts["callback_errors"]
            if n <= 10 or n % 1000 == 0:
                log.exception("decoding %s failed (%d callback errors so far)", kind, n)
            imu = None
        if kind == "HEARTBEAT":
            new_address = self._tracker.autopilot_address
            if (
                new_address is not None
                and self.state.last_autopilot_heartbeat_s == now
                and (new_address[0] == msg.get_srcSystem() and new_address[1] == msg.get_srcComponent())
            ):
                self._last_autopilot_rx_s = now
                self._autopilot_heartbeat(new_address)
        elif kind == "TIMESYNC":
            self._handle_timesync(msg, now)
        elif (
            kind == "COMMAND_ACK"
            and address is not None
            and (msg.get_srcSystem(), msg.get_srcComponent()) == address
            and self._ack_is_for_us(msg)
        ):
            fut = self._pending_acks.get(int(msg.command))
            if fut is not None and not fut.done():
                fut.set_result(int(msg.result))
        if imu is not None:
            for cb in list(self._imu_callbacks):
                self._call(cb, imu)
        for mcb in list(self._message_callbacks):
            self._call(mcb, msg)

    def _ack_is_for_us(self, msg: Any) -> bool:
        """COMMAND_ACK target ids: ArduPilot and PX4 address the sender of the command; 0 = not filled in
        (older firmware). An ACK of the same command sent by a GCS (e.g. through our forwarding) is not ours."""
        target_system = int(getattr(msg, "target_system", 0) or 0)
        target_component = int(getattr(msg, "target_component", 0) or 0)
        return target_system in (0, self._encoder.system_id) and target_component in (0, self._encoder.component_id)

    def _autopilot_heartbeat(self, address: tuple[int, int]) -> None:
        if self.config.system_id is None and self._encoder.system_id != address[0]:
            self._encoder.system_id = address[0]
        self._silent_reconnects = 0
        if not self._autopilot_present:
            self._autopilot_present = True
            if self._autopilot_since_s is None:
                self._autopilot_since_s = self._clock.now()
            self._autopilot_seen.set()
            if self._interval_task is None or self._interval_task.done():
                self._interval_task = asyncio.get_running_loop().create_task(
                    self._request_intervals(), name="mavlink-intervals"
                )
            if self._velocity_cmd is not None:
                self._setpoint_wake.set()

    def _handle_timesync(self, msg: Any, now: float) -> None:
        if msg.tc1 == 0:
            self._enqueue(self._encoder.timesync(max(1, round(now * 1e9)), msg.ts1), Priority.CONTROL)
            self._counts["timesync_answered"] += 1
        elif (msg.get_srcSystem(), msg.get_srcComponent()) == self._tracker.autopilot_address:
            self._timesync.add_response(int(msg.tc1), int(msg.ts1), now)
