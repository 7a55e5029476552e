"""Rack acquisition in the daemon: find the rack in the image when the tracker is not locked on it.

The start pose the daemon is given (`DaemonOptions.initial_T_ned_body`, the mission's start) is a
hint, not a survey: the tracker starts from it, and when it does not lock within
`lock_frames` frames -- or loses the rack later for `lost_frames` frames in a row (2 s at 15 Hz,
while the daemon's re-seeds from the filter have not brought it back) -- the daemon also runs
`companion.vision.rack.acquire_rack` on each frame until one gives a confident pose, resets the
tracker there and goes on tracking; the tracker itself keeps running meanwhile. The prior comes
from the vehicle: roll and pitch from the autopilot, the camera's height above the rack's support
plane, the along-pipe position and heading of the filter's estimate (or the hint) with generous
standard deviations. A wrong lock is worse than none: only confident results are taken.

Runs in the vision worker, like the trackers (no I/O, no clock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.checks import FloatArray

__all__ = ["END_SPAN_SIGMAS", "AcquisitionInputs", "RackAcquirer"]

END_SPAN_SIGMAS = 2.0  # the rack's end is looked for within this many along-pipe stds of the prior (+ 0.2 m)


@dataclass(frozen=True)
class AcquisitionInputs:
    """The vehicle's side of an acquisition prior, sampled with the frame.

    roll_rad, pitch_rad: autopilot attitude; height_above_rack_m/std: camera above the rack's support
    plane; T_ned_body_hint: the filter's estimate or the start hint (its rack y and heading are used);
    from_start_hint: T_ned_body_hint is the configured start (never located by vision yet).
    """

    roll_rad: float
    pitch_rad: float
    height_above_rack_m: float
    height_std_m: float
    T_ned_body_hint: FloatArray
    y_std_m: float = 1.0
    yaw_std_rad: float = 0.45
    from_start_hint: bool = False


class RackAcquirer:
    """Lock state of the rack tracker and the acquisition attempts (see the module docstring)."""

    def __init__(self, model: Any, camera: Any, T_body_cam: FloatArray, T_ned_rack: FloatArray, *,
                 lock_frames: int = 30, lost_frames: int = 30, config: Any | None = None) -> None:
        from companion.vision.rack import AcquisitionConfig

        self.model = model
        self.camera = camera
        self.T_body_cam = T_body_cam
        self.T_ned_rack = T_ned_rack
        self.lock_frames = int(lock_frames)
        self.lost_frames = int(lost_frames)
        self.config = config or AcquisitionConfig()
        self.locked = False  # the tracker has produced a good pose since its last (re)start
        self.acquiring = False  # the tracker did not lock / lost the rack: acquire on the next frames
        self.bad_frames = 0
        self.attempts = 0
        self.acquisitions = 0
        self.last: Any | None = None  # the last AcquisitionResult
        self.last_y_std_m = 0.0  # along-pipe std of the last acquired pose (y not observed: the prior's)
        self.y_unobserved = False  # the tracker's rack y is a prior's: look for the rack's end while tracking
        self.y_fixes = 0
        self.last_y_fix_m = 0.0  # the last correction of y from the rack's end (m)
        # the tracker's rack y is still the configured start's (an acquisition from the start hint kept it, and
        # nothing has observed y since): a mission must not place along-pipe waypoints with it
        self.y_from_start_hint = False

    def after_track(self, ok: bool) -> None:
        """Update the lock state with the tracker's verdict on this frame."""
        if ok:
            self.locked = True
            self.acquiring = False
            self.bad_frames = 0
            return
        self.bad_frames += 1
        limit = self.lost_frames if self.locked else self.lock_frames
        if self.bad_frames >= limit:
            self.acquiring = True
            self.locked = False

    def acquire(self, image: Any, inputs: AcquisitionInputs) -> FloatArray | None:
        """One attempt on `image`; the acquired T_rack_cam when confident (the lock state follows it), else None."""
        result = self.attempt(image, inputs)
        if not result.confident or result.best is None:
            return None
        return self.commit(result, inputs)

    def _T_rack_cam_hint(self, inputs: AcquisitionInputs) -> FloatArray:
        """The camera pose in the rack frame of the inputs' hint (4x4)."""
        T_rack_body = np.linalg.inv(self.T_ned_rack) @ np.asarray(inputs.T_ned_body_hint, dtype=np.float64)
        T: FloatArray = T_rack_body @ self.T_body_cam
        return T

    def attempt(self, image: Any, inputs: AcquisitionInputs) -> Any:
        """One `acquire_rack` call on `image` with the inputs' prior; the `AcquisitionResult` (nothing taken)."""
        from companion.vision.rack import AcquisitionPrior, acquire_rack

        T_rack_cam_hint = self._T_rack_cam_hint(inputs)
        yaw = math.atan2(float(inputs.T_ned_body_hint[1, 0]), float(inputs.T_ned_body_hint[0, 0]))
        prior = AcquisitionPrior(
            roll_rad=inputs.roll_rad, pitch_rad=inputs.pitch_rad,
            height_m=max(inputs.height_above_rack_m, 0.2), height_std_m=max(inputs.height_std_m, 0.05),
            y_m=float(T_rack_cam_hint[1, 3]), y_std_m=inputs.y_std_m, yaw_rad=yaw, yaw_std_rad=inputs.yaw_std_rad,
            T_body_cam=self.T_body_cam, T_ned_rack=self.T_ned_rack)
        self.attempts += 1
        result = acquire_rack(image, self.model, self.camera, prior, self.config)
        self.last = result
        return result

    def commit(self, result: Any, inputs: AcquisitionInputs) -> FloatArray:
        """Take a confident `result` of `attempt`: the lock state follows it; returns the T_rack_cam to restart
        the tracker at (y kept from the prior when no crossing pipe observed it)."""
        best = result.best
        self.acquiring = False
        self.locked = False  # until the tracker confirms it
        self.bad_frames = 0
        self.acquisitions += 1
        self.last_y_std_m = 0.0 if best.y_observed else float(inputs.y_std_m)
        self.y_unobserved = not best.y_observed
        # sticky until y is observed: a re-acquisition from the filter's estimate still carries the start's y
        self.y_from_start_hint = not best.y_observed and (self.y_from_start_hint or inputs.from_start_hint)
        T_rack_cam = np.asarray(best.T_rack_cam, dtype=np.float64).copy()
        if not best.y_observed:
            # nothing in view fixes the position along the pipes: keep the estimate's exactly (the refined
            # hypothesis can slide along them), so a re-acquisition never steps further than the drift
            T_rack_cam[1, 3] = self._T_rack_cam_hint(inputs)[1, 3]
        return T_rack_cam

    def fix_y(self, image: Any, T_rack_cam: FloatArray) -> FloatArray | None:
        """While y is the prior's: the tracked pose with y taken from the rack's end when one is in view, else None.

        The end (`companion.vision.rack.acquire_end`) comes into view on the climb after a take-off near it;
        the first clean one fixes y (the filter then takes the step as a reset) and the search stops.
        """
        if not self.y_unobserved:
            return None
        from companion.vision.rack.acquire_end import rack_end_fix

        gray = np.asarray(image)
        if gray.ndim == 3:
            gray = np.asarray(gray[:, :, 0] if gray.shape[2] == 1 else
                              (gray @ np.array([0.114, 0.587, 0.299])).astype(np.uint8))
        # the end is looked for as far from where the prior puts it as the prior's 2 std (+ the 15 cm of limbs
        # needed beyond it): with rack_end_fix's default 1 m, a start 0.9 m off along the pipes is never fixed
        span_m = max(1.0, END_SPAN_SIGMAS * self.last_y_std_m + 0.2)
        fix = rack_end_fix(gray, self.model, self.camera, T_rack_cam, span_m=span_m)
        if not fix.found:
            return None
        self.y_unobserved = False
        self.y_from_start_hint = False
        self.last_y_std_m = 0.0
        self.y_fixes += 1
        self.last_y_fix_m = fix.dy_m
        T = np.array(T_rack_cam, dtype=np.float64, copy=True)
        T[1, 3] += fix.dy_m
        return T
