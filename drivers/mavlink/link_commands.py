"""`CommandsMixin`: COMMAND_LONG with its COMMAND_ACK (retries, IN_PROGRESS), the commands built on it (arm,
modes, take-off, message intervals) and the message-interval requests sent whenever the autopilot appears."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Mapping
from types import MappingProxyType

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import CommandDenied, CommandTimeout, InputError, LinkError
from drivers.mavlink.link_core import log
from drivers.mavlink.link_outbound import OutboundMixin
from drivers.mavlink.sendqueue import Priority

__all__ = ["CommandsMixin"]

# If the autopilot refuses a stream, ask for these instead (same information, other message).
_INTERVAL_FALLBACKS: Mapping[str, tuple[str, ...]] = MappingProxyType({"HIGHRES_IMU": ("SCALED_IMU",)})

MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
FORCE_DISARM_MAGIC = 21196.0


class CommandsMixin(OutboundMixin):
    """Commands of `MavLink`; on `OutboundMixin` because hold and land stop the velocity-command stream first."""

    # ---------------------------------------------------------------- commands
    async def command_long(
        self,
        command: int,
        params: tuple[float, ...] = (),
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
        done_already: Callable[[], bool] | None = None,
    ) -> None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK, resending with confirmation+1 on timeout.

        Raises `CommandDenied` on a non-accepted result, `CommandTimeout` after all retries,
        `LinkError` when no autopilot is known. ``done_already``: for commands that are not idempotent
        (takeoff), a denial of a *resent* command is accepted when this says the first attempt worked
        (its ACK was lost).
        """
        target = self._tracker.autopilot_address
        if target is None:
            raise LinkError(f"command {_command_name(command)}: no autopilot on the link")
        timeout = self.config.command_timeout_s if timeout_s is None else timeout_s
        attempts = 1 + (self.config.command_retries if retries is None else retries)
        lock = self._command_locks.setdefault(command, asyncio.Lock())
        async with lock:
            loop = asyncio.get_running_loop()
            for attempt in range(attempts):
                fut: asyncio.Future[int] = loop.create_future()
                self._pending_acks[command] = fut
                try:
                    self._enqueue(self._encoder.command_long(target, command, params, attempt), Priority.CONTROL)
                    self._counts["commands_sent"] += 1
                    if attempt:
                        self._counts["command_retries"] += 1
                    result = await self._await_ack(command, fut, timeout)
                finally:
                    if self._pending_acks.get(command) is fut:
                        del self._pending_acks[command]
                if result is None:
                    continue
                if result == MAV_RESULT_ACCEPTED:
                    return
                if attempt > 0 and done_already is not None and done_already():
                    log.info("%s denied on retry but already done (first ACK lost)", _command_name(command))
                    return
                self._counts["commands_denied"] += 1
                raise CommandDenied(f"{_command_name(command)} {params}: {_result_name(result)}")
            self._counts["command_timeouts"] += 1
            raise CommandTimeout(f"{_command_name(command)}: no COMMAND_ACK after {attempts} attempts of {timeout} s")

    async def _await_ack(self, command: int, fut: asyncio.Future[int], timeout_s: float) -> int | None:
        while True:
            if not await self._wait_future(fut, timeout_s):
                return None
            result = fut.result()
            if result != MAV_RESULT_IN_PROGRESS:
                return result
            fut = asyncio.get_running_loop().create_future()  # keep waiting for the final ACK
            self._pending_acks[command] = fut

    async def arm(self) -> None:
        await self.command_long(MAV_CMD_COMPONENT_ARM_DISARM, (1.0,))

    async def disarm(self, force: bool = False) -> None:
        await self.command_long(MAV_CMD_COMPONENT_ARM_DISARM, (0.0, FORCE_DISARM_MAGIC if force else 0.0))

    async def set_mode(self, name: str) -> None:
        """Change flight mode by name through the autopilot profile (e.g. "GUIDED", "AUTO.LAND")."""
        profile = self._require_profile()
        await self.command_long(MAV_CMD_DO_SET_MODE, profile.set_mode_params(name))

    async def hold(self) -> None:
        """Stop the setpoint stream and switch to the profile's hold mode (ArduPilot BRAKE, PX4 AUTO.LOITER)."""
        self.set_velocity_command(None)
        await self.set_mode(self._require_profile().hold_mode)

    async def land(self) -> None:
        """Stop the setpoint stream and switch to the profile's land mode."""
        self.set_velocity_command(None)
        await self.set_mode(self._require_profile().land_mode)

    async def takeoff(self, height_m: float) -> None:
        """Climb to ``height_m`` above the take-off point (ArduPilot: enters GUIDED first; vehicle must be armed)."""
        profile = self._require_profile()
        if profile.takeoff_mode is not None and self.state.mode != profile.takeoff_mode:
            await self.set_mode(profile.takeoff_mode)
        origin_alt = self.state.ekf_origin_alt_m
        if origin_alt is None and self.config.origin is not None:
            origin_alt = self.config.origin[2]
        param7 = profile.takeoff_param7(height_m, origin_alt)
        await self.command_long(
            MAV_CMD_NAV_TAKEOFF,
            (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, param7),
            done_already=lambda: self.state.landed_state in ("takeoff", "in_air"),
        )

    async def set_message_interval(self, message_name: str, rate_hz: float) -> None:
        """Ask the autopilot to stream ``message_name`` at ``rate_hz`` (0 stops it)."""
        msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{message_name}", None)
        if msg_id is None:
            raise InputError(f"unknown MAVLink message {message_name!r}")
        interval_us = -1.0 if rate_hz <= 0.0 else 1e6 / rate_hz
        await self.command_long(MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), interval_us))

    async def _request_intervals(self) -> None:
        rates = dict(self.config.message_rates_hz)
        if self.config.request_sim_state:
            rates["SIM_STATE"] = self.config.sim_state_rate_hz
        for name, rate_hz in rates.items():
            for candidate in (name, *_INTERVAL_FALLBACKS.get(name, ())):
                try:
                    await self.set_message_interval(candidate, rate_hz)
                    break
                except LinkError as exc:
                    self._counts["interval_requests_failed"] += 1
                    log.info("message interval %s @ %.1f Hz not set: %s", candidate, rate_hz, exc)


def _command_name(command: int) -> str:
    entry = mavlink.enums.get("MAV_CMD", {}).get(command)
    return entry.name if entry is not None else f"MAV_CMD({command})"


def _result_name(result: int) -> str:
    entry = mavlink.enums.get("MAV_RESULT", {}).get(result)
    return entry.name if entry is not None else f"MAV_RESULT({result})"
