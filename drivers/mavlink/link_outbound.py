"""`OutboundMixin`: what `MavLink` sends when asked: vision poses (and the rule for their time base), the
velocity command the setpoint task streams, and ground-station messages (STATUSTEXT, NAMED_VALUE_FLOAT,
CAMERA_IMAGE_CAPTURED, any message as another component of ours)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

from companion.control.types import VelocityCommand
from companion.errors import InputError
from companion.geometry import frames
from drivers.mavlink.link_core import LinkCore, log
from drivers.mavlink.sendqueue import Priority
from drivers.mavlink.state import PoseOut
from drivers.mavlink.wire import Encoder, usec_from_s

__all__ = ["SEVERITY", "OutboundMixin"]

SEVERITY: Mapping[str, int] = MappingProxyType(
    {
        "emergency": 0,
        "alert": 1,
        "critical": 2,
        "error": 3,
        "warning": 4,
        "notice": 5,
        "info": 6,
        "debug": 7,
    }
)


class OutboundMixin(LinkCore):
    """Poses, the velocity-command setter and the ground-station messages of `MavLink`."""

    # ---------------------------------------------------------------- pose
    def send_pose(self, pose: PoseOut) -> bool:
        """Encode and enqueue a new pose (never blocks); returns whether it was queued.

        Refused (False, counted): not newer than the last pose sent, older than ``pose_max_age_s``, or
        while the stamp's time base is undecided (TIMESYNC converging, at most ``timesync_fallback_s``
        after the autopilot appeared). ``usec`` on the wire is the capture time in the autopilot's
        time base (TIMESYNC), or in ours if the autopilot does not answer TIMESYNC or the config
        says ``pose_stamp_base="local"``.
        """
        now = self._clock.now()
        if (self._last_pose_stamp_s is not None and pose.stamp_s <= self._last_pose_stamp_s) or (
            now - pose.stamp_s > self.config.pose_max_age_s
        ):
            self._counts["poses_rejected_stale"] += 1
            return False
        base = self._pose_time_base(now)
        if base is None:
            self._counts["poses_held_for_timesync"] += 1
            return False
        peer_s = self._timesync.to_peer_s(pose.stamp_s) if base == "autopilot" else pose.stamp_s
        if peer_s is None:  # the autopilot's clock jumped (reboot): wait for a new offset
            self._counts["poses_held_for_timesync"] += 1
            return False
        self._last_pose_stamp_s = pose.stamp_s
        usec = usec_from_s(peer_s)
        expires = pose.stamp_s + self.config.pose_max_age_s
        if self.pose_message == "odometry":
            self._enqueue(self._encoder.odometry(pose, usec), Priority.POSE, expires)
        else:
            self._enqueue(self._encoder.vision_position_estimate(pose, usec), Priority.POSE, expires)
            if self.config.send_vision_speed and pose.velocity_ned_m_s is not None:
                self._enqueue(self._encoder.vision_speed_estimate(pose, usec), Priority.POSE, expires)
        self._counts["poses_sent"] += 1
        return True

    def _pose_time_base(self, now: float) -> str | None:
        """ "autopilot" once TIMESYNC converged, "local" if it did not within ``timesync_fallback_s`` of the
        autopilot appearing (or is disabled), None while undecided. Decided once: the stamps never jump.
        With ``pose_stamp_base="auto"`` a PX4 gets "local" and anything else the TIMESYNC rule; undecided
        until the autopilot is known."""
        if self._pose_base is None:
            wanted = self.config.pose_stamp_base
            if wanted == "auto":
                profile = self.profile
                if profile is None and self.state.last_autopilot_heartbeat_s is None:
                    return None
                wanted = "local" if profile is not None and profile.name == "px4" else "autopilot"
            if wanted == "local":
                self._pose_base = "local"
            elif self._timesync.converged:
                self._pose_base = "autopilot"
            elif self.config.timesync_period_s <= 0.0 or (
                self._autopilot_since_s is not None and now - self._autopilot_since_s > self.config.timesync_fallback_s
            ):
                self._pose_base = "local"
                log.warning("no TIMESYNC answer from the autopilot: pose stamps stay in the companion's time base")
        return self._pose_base

    @property
    def pose_message(self) -> str:
        """What poses go out as: "odometry" or "vision"; "auto" is ODOMETRY for PX4 (which ignores
        VISION_SPEED_ESTIMATE), VISION_POSITION/SPEED_ESTIMATE for ArduPilot and unknown autopilots."""
        kind = self.config.pose_message
        if kind == "auto":
            profile = self.profile
            return "odometry" if profile is not None and profile.name == "px4" else "vision"
        return kind

    @property
    def pose_time_base(self) -> str | None:
        """Time base of outgoing pose stamps: "autopilot" (TIMESYNC), "local", or None (not decided yet)."""
        return self._pose_base

    # ---------------------------------------------------------------- setpoints
    def set_velocity_command(self, command: VelocityCommand | None) -> None:
        """Stream ``command`` at ``setpoint_rate_hz`` from now on (None stops the stream)."""
        if command is not None and not isinstance(command, VelocityCommand):
            raise InputError(f"set_velocity_command takes a VelocityCommand or None, got {type(command).__name__}")
        self._velocity_cmd = command
        if command is not None:
            self._setpoint_wake.set()
        else:  # a setpoint still waiting for the writer must not follow a hold/land command out
            self._queue.clear(Priority.SETPOINT)

    # ---------------------------------------------------------------- ground station
    def statustext(self, text: str, severity: int | str = "info") -> None:
        """Send a STATUSTEXT (chunked with id/chunk_seq when longer than 50 bytes)."""
        if isinstance(severity, str):
            if severity.lower() not in SEVERITY:
                raise InputError(f"unknown severity {severity!r}; one of {', '.join(SEVERITY)}")
            severity = SEVERITY[severity.lower()]
        if not 0 <= int(severity) <= 7:
            raise InputError(f"severity must be in [0, 7], got {severity}")
        self._statustext_id = self._statustext_id % 65535 + 1
        for frame in self._encoder.statustext(text, int(severity), self._statustext_id):
            self._enqueue(frame, Priority.CONTROL, to_gcs=True)

    def send_as(self, component_id: int, build: Callable[[Any], Any]) -> None:
        """Send one message as another component of our system (e.g. MAV_COMP_ID_CAMERA), to the autopilot and
        the GCS forwards. `build(mav)` returns the pymavlink message (``mav.heartbeat_encode(...)``)."""
        enc = self._component_encoders.get(component_id)
        if enc is None:
            enc = self._component_encoders[component_id] = Encoder(self._encoder.system_id, component_id)
        enc.system_id = self._encoder.system_id  # follows the autopilot's system id once heard
        self._enqueue(enc.pack(build(enc.mav)), Priority.CONTROL, to_gcs=True)

    def named_value_float(self, name: str, value: float) -> None:
        """Send NAMED_VALUE_FLOAT (name cut to 10 ASCII characters)."""
        self._enqueue(self._encoder.named_value_float(self._boot_ms(), name, value), Priority.CONTROL, to_gcs=True)

    def camera_image_captured(
        self,
        image_index: int,
        file_url: str = "",
        *,
        success: bool = True,
        time_utc_s: float | None = None,
        R_ned_cam: Any = None,
        lat_deg: float | None = None,
        lon_deg: float | None = None,
        alt_m: float | None = None,
        relative_alt_m: float | None = None,
    ) -> None:
        """Announce a photo (CAMERA_IMAGE_CAPTURED); orientation/position are optional (zeros/identity if unknown)."""
        q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        if R_ned_cam is not None:
            w, x, y, z = (float(v) for v in frames.quaternion_wxyz_from_rotation(R_ned_cam))
            q = (w, x, y, z)
        frame = self._encoder.camera_image_captured(
            self._boot_ms(),
            usec_from_s(self._wall_time_s() if time_utc_s is None else time_utc_s),
            int(image_index),
            file_url,
            success,
            q,
            round((lat_deg or 0.0) * 1e7),
            round((lon_deg or 0.0) * 1e7),
            round((alt_m or 0.0) * 1e3),
            round((relative_alt_m or 0.0) * 1e3),
        )
        self._enqueue(frame, Priority.CONTROL, to_gcs=True)
