"""An independent client flies the fake autopilot: MAVSDK-Python (native core) over real UDP, in real time.

MAVSDK keeps its own clock, so these tests run the fake on the SystemClock. They wait on MAVSDK's
telemetry streams (never on sleeps); the only sleep paces the 30 Hz vision feed that MAVSDK's
mocap plugin sends (the fake runs the non-GPS configuration and needs it to arm and fly).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable
from typing import Any, TypeVar

import numpy as np
import pytest

from companion.clock import SystemClock
from companion.sim.autopilot import FakeAutopilot, FakeAutopilotConfig, FlightParams

mavsdk_asyncio = pytest.importorskip("mavsdk.asyncio")

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.mocap import MocapAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, LandedState, TelemetryAsync  # noqa: E402
from mavsdk.plugins.mocap import AngleBody, Covariance, PositionBody, VisionPositionEstimate  # noqa: E402
from mavsdk.plugins.offboard import VelocityNedYaw  # noqa: E402

pytestmark = pytest.mark.timeout(60)

T = TypeVar("T")


async def first(stream: AsyncIterator[T], predicate: Callable[[T], bool], timeout_s: float) -> T:
    """The first item of a MAVSDK telemetry stream that satisfies `predicate` (the stream is closed after)."""

    async def scan() -> T:
        async for item in stream:
            if predicate(item):
                return item
        raise AssertionError("stream ended")

    try:
        return await asyncio.wait_for(scan(), timeout_s)
    finally:
        await stream.aclose()  # type: ignore[attr-defined]


@contextlib.asynccontextmanager
async def mavsdk_session(profile: str, **extra: Any) -> AsyncIterator[tuple[FakeAutopilot, dict[str, Any]]]:
    config = FakeAutopilotConfig(profile=profile, listen="udpin:127.0.0.1:0", seed=11, **extra)
    async with FakeAutopilot(config, clock=SystemClock()) as ap:
        url = ap.url_for_client.replace("udpout:", "udpout://")
        async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as mavsdk:
            await mavsdk.add_any_connection(url)
            system = await mavsdk.first_autopilot(timeout_s=10.0)
            assert system is not None
            plugins = {
                "telemetry": TelemetryAsync(system),
                "action": ActionAsync(system),
                "offboard": OffboardAsync(system),
                "mocap": MocapAsync(system),
            }
            feeder = asyncio.create_task(feed_vision(ap, plugins["mocap"]))
            try:
                yield ap, plugins
            finally:
                feeder.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await feeder


async def feed_vision(ap: FakeAutopilot, mocap: MocapAsync) -> None:
    """Perfect 'vision': the true pose through MAVSDK's mocap plugin (VISION_POSITION_ESTIMATE) at 30 Hz."""
    from companion.geometry import frames

    while True:
        truth = ap.truth
        x, y, z = (float(v) for v in truth.T_ned_body[:3, 3])
        roll, pitch, yaw = (float(a) for a in frames.euler_zyx_from_rotation(truth.T_ned_body[:3, :3]))
        estimate = VisionPositionEstimate(
            int(time.monotonic() * 1e6),
            PositionBody(x, y, z),
            AngleBody(roll, pitch, yaw),
            Covariance([float("nan")]),
            0,
        )
        await mocap.set_vision_position_estimate(estimate)
        await asyncio.sleep(1.0 / 30.0)


async def test_mavsdk_flies_px4_profile_takeoff_and_offboard_velocity() -> None:
    async with mavsdk_session("px4") as (ap, p):
        tel, action, offboard = p["telemetry"], p["action"], p["offboard"]
        # Telemetry decoded by MAVSDK.
        attitude = await first(tel.subscribe_attitude_euler(), lambda a: True, 5.0)
        assert abs(attitude.roll_deg) < 1.0 and abs(attitude.pitch_deg) < 1.0
        battery = await first(tel.subscribe_battery(), lambda b: True, 5.0)
        assert battery.voltage_v == pytest.approx(16.8, abs=0.1)
        assert await first(tel.subscribe_flight_mode(), lambda m: True, 5.0) == FlightMode.POSCTL
        # Vision poses make the EKF healthy; then arm and take off (AUTO.TAKEOFF, then AUTO.LOITER).
        await asyncio.wait_for(ap.wait_received("VISION_POSITION_ESTIMATE", count=5), 5.0)
        await action.arm()
        assert ap.armed
        await action.set_takeoff_altitude(1.5)
        await action.takeoff()
        assert await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.TAKEOFF, 5.0)
        await first(tel.subscribe_position_velocity_ned(), lambda pv: pv.position.down_m < -1.4, 10.0)
        await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 5.0)
        assert ap.truth.height_m == pytest.approx(1.5, abs=0.15)
        # Offboard velocity: PX4 wants the setpoint stream first.
        n = len(ap.received_of("SET_POSITION_TARGET_LOCAL_NED"))
        await offboard.set_velocity_ned(VelocityNedYaw(1.0, 0.0, 0.0, 0.0))
        await asyncio.wait_for(ap.wait_received("SET_POSITION_TARGET_LOCAL_NED", count=n + 3), 5.0)
        await offboard.start()
        await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 5.0)
        assert ap.mode == "OFFBOARD"
        await first(tel.subscribe_position_velocity_ned(), lambda pv: pv.velocity.north_m_s > 0.95, 5.0)
        truth = ap.truth
        assert truth.velocity_ned_m_s == pytest.approx([1.0, 0.0, 0.0], abs=0.08)
        assert truth.height_m == pytest.approx(1.5, abs=0.15)
        setpoint = ap.received_of("SET_POSITION_TARGET_LOCAL_NED")[-1].fields
        assert setpoint["coordinate_frame"] == 1 and setpoint["vx"] == pytest.approx(1.0)
        # Stop (hold), land, disarm on the ground.
        await offboard.stop()
        await action.land()
        await first(tel.subscribe_landed_state(), lambda s: s == LandedState.ON_GROUND, 10.0)
        await first(tel.subscribe_armed(), lambda armed: not armed, 5.0)
        assert ap.truth.on_ground and not ap.armed
        assert ap.truth.position_ned_m[0] > 1.0
        vision = ap.received_of("VISION_POSITION_ESTIMATE")
        assert len(vision) > 60 and np.isfinite(vision[-1].fields["x"])


async def test_mavsdk_flies_ardupilot_profile_guided_takeoff_and_velocity() -> None:
    # MAVSDK sets no EKF origin: the fake starts with one (as with GPS), so ArduPilot can set home; its
    # EKF alignment (~12 s of vision on ArduCopter SITL) is shortened to keep this real-time test short.
    extra = {"origin_lla": (47.397742, 8.545594, 488.0), "flight": FlightParams(ekf_alignment_s=0.5)}
    async with mavsdk_session("ardupilot", **extra) as (ap, p):
        tel, action, offboard = p["telemetry"], p["action"], p["offboard"]
        await tel.set_rate_attitude_euler(10.0)
        attitude = await first(tel.subscribe_attitude_euler(), lambda a: True, 5.0)
        assert abs(attitude.yaw_deg) < 2.0
        assert await first(tel.subscribe_flight_mode(), lambda m: True, 5.0) == FlightMode.STABILIZED
        await asyncio.wait_for(ap.wait_received("VISION_POSITION_ESTIMATE", count=25), 5.0)
        await action.arm()
        await action.set_takeoff_altitude(1.5)
        await action.takeoff()  # MAVSDK switches ArduPilot to GUIDED, then NAV_TAKEOFF
        assert ap.mode == "GUIDED"
        await first(tel.subscribe_position_velocity_ned(), lambda pv: pv.position.down_m < -1.4, 10.0)
        await offboard.set_velocity_ned(VelocityNedYaw(0.0, -1.0, 0.0, 0.0))
        await offboard.start()
        await first(tel.subscribe_position_velocity_ned(), lambda pv: pv.velocity.east_m_s < -0.95, 5.0)
        assert ap.truth.velocity_ned_m_s == pytest.approx([0.0, -1.0, 0.0], abs=0.08)
        await offboard.stop()  # BRAKE on ArduPilot
        await action.land()
        await first(tel.subscribe_armed(), lambda armed: not armed, 10.0)
        assert ap.mode == "LAND" and ap.truth.on_ground
        takeoff = [r for r in ap.received_of("COMMAND_LONG") if r.fields["command"] == 22]
        assert takeoff and takeoff[-1].fields["param7"] == pytest.approx(1.5)
