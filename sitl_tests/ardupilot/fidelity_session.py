"""One scripted MAVLink session for comparing the fake autopilot with the real ArduCopter SITL.

The same script runs against both peers over TCP: against the real SITL in real time
(`SystemClock`), against `companion fake-autopilot`'s ArduPilot profile on a `ManualClock`
(the script itself moves the clock, so the session takes seconds of CPU). It records what the
autopilot answered and when, as a JSON-able dict of observations (values + times in s).

    python sitl_tests/ardupilot/fidelity_session.py --record OUT.json   # against a fresh real SITL

Phases: boot and message intervals (known and unknown ids), GET/REQUEST_MESSAGE, EKF flags before
vision, GUIDED and ARM before the EKF is ready, origin → GPS_GLOBAL_ORIGIN / HOME_POSITION,
external vision (VISION_POSITION_ESTIMATE at ~30 Hz from the SIM_STATE truth in the origin's NED),
time to pre-arm ready, TIMESYNC both ways, denied/unsupported commands, arm + NAV_TAKEOFF 1 m,
a velocity step and the GUIDED setpoint timeout, a 3 s vision dropout in flight, LAND, then a long
vision loss in flight (who lands the vehicle, and when).
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import math
import socket
import statistics
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

EARTH_RADIUS_M = 6378137.0
GCS_SYSID, GCS_COMPID = 255, 190
CUSTOM = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
GUIDED, LAND = 4.0, 9.0
UNKNOWN_MSG_ID = 9999  # not a MAVLink message
UNSTREAMABLE_MSG_ID = mavlink.MAVLINK_MSG_ID_HIL_STATE  # a real message no autopilot streams
UNKNOWN_COMMAND = 12345  # not a MAV_CMD
TICK_S = 1.0 / 30.0  # the script's step: vision and heartbeat go out on it
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK

Sleep = Callable[[float], Awaitable[None]]


class Peer:
    """A MAVLink 2 client on a non-blocking TCP socket; every message is stamped with `now()` on arrival.

    Answers the autopilot's own TIMESYNC requests (tc1 = 0) at once, as a companion would.
    """

    def __init__(self, url: str, now: Callable[[], float], pause: Sleep) -> None:
        scheme, host, port = url.split(":")
        if scheme != "tcp":
            raise ValueError(f"fidelity session needs a tcp:HOST:PORT url, got {url!r}")
        self.sock = socket.create_connection((host, int(port)), timeout=10.0)
        self.sock.setblocking(False)
        self.now, self._pause = now, pause
        self.t0 = now()
        self.mav = mavlink.MAVLink(None, srcSystem=GCS_SYSID, srcComponent=GCS_COMPID)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.log: list[tuple[float, Any]] = []  # (s since t0, message) from the autopilot
        self.ap_timesync_requests: list[float] = []
        self.vision_on = False
        self.origin: tuple[float, float, float] | None = None
        self.truth: Any = None  # the newest SIM_STATE
        self._next_hb = 0.0
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.sock.fileno(), self._read)

    # ----- I/O ---------------------------------------------------------------------------

    def t(self) -> float:
        return self.now() - self.t0

    def _read(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            if not data:
                return
            for msg in self.parser.parse_buffer(data) or []:
                if msg.get_type() == "BAD_DATA" or msg.get_srcSystem() != 1:
                    continue
                t = self.t()
                self.log.append((t, msg))
                kind = msg.get_type()
                if kind == "SIM_STATE":
                    self.truth = msg
                elif kind == "TIMESYNC" and msg.tc1 == 0:
                    self.ap_timesync_requests.append(t)
                    self.send(self.mav.timesync_encode(round(self.t() * 1e9), msg.ts1))

    def send(self, msg: Any) -> None:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.sock.sendall(buf)

    def close(self) -> None:
        self._loop.remove_reader(self.sock.fileno())
        self.sock.close()

    async def step(self) -> None:
        """One tick: GCS heartbeat at 1 Hz, a vision pose when vision is on, then let time pass."""
        t = self.t()
        if t >= self._next_hb:
            self.send(self.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3))
            self._next_hb = t + 1.0
        if self.vision_on:
            self._send_vision()
        await self._pause(TICK_S)
        self._read()

    async def run_for(self, seconds: float) -> None:
        end = self.t() + seconds
        while self.t() < end:
            await self.step()

    async def wait(self, pred: Callable[[], Any], timeout_s: float) -> Any:
        """Step until `pred()` is truthy (returned) or the timeout (None)."""
        end = self.t() + timeout_s
        while True:
            value = pred()
            if value:
                return value
            if self.t() >= end:
                return None
            await self.step()

    # ----- helpers -----------------------------------------------------------------------

    def since(self, t: float, kind: str) -> list[tuple[float, Any]]:
        return [(tm, m) for tm, m in self.log if tm >= t and m.get_type() == kind]

    def last(self, kind: str) -> Any:
        for _, m in reversed(self.log):
            if m.get_type() == kind:
                return m
        return None

    def command(self, command: int, *params: float) -> float:
        p = [*params, *([0.0] * (7 - len(params)))]
        t = self.t()
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))
        return t

    async def ack(self, command: int, t_sent: float, timeout_s: float = 3.0) -> int | None:
        found = await self.wait(
            lambda: next((m for _, m in self.since(t_sent, "COMMAND_ACK") if m.command == command), None), timeout_s
        )
        return None if found is None else int(found.result)

    async def command_result(self, command: int, *params: float) -> int | None:
        return await self.ack(command, self.command(command, *params))

    def mode(self) -> int | None:
        hb = self.last("HEARTBEAT")
        return None if hb is None else int(hb.custom_mode)

    def armed(self) -> bool:
        hb = self.last("HEARTBEAT")
        return hb is not None and bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def texts(self, t_from: float, t_to: float = math.inf) -> list[str]:
        return [m.text for tm, m in self.since(t_from, "STATUSTEXT") if tm <= t_to]

    def ekf_flags(self) -> int | None:
        m = self.last("EKF_STATUS_REPORT")
        return None if m is None else int(m.flags)

    def height_m(self) -> float | None:
        """True height above the resting height (SIM_STATE altitude)."""
        if self.truth is None or self.origin is None:
            return None
        return float(self.truth.alt) - self.origin[2]

    def truth_ned(self, msg: Any) -> tuple[float, float, float]:
        assert self.origin is not None
        lat0, lon0, alt0 = self.origin
        lat, lon = _latlon(msg)
        north = math.radians(lat - lat0) * EARTH_RADIUS_M
        east = math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
        return north, east, alt0 - float(msg.alt)

    def _send_vision(self) -> None:
        m = self.truth
        if m is None or self.origin is None:
            return
        n, e, d = self.truth_ned(m)
        cov = [0.0025, 0, 0, 0, 0, 0, 0.0025, 0, 0, 0, 0, 0.0025, 0, 0, 0, 0.0003, 0, 0, 0.0003, 0, 0.0003]
        usec = round(self.t() * 1e6)
        self.send(self.mav.vision_position_estimate_encode(usec, n, e, d, m.roll, m.pitch, m.yaw, cov, 0))

    def velocity(self, vn: float, ve: float, vd: float) -> None:
        mask = 0b0000_1101_1100_0111  # velocity only, no yaw, no yaw rate
        self.send(self.mav.set_position_target_local_ned_encode(0, 1, 1, 1, mask, 0, 0, 0, vn, ve, vd, 0, 0, 0, 0, 0))

    def set_interval(self, msg_id: int, hz: float) -> float:
        return self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), 1e6 / hz)


def _latlon(msg: Any) -> tuple[float, float]:
    lat_int, lon_int = getattr(msg, "lat_int", 0), getattr(msg, "lon_int", 0)
    if lat_int or lon_int:
        return lat_int / 1e7, lon_int / 1e7
    return float(msg.lat), float(msg.lon)


def _r(x: float | None, nd: int = 3) -> float | None:
    return None if x is None else round(float(x), nd)


def _landed_sequence(peer: Peer, t_from: float) -> list[int]:
    seq: list[int] = []
    for _, m in peer.since(t_from, "EXTENDED_SYS_STATE"):
        if not seq or seq[-1] != m.landed_state:
            seq.append(int(m.landed_state))
    return seq


def _flag_sequence(peer: Peer, t_from: float, t_to: float) -> list[int]:
    seq: list[int] = []
    for tm, m in peer.since(t_from, "EKF_STATUS_REPORT"):
        if tm <= t_to and (not seq or seq[-1] != m.flags):
            seq.append(int(m.flags))
    return seq


async def _disarm_time(peer: Peer, t_from: float, timeout_s: float) -> float | None:
    """When the autopilot disarmed: its "Disarming motors" text (HEARTBEAT comes at 1 Hz only), else the
    first disarmed HEARTBEAT."""
    def seen() -> float | None:
        texts = [tm for tm, m in peer.since(t_from, "STATUSTEXT") if m.text.startswith("Disarming motors")]
        if texts:
            return texts[0]
        return peer.t() if not peer.armed() else None

    found = await peer.wait(seen, timeout_s)
    return None if found is None else float(found)


async def _hover_height(peer: Peer) -> float:
    await peer.step()
    h = peer.height_m()
    return 0.0 if h is None else h


async def run_session(url: str, now: Callable[[], float], pause: Sleep, long_dropout: bool = True) -> dict[str, Any]:
    """Run the scripted session against the autopilot at `url` (tcp:HOST:PORT); return the observations.

    `now()` is the clock in s, `pause(s)` lets that much time pass (asyncio.sleep for a real peer, a
    ManualClock's advance for the fake). Times in the result are s; heights m; speeds m/s.
    """
    peer = Peer(url, now, pause)
    obs: dict[str, Any] = {}
    try:
        await _session(peer, obs, long_dropout)
    finally:
        obs["autopilot_timesync"] = _timesync_summary(peer.ap_timesync_requests)
        obs["timeline"] = _timeline(peer)
        obs["message_counts"] = _message_counts(peer)
        obs["session_s"] = _r(peer.t())
        peer.close()
    return obs


def _message_counts(peer: Peer) -> dict[str, int]:
    """How many of each message type the autopilot sent over the session (asked for or not)."""
    counts: dict[str, int] = {}
    for _, m in peer.log:
        counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
    return dict(sorted(counts.items()))


def _timeline(peer: Peer) -> dict[str, list[list[float]]]:
    """When the EKF flags, the mode, the armed state and the landed state changed: [[t_s, value], ...]."""
    series: dict[str, list[list[float]]] = {"ekf_flags": [], "mode": [], "armed": [], "landed_state": []}
    for tm, m in peer.log:
        kind = m.get_type()
        values = []
        if kind == "EKF_STATUS_REPORT":
            values = [("ekf_flags", int(m.flags))]
        elif kind == "HEARTBEAT":
            values = [("mode", int(m.custom_mode)), ("armed", int(bool(m.base_mode & 128)))]
        elif kind == "EXTENDED_SYS_STATE":
            values = [("landed_state", int(m.landed_state))]
        for key, value in values:
            if not series[key] or series[key][-1][1] != value:
                series[key].append([round(tm, 3), value])
    return series


def _timesync_summary(times: list[float]) -> dict[str, Any]:
    gaps = [b - a for a, b in itertools.pairwise(times)]
    return {"count": len(times), "median_interval_s": _r(statistics.median(gaps)) if gaps else None}


async def _session(peer: Peer, obs: dict[str, Any], long_dropout: bool) -> None:
    # --- boot ---------------------------------------------------------------------------------
    hb = await peer.wait(lambda: peer.last("HEARTBEAT"), 60.0)
    if hb is None:
        raise RuntimeError("no HEARTBEAT from the autopilot in 60 s")
    obs["boot"] = {"first_heartbeat_s": _r(peer.t()), "mode": int(hb.custom_mode), "autopilot": int(hb.autopilot),
                   "type": int(hb.type), "armed": peer.armed()}
    # --- message intervals, GET / REQUEST_MESSAGE ---------------------------------------------
    intervals: dict[str, Any] = {}
    for name, msg_id, hz in (("SIM_STATE", mavlink.MAVLINK_MSG_ID_SIM_STATE, 30.0),
                             ("EKF_STATUS_REPORT", mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 4.0),
                             ("EXTENDED_SYS_STATE", mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5.0),
                             ("SYS_STATUS", mavlink.MAVLINK_MSG_ID_SYS_STATUS, 2.0),
                             ("LOCAL_POSITION_NED", mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10.0),
                             ("unknown_9999", UNKNOWN_MSG_ID, 10.0),
                             ("HIL_STATE", UNSTREAMABLE_MSG_ID, 10.0)):
        intervals[name] = await peer.ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, peer.set_interval(msg_id, hz))
    obs["set_message_interval"] = intervals
    t = peer.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, float(mavlink.MAVLINK_MSG_ID_SIM_STATE))
    res = await peer.ack(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, t)
    mi = [m for _, m in peer.since(t, "MESSAGE_INTERVAL") if m.message_id == mavlink.MAVLINK_MSG_ID_SIM_STATE]
    obs["get_message_interval"] = {
        "SIM_STATE": res,
        "SIM_STATE_interval_us": int(mi[0].interval_us) if mi else None,
        "unknown_9999": await peer.command_result(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, float(UNKNOWN_MSG_ID)),
    }
    req: dict[str, Any] = {}
    for name, msg_id in (("AUTOPILOT_VERSION", mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION),
                         ("GPS_GLOBAL_ORIGIN_before_origin", mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN),
                         ("HOME_POSITION_before_origin", mavlink.MAVLINK_MSG_ID_HOME_POSITION),
                         ("unknown_9999", UNKNOWN_MSG_ID)):
        t = peer.t()
        req[name] = await peer.command_result(mavlink.MAV_CMD_REQUEST_MESSAGE, float(msg_id))
        await peer.run_for(0.3)
        kind = name.split("_before")[0]
        req[name + "_sent"] = bool(peer.since(t, kind)) if kind != "unknown_9999" else None
    obs["request_message"] = req
    # rates actually seen over 3 s
    t = peer.t()
    await peer.run_for(3.0)
    obs["rates_hz"] = {k: _r(len(peer.since(t, k)) / 3.0, 1) for k in ("SIM_STATE", "HEARTBEAT")}
    obs["local_position_before_vision"] = len(peer.since(0.0, "LOCAL_POSITION_NED")) > 0
    # --- before vision ------------------------------------------------------------------------
    obs["ekf_flags_at_boot"] = peer.ekf_flags()
    sys_status = peer.last("SYS_STATUS")
    obs["prearm_ok_before_vision"] = bool(sys_status.onboard_control_sensors_health & PREARM) if sys_status else None
    t = peer.command(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, GUIDED)
    obs["guided_before_ready"] = {"result": await peer.ack(mavlink.MAV_CMD_DO_SET_MODE, t)}
    await peer.run_for(1.5)
    obs["guided_before_ready"]["mode_after"] = peer.mode()
    t = peer.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    arm_result = await peer.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, t)
    await peer.run_for(1.5)
    obs["arm_before_ready"] = {"result": arm_result, "texts": sorted(set(peer.texts(t))), "armed": peer.armed()}
    # --- origin -------------------------------------------------------------------------------
    truth = await peer.wait(lambda: peer.truth, 10.0)
    if truth is None:
        raise RuntimeError("no SIM_STATE: cannot place the origin")
    lat0, lon0 = _latlon(truth)
    peer.origin = (lat0, lon0, float(truth.alt))
    t = peer.t()
    peer.send(peer.mav.set_gps_global_origin_encode(1, round(lat0 * 1e7), round(lon0 * 1e7),
                                                    round(peer.origin[2] * 1000), round(t * 1e6)))
    await peer.run_for(3.0)
    ggo = peer.since(t, "GPS_GLOBAL_ORIGIN")
    home = peer.since(t, "HOME_POSITION")
    assert peer.origin is not None
    obs["origin"] = {"gps_global_origin_after_s": _r(ggo[0][0] - t) if ggo else None,
                     "home_position_after_s": _r(home[0][0] - t) if home else None,
                     "texts": peer.texts(t)}
    obs["ekf_flags_before_vision"] = peer.ekf_flags()
    t_origin = t
    # --- vision and alignment -----------------------------------------------------------------
    peer.vision_on = True
    t_vision = peer.t()
    # TIMESYNC from our side during the alignment: tc1 = the autopilot's clock, ts1 echoed
    t = peer.t()
    ts1 = 123_456_789_000
    peer.send(peer.mav.timesync_encode(0, ts1))
    reply = await peer.wait(lambda: next((m for _, m in peer.since(t, "TIMESYNC") if m.ts1 == ts1 and m.tc1 != 0),
                                         None), 3.0)
    obs["timesync_reply"] = {"answered": reply is not None}
    # denied / unsupported commands, on the ground while the EKF aligns
    denied: dict[str, Any] = {}
    denied["arm_param1_2"] = await peer.command_result(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 2.0)
    denied["unknown_command"] = await peer.command_result(UNKNOWN_COMMAND)
    denied["set_mode_unknown_custom_99"] = await peer.command_result(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, 99.0)
    denied["takeoff_disarmed"] = await peer.command_result(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0)
    denied["disarm_when_disarmed"] = await peer.command_result(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
    obs["commands_on_ground"] = denied
    # ARM while the EKF aligns on vision (origin set, vision flowing, not yet ready)
    await peer.wait(lambda: peer.t() >= t_vision + 4.0, 10.0)
    t = peer.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    arm_result = await peer.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, t)
    await peer.run_for(1.0)
    obs["arm_during_alignment"] = {"result": arm_result, "texts": sorted(set(peer.texts(t, t + 1.0))),
                                   "armed": peer.armed()}

    def prearm_ok() -> bool:
        s = peer.last("SYS_STATUS")
        return s is not None and bool(s.onboard_control_sensors_health & PREARM) and peer.t() > t_vision + 0.2

    ready = await peer.wait(prearm_ok, 60.0)
    t_ready = peer.t()
    obs["alignment"] = {
        "prearm_ready_after_vision_s": _r(t_ready - t_vision) if ready else None,
        "ekf_flags_sequence": _flag_sequence(peer, t_vision, t_ready + 0.5),
        "local_position_after_vision_s": _r(lp[0][0] - t_vision) if (lp := peer.since(t_vision, "LOCAL_POSITION_NED"))
        else None,
        "texts": peer.texts(t_vision, t_ready),
    }
    await peer.run_for(1.0)
    obs["ekf_flags_with_vision"] = peer.ekf_flags()
    homes = peer.since(t_origin, "HOME_POSITION")
    obs["home_position"] = {"first_after_origin_s": _r(homes[0][0] - t_origin) if homes else None,
                            "first_after_vision_s": _r(homes[0][0] - t_vision) if homes else None,
                            "before_ready": bool(homes) and homes[0][0] <= t_ready + 0.5}
    # --- arm and take off ---------------------------------------------------------------------
    t = peer.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    arm = {"result": await peer.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, t)}
    armed_at = await peer.wait(lambda: peer.t() if peer.armed() else None, 3.0)
    arm["armed_after_s"] = _r(armed_at - t) if armed_at else None
    arm["mode"] = peer.mode()
    obs["arm"] = arm
    if not peer.armed():
        raise RuntimeError(f"could not arm: {peer.texts(t)}")
    t_to = peer.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0)
    take: dict[str, Any] = {"result": await peer.ack(mavlink.MAV_CMD_NAV_TAKEOFF, t_to)}
    left = await peer.wait(lambda: peer.t() if (peer.height_m() or 0.0) > 0.05 else None, 15.0)
    reached = await peer.wait(lambda: peer.t() if (peer.height_m() or 0.0) >= 0.95 else None, 15.0)
    await peer.run_for(3.0)
    take.update({"left_ground_s": _r(left - t_to) if left else None,
                 "reached_95pct_s": _r(reached - t_to) if reached else None,
                 "height_after_3s_m": _r(peer.height_m()),
                 "landed_states": _landed_sequence(peer, t_to),
                 "mode": peer.mode()})
    obs["takeoff"] = take
    # --- denied in flight ---------------------------------------------------------------------
    obs["commands_in_flight"] = {
        "takeoff_while_flying": await peer.command_result(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0),
        "arm_while_armed": await peer.command_result(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0),
    }
    await peer.run_for(1.0)
    # --- velocity step and the GUIDED timeout -------------------------------------------------
    step_speed = 0.5
    v0 = peer.truth.vn if peer.truth is not None else 0.0
    t_step = peer.t()
    moved = None
    sent_until = t_step + 2.0
    next_sp = t_step
    while peer.t() < sent_until:
        if peer.t() >= next_sp:
            peer.velocity(step_speed, 0.0, 0.0)
            next_sp += 0.1
        if moved is None and peer.truth is not None and peer.truth.vn - v0 > 0.05:
            moved = peer.t()
        await peer.step()
    t_last = peer.t()
    speed_at_last = float(peer.truth.vn) if peer.truth is not None else None
    stopped = await peer.wait(lambda: peer.t() if peer.truth is not None and peer.truth.vn < 0.5 * step_speed
                              else None, 10.0)
    await peer.run_for(2.0)
    obs["velocity_step"] = {"start_moving_s": _r(moved - t_step) if moved else None,
                            "speed_after_2s_m_s": _r(speed_at_last, 2),
                            "slowed_below_half_after_last_setpoint_s": _r(stopped - t_last) if stopped else None,
                            "mode": peer.mode()}
    # --- 3 s vision dropout in flight ---------------------------------------------------------
    h0 = await _hover_height(peer)
    t_drop = peer.t()
    peer.vision_on = False
    heights: list[float] = []
    modes: set[int] = set()
    while peer.t() < t_drop + 3.0:
        await peer.step()
        heights.append(peer.height_m() or 0.0)
        modes.add(-1 if (m := peer.mode()) is None else m)
    peer.vision_on = True
    t_back = peer.t()
    await peer.run_for(4.0)
    obs["dropout_3s"] = {"modes": sorted(modes), "mode_after": peer.mode(), "armed_after": peer.armed(),
                         "max_height_deviation_m": _r(max(abs(h - h0) for h in heights)),
                         "ekf_flags_during": _flag_sequence(peer, t_drop, t_back),
                         "ekf_flags_after": peer.ekf_flags(),
                         "texts": peer.texts(t_drop)}
    # --- LAND ---------------------------------------------------------------------------------
    t_land = peer.command(mavlink.MAV_CMD_NAV_LAND)
    land: dict[str, Any] = {"result": await peer.ack(mavlink.MAV_CMD_NAV_LAND, t_land)}
    samples: list[tuple[float, float]] = []

    def touch() -> float | None:
        h = peer.height_m()
        if h is not None:
            samples.append((peer.t(), h))
        return peer.t() if h is not None and h < 0.05 else None

    touchdown = await peer.wait(touch, 20.0)
    disarmed = await _disarm_time(peer, t_land, 20.0)
    await peer.run_for(1.0)
    mid = [(tm, h) for tm, h in samples if 0.2 <= h <= 0.7]
    rate = (mid[0][1] - mid[-1][1]) / (mid[-1][0] - mid[0][0]) if len(mid) >= 2 and mid[-1][0] > mid[0][0] else None
    land.update({"mode": int(peer.since(t_land, "HEARTBEAT")[1][1].custom_mode)
                 if len(peer.since(t_land, "HEARTBEAT")) > 1 else None,
                 "descent_rate_m_s": _r(rate, 2),
                 "touchdown_s": _r(touchdown - t_land) if touchdown else None,
                 "disarmed_s": _r(disarmed - t_land) if disarmed else None,
                 "landed_states": _landed_sequence(peer, t_land),
                 "texts": peer.texts(t_land)})
    land["ekf_flags_on_ground_after"] = peer.ekf_flags()
    obs["land"] = land
    if long_dropout:
        obs["long_dropout"] = await _long_dropout(peer)


async def _long_dropout(peer: Peer) -> dict[str, Any]:
    """Fly again at 1 m and stop vision for good: when does the autopilot react, and how?"""
    out: dict[str, Any] = {}
    await peer.command_result(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, GUIDED)
    out["arm_result"] = await peer.command_result(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    out["takeoff_result"] = await peer.command_result(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0)
    await peer.wait(lambda: (peer.height_m() or 0.0) >= 0.95, 15.0)
    await peer.run_for(3.0)
    h0 = await _hover_height(peer)
    mode0 = peer.mode()
    t_drop = peer.t()
    peer.vision_on = False
    changed = await peer.wait(lambda: peer.t() if peer.mode() != mode0 or not peer.armed() else None, 30.0)
    out["mode_change_after_s"] = _r(changed - t_drop) if changed else None
    out["mode_after"] = peer.mode()
    out["max_height_deviation_before_reaction_m"] = _r(
        max((abs(float(m.alt) - peer.origin[2] - h0) for tm, m in peer.since(t_drop, "SIM_STATE")
             if changed is None or tm <= changed), default=0.0))
    out["ekf_flags_during"] = _flag_sequence(peer, t_drop, peer.t())
    out["ekf_flags_changed_after_s"] = next(
        (_r(tm - t_drop) for tm, m in peer.since(t_drop, "EKF_STATUS_REPORT") if m.flags != out["ekf_flags_during"][0]),
        None) if out["ekf_flags_during"] else None
    first_text = peer.since(t_drop, "STATUSTEXT")
    out["first_text_after_s"] = _r(first_text[0][0] - t_drop) if first_text else None
    disarmed = await _disarm_time(peer, t_drop, 20.0)
    out["disarmed_after_s"] = _r(disarmed - t_drop) if disarmed else None
    out["texts"] = peer.texts(t_drop)
    out["landed_states"] = _landed_sequence(peer, t_drop)
    peer.vision_on = True
    await peer.run_for(1.0)
    return out


async def record_real_sitl(long_dropout: bool = True) -> dict[str, Any]:
    """Start a fresh real ArduCopter SITL (extnav preset), run the session in real time, stop the SITL."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from sitl_tests.ardupilot.sitl import ArduPilotSitl, sitl_binary

    binary = sitl_binary()
    if binary is None:
        raise RuntimeError("no ArduCopter SITL binary (set COMPANION_ARDUPILOT_SITL or provide ../shared/ardupilot)")
    with ArduPilotSitl(binary, home="-35.363261,149.165230,584,0") as sitl:
        obs = await run_session(sitl.url, time.monotonic, asyncio.sleep, long_dropout)
    source = (binary.parent / "SOURCE_COMMIT")
    obs["peer"] = {"kind": "arducopter-sitl", "source_commit": source.read_text().splitlines()[0]
                   if source.exists() else None, "params": "companion/data/ardupilot/extnav.parm"}
    return obs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--record", type=Path, required=True, help="write the observations (JSON) here")
    parser.add_argument("--no-long-dropout", action="store_true", help="skip the final long vision loss")
    args = parser.parse_args(argv)
    obs = asyncio.run(record_real_sitl(not args.no_long_dropout))
    args.record.parent.mkdir(parents=True, exist_ok=True)
    args.record.write_text(json.dumps(obs, indent=1, sort_keys=True) + "\n")
    print(json.dumps(obs, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
