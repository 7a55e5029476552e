"""The per-frame vision pipeline of the daemon.

Split in two so the expensive part can run in a worker thread while the
navigation filter stays on the event-loop thread (it also receives the IMU
callbacks there, so it is never touched by two threads):

* `VisionPipeline.measure(image, stamp_s, inputs)` -- rack tracker and/or ground
  odometer on one image; thread-safe with respect to the event loop (it only
  touches the trackers, which nothing else uses).
* `VisionPipeline.fuse(measurement, nav_filter)` -- feeds the measurement to the
  `NavigationFilter` and returns its estimate (event-loop thread).

Which sources run follows ``vision.source``: "rack", "ground" or "auto" (both;
the filter selects). The rack tracker is (re)initialised from a pose in NED:
the start pose, then the filter's estimate after it lost the rack.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import ConfigError
from companion.geometry import frames

__all__ = ["FrameInputs", "Measurement", "VisionPipeline", "rack_std_floor_from_config"]

SOURCES = ("rack", "ground", "auto")


@dataclass(frozen=True)
class FrameInputs:
    """Vehicle state sampled on the event loop when a frame is handed to the vision worker.

    height_m: camera optical centre above the ground plane (m), None if unknown.
    roll_rad, pitch_rad: attitude of the body at capture (rad).
    reset_T_ned_body: if set, re-initialise the rack tracker at this body pose (NED) before tracking.
    """

    height_m: float | None
    roll_rad: float
    pitch_rad: float
    reset_T_ned_body: FloatArray | None = None


@dataclass(frozen=True)
class Measurement:
    """What the vision worker produced for one frame (estimates as returned by the trackers)."""

    stamp_s: float
    seq: int
    rack: Any | None
    ground: Any | None
    process_s: float

    @property
    def rack_ok(self) -> bool:
        return self.rack is not None and bool(self.rack.ok)

    @property
    def ground_ok(self) -> bool:
        return self.ground is not None and bool(self.ground.ok)


class VisionPipeline:
    """Rack tracker and/or ground odometer on the frames of one camera."""

    def __init__(
        self,
        *,
        source: str,
        camera: PinholeCamera,
        T_body_cam: Any,
        T_ned_rack: Any,
        rack_model: Any | None = None,
        rack_config: Any | None = None,
        ground_config: Any | None = None,
        initial_T_ned_body: Any | None = None,
        min_ground_height_m: float = 0.15,
        rack_std_floor: tuple[float, ...] = (0.01, 0.01, 0.01, 0.0087, 0.0087, 0.0087),
        rack_along_pipe_std_m: float = 0.0,
    ) -> None:
        if source not in SOURCES:
            raise ConfigError(f"vision.source: must be one of {SOURCES}, got {source!r}")
        self.source = source
        self.camera = camera
        self.T_body_cam = check_transform(T_body_cam, "T_body_cam")
        self.T_ned_rack = check_transform(T_ned_rack, "T_ned_rack")
        self.min_ground_height_m = float(min_ground_height_m)
        floor = np.asarray(rack_std_floor, dtype=np.float64).reshape(6)
        self.rack_covariance_floor: FloatArray = np.diag(floor**2)
        self.rack_along_pipe_std_m = float(rack_along_pipe_std_m)
        T0 = np.eye(4) if initial_T_ned_body is None else check_transform(initial_T_ned_body, "initial_T_ned_body")
        self.rack_tracker: Any | None = None
        self.ground_odometer: Any | None = None
        if source in ("rack", "auto"):
            from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig

            model = rack_model if rack_model is not None else RackModel.load(_default_rack_path())
            self.rack_tracker = RackTracker(model, camera, rack_config or RackTrackerConfig())
            self.rack_tracker.reset(self.T_rack_cam_from(T0))
        if source in ("ground", "auto"):
            from companion.vision.ground import GroundOdometer, GroundOdometerConfig

            self.ground_odometer = GroundOdometer(camera, ground_config or GroundOdometerConfig(),
                                                  T_body_cam=self.T_body_cam)
            yaw = float(frames.yaw_from_rotation(T0[:3, :3]))
            self.ground_odometer.reset(x_m=float(T0[0, 3]), y_m=float(T0[1, 3]), yaw_rad=yaw)
        self.frames = 0
        self.rack_ok_frames = 0
        self.ground_ok_frames = 0

    def T_rack_cam_from(self, T_ned_body: Any) -> FloatArray:
        """Camera pose in the rack frame for a body pose in NED."""
        return frames.T_rack_cam_from_T_ned_body(T_ned_body, self.T_ned_rack, self.T_body_cam)

    def reset_rack(self, T_ned_body: Any) -> None:
        """Re-initialise the rack tracker at a body pose in NED."""
        if self.rack_tracker is not None:
            self.rack_tracker.reset(self.T_rack_cam_from(T_ned_body))

    def measure(self, image: Any, stamp_s: float, seq: int, inputs: FrameInputs) -> Measurement:
        """Run the configured trackers on one image (worker thread or inline)."""
        t0 = time.perf_counter()
        if inputs.reset_T_ned_body is not None:
            self.reset_rack(inputs.reset_T_ned_body)
        rack = None
        ground = None
        if self.rack_tracker is not None:
            rack = self.rack_tracker.track(image, stamp_s)
        if (self.ground_odometer is not None and inputs.height_m is not None
                and inputs.height_m >= self.min_ground_height_m):
            ground = self.ground_odometer.update(image, stamp_s, inputs.height_m, inputs.roll_rad, inputs.pitch_rad)
        self.frames += 1
        m = Measurement(stamp_s=stamp_s, seq=seq, rack=rack, ground=ground, process_s=time.perf_counter() - t0)
        self.rack_ok_frames += int(m.rack_ok)
        self.ground_ok_frames += int(m.ground_ok)
        return m

    def fuse(self, measurement: Measurement, nav_filter: Any) -> Any:
        """Feed one measurement to the navigation filter and return its estimate (event-loop thread).

        The rack pose's covariance gets a floor (`rack_std_floor`: 1 cm, 0.5 deg by default, camera
        frame twist order v, w): the tracker's own covariance is a few millimetres, tighter than the
        camera-IMU time alignment on a busy computer, which would make the filter gate good poses out.
        `rack_along_pipe_std_m` > 0 adds that much standard deviation along the pipes' direction, which
        the pipe edges do not observe (the tracker's texture term can slide along them).
        """
        if measurement.rack is not None:
            rack = measurement.rack
            if bool(rack.ok):
                cov = np.asarray(rack.covariance, dtype=np.float64) + self.rack_covariance_floor
                if self.rack_along_pipe_std_m > 0.0:
                    # edges do not fix the position along the pipes: say so (rack +y in the camera frame)
                    d_cam = np.asarray(rack.T_rack_cam, dtype=np.float64)[:3, :3].T @ np.array([0.0, 1.0, 0.0])
                    cov = cov.copy()
                    cov[:3, :3] += self.rack_along_pipe_std_m**2 * np.outer(d_cam, d_cam)
                rack = _RackWithFloor(rack, cov)
            nav_filter.add_rack(rack, measurement.stamp_s)
        if measurement.ground is not None:
            nav_filter.add_ground(measurement.ground, measurement.stamp_s)
        return nav_filter.estimate()


@dataclass(frozen=True)
class _RackWithFloor:
    """A rack estimate as the filter reads it (ok, T_rack_cam, covariance) with a floored covariance."""

    base: Any
    covariance: FloatArray

    @property
    def ok(self) -> bool:
        return bool(self.base.ok)

    @property
    def T_rack_cam(self) -> FloatArray:
        return np.asarray(self.base.T_rack_cam, dtype=np.float64)


def rack_std_floor_from_config(vision: Any) -> tuple[float, ...]:
    """`VisionPipeline`'s ``rack_std_floor`` from the ``[vision]`` config section (m, m, m, rad, rad, rad)."""
    floor_m = float(vision.rack_std_floor_m)
    floor_rad = math.radians(float(vision.rack_std_floor_deg))
    return (floor_m, floor_m, floor_m, floor_rad, floor_rad, floor_rad)


def _default_rack_path() -> str:
    from companion.data import data_path

    return str(data_path("racks/sweep_5pipe.toml"))
