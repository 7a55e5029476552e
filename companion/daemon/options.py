"""`DaemonOptions`: how the daemon is wired beyond the config file (tests, the simulator, the CLI)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.checks import FloatArray

__all__ = ["DaemonOptions"]


@dataclass
class DaemonOptions:
    """How the daemon is wired (beyond the config file).

    vision_inline: run the trackers on the loop thread (deterministic tests) instead of a worker.
    flight_root / flight_name: where the flight folder goes (default ``logging.flight_root``).
    render / pose_source: the synthetic camera's renderer and truth source (None: built from the
        config's rack model, and the link's SIM_STATE).
    camera_source: a ready `CameraSource` to use instead of opening the configured one.
    initial_T_ned_body: the start pose prior for the filter and the rack tracker (default: origin).
    api / sdnotify: enable the control API server and the systemd notifier.
    The options below override the config key named in brackets when given (None: the config's value).

    record_frames: keep every processed frame in the flight folder (``frames/`` + ``timestamps.txt``)
        for `companion replay` [logging.record_frames].
    turn_first_rad: heading errors above this (rad) are turned out in place before moving (0 = off)
        [mission.turn_first_deg].
    rack_along_pipe_std_m: standard deviation (m) added to the rack pose along the pipes, which the
        pipe edges do not observe (see `VisionPipeline.fuse`); 0 trusts the tracker's covariance
        [vision.rack_along_pipe_std_m].
    frame_gap_reset_s: a longer gap between frames restarts the rack tracker [vision.frame_gap_reset_s].
    visual_ground_z_ned_m: the NED z of the ground the camera sees, when it differs from what the
        rangefinder measures to (the simulator's deck); the ground odometer's height then comes from
        the estimate. None: rangefinder (or the filter's ground) as usual [camera.sim_ground_z_ned_m].
    """

    vision_inline: bool = False
    flight_root: Path | None = None
    flight_name: str | None = None
    render: Callable[[Any], Any] | None = None
    pose_source: Callable[[], Any] | None = None
    camera_source: Any | None = None
    initial_T_ned_body: FloatArray | None = None
    api: bool = True
    sdnotify: bool = True
    control_period_s: float = 0.05
    watchdog_period_s: float = 0.1
    photo_folder: Path | None = None
    visual_ground_z_ned_m: float | None = None
    frame_gap_reset_s: float | None = None
    record_frames: bool | None = None
    rack_along_pipe_std_m: float | None = None
    turn_first_rad: float | None = None
