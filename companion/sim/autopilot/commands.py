"""The fake autopilot's incoming side: frame parsing, commands and their COMMAND_ACK results, setpoints,
vision, origin, TIMESYNC, PING and parameters."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.autopilot.config import (
    ACCEPTED,
    DEFAULT_RATES_HZ,
    FAILED,
    FORCE_MAGIC,
    MAX_PARSERS,
    MAX_RATE_HZ,
    REJECT_RESULTS,
    ReceivedMessage,
    msg_fields,
)
from companion.sim.autopilot.flight import Setpoint
from companion.sim.autopilot.profiles import ModeDef
from companion.sim.autopilot.telemetry import Telemetry
from companion.sim.autopilot.transport import PeerKey


class Commands(Telemetry):
    """Handles every message the fake receives."""

    # ----- receiving -------------------------------------------------------------------------

    def _on_bytes(self, data: bytes, peer: PeerKey) -> None:
        now = self.clock.now()
        if self._active("link-loss", now):
            self.stats["dropped_in"] += 1
            return
        parser = self._parsers.get(peer)
        if parser is None:
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            self._parsers[peer] = parser
            while len(self._parsers) > MAX_PARSERS:  # UDP senders come and go: forget the oldest
                del self._parsers[next(iter(self._parsers))]
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:
            self.stats["parse_errors"] += 1
            return
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.stats["parse_errors"] += 1
                continue
            self._incoming(msg, now)

    def _incoming(self, msg: Any, now_s: float) -> None:
        for f in self._active("message-loss", now_s):
            if f.params["direction"] in ("both", "in") and self._fault_rng.random() * 100.0 < float(
                f.params["percent"]
            ):
                self.stats["dropped_in"] += 1
                return
        delay_s = sum(
            float(f.params["ms"]) / 1000.0
            for f in self._active("latency", now_s)
            if f.params["direction"] in ("both", "in")
        )
        if delay_s > 0.0:
            self._later(delay_s, self._handle, msg)
        else:
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        now = self.clock.now()
        if self._started:
            self._advance_physics(now)
        msg_type = msg.get_type()
        record = ReceivedMessage(
            now, msg_type, msg_fields(msg), bytes(msg.get_msgbuf()), msg.get_srcSystem(), msg.get_srcComponent()
        )
        self._records.append(record)
        limit = self.config.max_records
        if limit is not None and len(self._records) > limit:
            # Trim in batches: deleting one record per message from the front of a 200k list is
            # O(n) each time. Between trims the list holds 15/16 .. 1 times `limit` records.
            del self._records[: len(self._records) - limit + limit // 16]
        self.stats["received"] += 1
        self._record_event.set()
        handler = getattr(self, "_on_" + msg_type.lower(), None)
        if handler is not None:
            try:
                handler(msg, now)
            except (ValueError, TypeError, OverflowError, AttributeError):
                # A malformed but CRC-valid message (NaN where an integer belongs, ...) is ignored.
                self.stats["parse_errors"] += 1
        self._flush_events()

    def _for_me(self, msg: Any) -> bool:
        target_system = getattr(msg, "target_system", 0)
        target_component = getattr(msg, "target_component", 0)
        return target_system in (0, self.config.system_id) and target_component in (0, self.config.component_id)

    def _ack(self, command: int, result: int, msg: Any) -> None:
        self._send(self._mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_command_long(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._command(msg, int(msg.command), tuple(float(x) for x in params), now_s)

    def _on_command_int(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x / 1e7, msg.y / 1e7, msg.z)
        self._command(msg, int(msg.command), params, now_s)

    def _rejection(self, command: int, now_s: float) -> int | None:
        """The scripted answer to `command` (None = no fault; -1 = do not answer)."""
        for f in self._active("command-reject", now_s):
            commands = f.params["commands"]
            if commands is None or command in commands:
                result = f.params["result"]
                return -1 if result == "timeout" else int(REJECT_RESULTS[result])
        return None

    def _command(self, msg: Any, command: int, p: tuple[float, ...], now_s: float) -> None:
        rejection = self._rejection(command, now_s)
        if rejection is not None:
            if rejection >= 0:
                self._ack(command, rejection, msg)
            return
        flight, vehicle = self._flight, self._vehicle
        ardupilot = self.profile.name == "ardupilot"
        result: int
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = math.isfinite(p[1]) and round(p[1]) == FORCE_MAGIC
            if ardupilot and p[0] not in (0.0, 1.0):
                result = mavlink.MAV_RESULT_UNSUPPORTED  # ArduPilot: param1 must be exactly 0 or 1
            elif p[0] >= 0.5:
                was_armed = flight.armed
                result, _ = flight.arm(now_s, vehicle, force)
                if ardupilot and flight.armed and not was_armed and flight.home_set:
                    self._send_home()  # arming moves home to the vehicle (AP_AHRS::set_home)
            else:
                result, _ = flight.disarm(now_s, vehicle, force)
        elif command == mavlink.MAV_CMD_DO_SET_MODE:
            mode = self.profile.mode_from_do_set_mode(p[0], p[1], p[2])
            if mode is None and ardupilot and math.isfinite(p[1]):
                flight.events.append((mavlink.MAV_SEVERITY_WARNING, f"No such mode {int(p[1])}"))
            result = mavlink.MAV_RESULT_FAILED if mode is None else flight.set_mode(mode, now_s, vehicle)[0]
        elif command == mavlink.MAV_CMD_NAV_TAKEOFF:
            result, _ = flight.takeoff(self._takeoff_height(p[6]), now_s, vehicle)
        elif command == mavlink.MAV_CMD_NAV_LAND:
            result, _ = flight.land(now_s, vehicle)
        elif command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            result, _ = flight.set_mode(self.profile.mode(self.profile.rtl_mode), now_s, vehicle)
        elif command == mavlink.MAV_CMD_NAV_LOITER_UNLIM:
            result, _ = flight.set_mode(self.profile.mode(self.profile.hold_mode), now_s, vehicle)
        elif command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(int(p[0]), p[1], now_s)
        elif command == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            result = self._get_interval(int(p[0]))
        elif command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            result = self._request_message(int(p[0]), now_s)
        elif command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result = self._request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, now_s)
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        self._ack(command, result, msg)

    def _takeoff_height(self, param7: float) -> float:
        if not math.isfinite(param7):
            return float(self._params.get("MIS_TAKEOFF_ALT", self._flight.params.default_takeoff_height_m))
        if self.profile.name == "px4" and self._origin is not None:
            return param7 - self._origin[2]  # PX4 takes an AMSL altitude
        return param7

    def _message_name(self, msg_id: int) -> str | None:
        cls = mavlink.mavlink_map.get(msg_id)
        return None if cls is None else str(cls.msgname)

    def _set_interval(self, msg_id: int, interval_us: float, now_s: float) -> int:
        name = self._message_name(msg_id)
        if name is None or (name not in self._streams):
            # ArduPilot answers DENIED for a message it cannot stream (unknown id included)
            return mavlink.MAV_RESULT_DENIED if self.profile.name == "ardupilot" else FAILED
        stream = self._streams[name]
        if interval_us < 0:
            stream.interval_s = 0.0
        elif interval_us == 0:
            rates = dict(DEFAULT_RATES_HZ[self.profile.name])
            rates.update(self.config.rates_hz or {})
            stream.interval_s = self._interval(rates.get(name, 1.0))
        else:
            interval_s = interval_us / 1e6
            if self.profile.name == "ardupilot":
                interval_s = max(round(interval_s * 1000.0), 1) / 1000.0  # ArduPilot keeps whole ms
            stream.interval_s = max(interval_s, 1.0 / MAX_RATE_HZ)
        stream.next_due_s = now_s
        self._wake.set()
        return ACCEPTED

    def _get_interval(self, msg_id: int) -> int:
        name = self._message_name(msg_id)
        if name is None or name not in self._streams:
            return FAILED
        stream = self._streams[name]
        interval_us = -1 if stream.interval_s <= 0.0 else int(stream.interval_s * 1e6)
        self._send(self._mav.message_interval_encode(msg_id, interval_us))
        return ACCEPTED

    def _request_message(self, msg_id: int, now_s: float) -> int:
        name = self._message_name(msg_id)
        if name is None:
            return FAILED
        out = self._build(name, now_s)
        if out is None:
            # ArduPilot accepts a known message it has nothing to send yet (e.g. HOME_POSITION before home)
            return ACCEPTED if self.profile.name == "ardupilot" and name in self._streams else FAILED
        self._send(out)
        return ACCEPTED

    def _on_set_mode(self, msg: Any, now_s: float) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        rejection = self._rejection(mavlink.MAVLINK_MSG_ID_SET_MODE, now_s)
        ack_command = (
            mavlink.MAVLINK_MSG_ID_SET_MODE if self.profile.name == "ardupilot" else mavlink.MAV_CMD_DO_SET_MODE
        )
        if rejection is not None:
            if rejection >= 0:
                self._ack(ack_command, rejection, msg)
            return
        mode: ModeDef | None = None
        if msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            mode = self.profile.mode_from_custom(int(msg.custom_mode))
        if mode is None:
            self._ack(ack_command, mavlink.MAV_RESULT_FAILED, msg)
            return
        result, _ = self._flight.set_mode(mode, now_s, self._vehicle)
        self._ack(ack_command, result, msg)

    def _on_set_position_target_local_ned(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        mask = int(msg.type_mask)
        frame = int(msg.coordinate_frame)
        if frame not in (
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
            mavlink.MAV_FRAME_BODY_NED,
            mavlink.MAV_FRAME_BODY_OFFSET_NED,
        ):
            return
        vehicle = self._vehicle
        body = frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
        offset = frame in (mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
        c, s = math.cos(vehicle.yaw_rad), math.sin(vehicle.yaw_rad)

        def rotate(x: float, y: float) -> tuple[float, float]:
            return (c * x - s * y, s * x + c * y) if body else (x, y)

        velocity = None
        if not mask & 0b111000:
            vn, ve = rotate(msg.vx, msg.vy)
            velocity = (vn, ve, float(msg.vz))
        position = None
        if not mask & 0b111:
            pn, pe = rotate(msg.x, msg.y)
            if offset or body:
                p0 = vehicle.position_ned_m
                position = (p0[0] + pn, p0[1] + pe, p0[2] + float(msg.z))
            else:
                position = (pn, pe, float(msg.z))
        yaw = None if mask & 1024 else float(msg.yaw)
        yaw_rate = None if mask & 2048 else float(msg.yaw_rate)
        values = [
            *(velocity or ()),
            *(position or ()),
            *([yaw] if yaw is not None else []),
            *([yaw_rate] if yaw_rate is not None else []),
        ]
        if not all(math.isfinite(x) for x in values):
            return
        self._flight.on_setpoint(Setpoint(now_s, velocity, position, yaw, yaw_rate))

    def _vision(self, now_s: float) -> None:
        if not self._active("vision-reject", now_s):
            first = self._flight.ekf.last_vision_s is None
            self._flight.on_vision(now_s)
            if first and self.profile.name == "ardupilot":
                self._flight.events.append((mavlink.MAV_SEVERITY_INFO, "EKF3 IMU0 is using external nav data"))
            self._check_home(now_s)

    def _check_home(self, now_s: float) -> None:
        """Home is set once the EKF has an origin and a position; ArduPilot then sends HOME_POSITION
        (the SITL: 50 ms after the first vision pose, or after the origin if vision came first)."""
        flight = self._flight
        if not flight.home_set and self._origin is not None and flight.ekf.has_position(now_s):
            flight.home_set = True
            if self.profile.name == "ardupilot":
                self._send_home()

    def _send_home(self) -> None:
        """ArduPilot sends HOME_POSITION and GPS_GLOBAL_ORIGIN whenever home is set (AP_AHRS::set_home;
        the SITL: at the first pose and at each arming)."""
        now_s = self.clock.now()
        self._send_stream("HOME_POSITION", now_s)
        self._send_stream("GPS_GLOBAL_ORIGIN", now_s)

    def _on_vision_position_estimate(self, msg: Any, now_s: float) -> None:
        if all(math.isfinite(x) for x in (msg.x, msg.y, msg.z)):
            self._vision(now_s)

    def _on_odometry(self, msg: Any, now_s: float) -> None:
        if all(math.isfinite(x) for x in (msg.x, msg.y, msg.z)):
            self._vision(now_s)

    def _on_att_pos_mocap(self, msg: Any, now_s: float) -> None:
        self._vision(now_s)

    def _on_set_gps_global_origin(self, msg: Any, now_s: float) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        if self._origin is None:
            self._origin = (msg.latitude / 1e7, msg.longitude / 1e7, msg.altitude / 1000.0)
            text = "EKF3 IMU0 origin set" if self.profile.name == "ardupilot" else "EKF origin set"
            self._flight.events.append((mavlink.MAV_SEVERITY_INFO, text))
        # Settable once: later requests only repeat the origin in use.
        self._send_stream("GPS_GLOBAL_ORIGIN", now_s)
        self._check_home(now_s)

    def _on_ping(self, msg: Any, now_s: float) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            self._send(self._mav.ping_encode(msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_timesync(self, msg: Any, now_s: float) -> None:
        if msg.tc1 == 0:
            self._send(self._mav.timesync_encode(round((now_s - self._boot_s) * 1e9), msg.ts1))

    def _on_param_request_read(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        names = sorted(self._params)
        name = (
            msg.param_id if msg.param_index < 0 else (names[msg.param_index] if msg.param_index < len(names) else None)
        )
        if isinstance(name, bytes):
            name = name.decode(errors="replace")
        if name in self._params:
            self._send_param(str(name))

    def _on_param_request_list(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        for name in sorted(self._params):
            self._send_param(name)

    def _on_param_set(self, msg: Any, now_s: float) -> None:
        if not self._for_me(msg):
            return
        name = msg.param_id.decode(errors="replace") if isinstance(msg.param_id, bytes) else str(msg.param_id)
        if name not in self._params or not math.isfinite(msg.param_value):
            return
        self._params[name] = float(msg.param_value)
        if name in ("FS_EKF_ACTION", "FS_EKF_THRESH"):
            if name == "FS_EKF_THRESH":
                self._flight.params = dataclasses.replace(self._flight.params, fs_ekf_thresh=float(msg.param_value))
            elif round(msg.param_value) in (1, 2, 3):
                self._flight.params = dataclasses.replace(self._flight.params, fs_ekf_action=round(msg.param_value))
            else:
                return
        if name == "MIS_TAKEOFF_ALT":
            self._flight.params = dataclasses.replace(
                self._flight.params, default_takeoff_height_m=float(msg.param_value)
            )
        self._send_param(name)

    def _send_param(self, name: str) -> None:
        names = sorted(self._params)
        self._send(
            self._mav.param_value_encode(
                name.encode(), self._params[name], mavlink.MAV_PARAM_TYPE_REAL32, len(names), names.index(name)
            )
        )
