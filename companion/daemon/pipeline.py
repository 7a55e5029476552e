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

import dataclasses
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
# Extra yaw standard deviation (rad) of a ground increment taken with the pipes in view (the odometer's
# heading drifts ~0.3 deg per frame over the rack at 15 fps).
GROUND_PIPES_YAW_STD_RAD = 0.005


@dataclass(frozen=True)
class FrameInputs:
    """Vehicle state sampled on the event loop when a frame is handed to the vision worker.

    height_m: camera optical centre above the ground plane (m), None if unknown.
    roll_rad, pitch_rad: attitude of the body at capture (rad); attitude_known: they are the autopilot's.
    reset_T_ned_body: if set, re-initialise the rack tracker at this body pose (NED) before tracking.
    """

    height_m: float | None
    roll_rad: float
    pitch_rad: float
    reset_T_ned_body: FloatArray | None = None
    attitude_known: bool = False  # roll_rad / pitch_rad come from the autopilot (else they are placeholders)
    acquisition: Any | None = None  # `AcquisitionInputs` for an attempt, when the tracker needs one
    reset_keeps_appearance: bool = False  # that re-seed keeps the limb polarity learnt (after a gap in the frames)


@dataclass(frozen=True)
class Measurement:
    """What the vision worker produced for one frame (estimates as returned by the trackers)."""

    stamp_s: float
    seq: int
    rack: Any | None
    ground: Any | None
    process_s: float
    rack_reset: bool = False  # the rack tracker was re-initialised (FrameInputs.reset_T_ned_body) on this frame
    rack_acquired: bool = False  # the rack was acquired from this image and the tracker restarted there
    acquisition: Any | None = None  # the `AcquisitionResult` of an attempt on this frame
    rack_y_fixed: bool = False  # the tracker's along-pipe position was corrected from the rack's end
    hint_check: Any | None = None  # the `HintCheck` of the start-hint lock made on this frame

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
        ground_pipes_in_view_rel_std: float = 1.0,
        acquire: bool = True,
        rack_attitude_prior_std_rad: float = 0.0,
        verify_start: bool = True,
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
        self.ground_pipes_in_view_rel_std = float(ground_pipes_in_view_rel_std)
        # the autopilot's gravity direction as the rack tracker's attitude prior (0: vision only)
        self.rack_attitude_prior_std_rad = float(rack_attitude_prior_std_rad)
        T0 = np.eye(4) if initial_T_ned_body is None else check_transform(initial_T_ned_body, "initial_T_ned_body")
        self.rack_tracker: Any | None = None
        self.acquirer: Any | None = None  # `RackAcquirer` when acquisition is on (vision.rack_acquire)
        self.hint_checker: Any | None = None  # `HintChecker` of the start-hint lock (vision.rack_verify_start)
        self._y_fix_pending = False  # y was fixed on a frame the tracker missed: mark its next good pose
        self._pipe_top_m = 0.0  # mean height of the parallel pipes' tops above the support plane (m)
        self.ground_odometer: Any | None = None
        if source in ("rack", "auto"):
            from companion.vision.rack import RackModel, RackTracker, RackTrackerConfig

            model = rack_model if rack_model is not None else RackModel.load(_default_rack_path())
            self.rack_tracker = RackTracker(model, camera, rack_config or RackTrackerConfig())
            self._pipe_top_m = 2.0 * float(np.mean(model.radii))
            self.rack_tracker.reset(self.T_rack_cam_from(T0))
            if acquire:
                from companion.daemon.acquisition import RackAcquirer

                self.acquirer = RackAcquirer(model, camera, self.T_body_cam, self.T_ned_rack)
                if verify_start:
                    from companion.daemon.hint_check import HintChecker

                    # the tracker starts from the start hint: check that lock against the image (hint_check.py)
                    self.hint_checker = HintChecker()
        if source in ("ground", "auto"):
            from companion.vision.ground import GroundOdometer, GroundOdometerConfig

            self.ground_odometer = GroundOdometer(camera, ground_config or GroundOdometerConfig(),
                                                  T_body_cam=self.T_body_cam)
            yaw = float(frames.yaw_from_rotation(T0[:3, :3]))
            self.ground_odometer.reset(x_m=float(T0[0, 3]), y_m=float(T0[1, 3]), yaw_rad=yaw)
        self.frames = 0
        self.rack_ok_frames = 0
        self.ground_ok_frames = 0
        # Along-pipe standard deviation (m) of the pose the rack tracker was last seeded with (0: the start
        # pose, taken as exact): the pipes' edges do not correct it, so the tracker keeps that error.
        self.rack_seed_along_pipe_std_m = 0.0

    @property
    def along_pipe_from_start_hint(self) -> bool:
        """The rack tracker's position along the pipes is still the configured start's (acquired on the deck
        without a crossing pipe in view, no rack end seen since), or its fix has not reached the filter yet."""
        acq = self.acquirer
        return acq is not None and (bool(acq.y_from_start_hint) or self._y_fix_pending)

    def T_rack_cam_from(self, T_ned_body: Any) -> FloatArray:
        """Camera pose in the rack frame for a body pose in NED."""
        return frames.T_rack_cam_from_T_ned_body(T_ned_body, self.T_ned_rack, self.T_body_cam)

    def reset_rack(self, T_ned_body: Any, keep_appearance: bool = False) -> None:
        """Re-initialise the rack tracker at a body pose in NED (`RackTracker.reset`'s `keep_appearance`)."""
        if self.rack_tracker is not None:
            self.rack_tracker.reset(self.T_rack_cam_from(T_ned_body), keep_appearance=keep_appearance)

    def _attitude_prior(self, inputs: FrameInputs) -> dict[str, Any]:
        """`RackTracker.track`'s attitude prior from the autopilot's roll and pitch (empty when off or unknown).

        The tracker uses only the gravity direction of `R_prior` (R_rack_cam), so the heading is left at
        zero: for a level rack (T_ned_rack a turn about NED down) gravity in the camera frame does not
        depend on it. Limbs of a few parallel pipes hardly tell a roll about the pipes from a slide across
        them; gravity does.
        """
        if self.rack_attitude_prior_std_rad <= 0.0 or not inputs.attitude_known:
            return {}
        R_ned_body = frames.rotation_from_euler_zyx(inputs.roll_rad, inputs.pitch_rad, 0.0)
        R_rack_cam = self.T_ned_rack[:3, :3].T @ R_ned_body @ self.T_body_cam[:3, :3]
        return {"R_prior": R_rack_cam, "R_prior_std_rad": self.rack_attitude_prior_std_rad}

    def measure(self, image: Any, stamp_s: float, seq: int, inputs: FrameInputs) -> Measurement:
        """Run the configured trackers on one image (worker thread or inline)."""
        t0 = time.perf_counter()
        if inputs.reset_T_ned_body is not None:
            self.reset_rack(inputs.reset_T_ned_body, inputs.reset_keeps_appearance)
        rack_reset = inputs.reset_T_ned_body is not None and self.rack_tracker is not None
        rack = None
        ground = None
        acquired = False
        y_fixed = False
        acquisition = None
        acq = self.acquirer
        if self.rack_tracker is not None and acq is not None and acq.acquiring and inputs.acquisition is not None:
            T_rack_cam = acq.acquire(image, inputs.acquisition)
            acquisition = acq.last
            if T_rack_cam is not None:
                self.rack_tracker.reset(T_rack_cam)
                acquired = True
                if self.hint_checker is not None and self.hint_checker.pending:
                    self.hint_checker.settle("acquired")  # located by the image: no longer the hint's lock
        if self.rack_tracker is not None:
            # the tracker keeps running while acquiring: the daemon's re-seed from the filter stays the first
            # way back (it works where acquisition cannot, e.g. on the deck right over the pipes)
            rack = self.rack_tracker.track(image, stamp_s, **self._attitude_prior(inputs))
            hint_check, rack, acquired = self._check_hint_lock(image, stamp_s, inputs, rack, acquired)
            if acq is not None:
                acq.after_track(bool(rack.ok))
                ok = bool(rack.ok)
                # The end coming into view with y wrong is what makes the tracker miss frames (its limbs run
                # past the end): look on those too, from its predicted pose, while it is still locked.
                if acq.y_unobserved and (ok or acq.locked) and hasattr(rack, "__dataclass_fields__"):
                    T_fixed = acq.fix_y(image, np.asarray(rack.T_rack_cam, dtype=np.float64))
                    if T_fixed is not None:
                        self.rack_tracker.reset(T_fixed)
                        rack = dataclasses.replace(rack, T_rack_cam=T_fixed)  # type: ignore[type-var]
                        y_fixed, self._y_fix_pending = ok, not ok
                elif ok and self._y_fix_pending:
                    # the first good pose after a fix made on a missed frame goes to the filter as the reset
                    y_fixed, self._y_fix_pending = True, False
        if (self.ground_odometer is not None and inputs.height_m is not None
                and inputs.height_m >= self.min_ground_height_m):
            ground = self.ground_odometer.update(image, stamp_s, inputs.height_m, inputs.roll_rad, inputs.pitch_rad)
        self.frames += 1
        m = Measurement(stamp_s=stamp_s, seq=seq, rack=rack, ground=ground, process_s=time.perf_counter() - t0,
                        rack_reset=rack_reset, rack_acquired=acquired, acquisition=acquisition,
                        rack_y_fixed=y_fixed, hint_check=hint_check)
        self.rack_ok_frames += int(m.rack_ok)
        self.ground_ok_frames += int(m.ground_ok)
        return m

    def _check_hint_lock(self, image: Any, stamp_s: float, inputs: FrameInputs, rack: Any,
                         acquired: bool) -> tuple[Any | None, Any, bool]:
        """Check the tracker's lock from the start hint against an acquisition on this image when one is due and
        the daemon gave a prior (`hint_check.py`); moves the tracker to the acquired pose when the check says so
        (re-tracked on this image). Returns (the `HintCheck` or None, this frame's rack estimate, acquired)."""
        checker, acq = self.hint_checker, self.acquirer
        if checker is None or acq is None or not checker.pending:
            return None, rack, acquired
        checker.tick()  # counted before a check, which restarts the count: one check every `every_frames` frames
        if acquired or acq.acquiring or inputs.acquisition is None or not checker.due or not bool(rack.ok):
            return None, rack, acquired
        result = acq.attempt(image, inputs.acquisition)
        best = result.best if result.confident else None
        check = checker.check(np.asarray(rack.T_rack_cam, dtype=np.float64), np.asarray(rack.covariance),
                              None if best is None else np.asarray(best.T_rack_cam, dtype=np.float64),
                              None if best is None else np.asarray(best.covariance), str(result.status))
        if check.outcome != "re-acquire":
            return check, rack, acquired
        assert self.rack_tracker is not None
        self.rack_tracker.reset(acq.commit(result, inputs.acquisition))
        return check, self.rack_tracker.track(image, stamp_s, **self._attitude_prior(inputs)), True

    def fuse(self, measurement: Measurement, nav_filter: Any) -> Any:
        """Feed one measurement to the navigation filter and return its estimate (event-loop thread).

        The rack pose's covariance gets a floor (`rack_std_floor`: 1 cm, 0.5 deg by default, camera
        frame twist order v, w): the tracker's own covariance is a few millimetres, tighter than the
        camera-IMU time alignment on a busy computer, which would make the filter gate good poses out.
        `rack_along_pipe_std_m` > 0 adds that much standard deviation along the pipes' direction, which
        the pipe edges do not observe (the tracker's texture term can slide along them). A slide along
        the pipes by s and a tilt by s / h about the axis across them (h: the pipes' depth) move the
        texture alike, so the two come together (`_along_pipe_outer`); the filter's roll and pitch,
        held by gravity, then tell the slide apart from a real tilt.

        After the tracker was re-initialised from the filter's estimate (`Measurement.rack_reset`: after
        losing the rack, a frame gap or rejected poses), its position along the pipes is that estimate's,
        carried on by its texture points: nothing in view corrects it. The along-pipe standard deviation
        is then at least the estimate's at that moment (`rack_seed_along_pipe_std_m`, until the next
        re-initialisation), so the filter neither takes the seed's error back as a precise measurement
        (a switch to the rack moves the pose across the pipes, not along them), nor takes the tilt the
        re-locking tracker shows with it (a few degrees at the rack's end, which leaked gravity into the
        velocity), nor gates the tracker out while it settles (which re-seeded it again, with zero
        velocity, and let it slide).

        Ground increments are re-expressed in the filter's heading (`_GroundInHeading.rotated`: the
        odometer's own heading drifts, by tens of degrees over the rack). On a frame where the rack
        tracker finds the pipes, the odometer has tracked features on them too (metres above the ground
        it assumes: about twice the true motion at 5 m over this rack), so the increment's standard
        deviation is raised by `ground_pipes_in_view_rel_std` times its size.
        """
        if measurement.rack_reset:
            self.rack_seed_along_pipe_std_m = self._along_pipe_std(nav_filter)
        if measurement.rack_acquired and self.acquirer is not None:
            # acquired without a crossing pipe in view: y is the prior's, as uncertain as it was
            self.rack_seed_along_pipe_std_m = float(self.acquirer.last_y_std_m)
        if measurement.rack_y_fixed:
            self.rack_seed_along_pipe_std_m = 0.0  # y from the rack's end: as good as across the pipes
        if measurement.rack is not None:
            rack = measurement.rack
            if bool(rack.ok):
                cov = np.asarray(rack.covariance, dtype=np.float64) + self.rack_covariance_floor
                along_std_m = max(self.rack_along_pipe_std_m, self.rack_seed_along_pipe_std_m)
                if along_std_m > 0.0:
                    cov = cov + along_std_m**2 * self._along_pipe_outer(np.asarray(rack.T_rack_cam, dtype=np.float64))
                rack = _RackWithFloor(rack, cov)
            # an acquired pose or y from the rack's end is better than the estimate: a reset if they disagree
            if bool(rack.ok) and (measurement.rack_acquired or measurement.rack_y_fixed):
                nav_filter.add_rack(rack, measurement.stamp_s, reset=True)
            else:
                nav_filter.add_rack(rack, measurement.stamp_s)
        if measurement.ground is not None:
            ground = measurement.ground
            if bool(ground.ok):
                T_ned_body = np.asarray(nav_filter.estimate_latest().T_ned_body, dtype=np.float64)
                yaw_filter_rad = float(frames.yaw_from_rotation(T_ned_body[:3, :3]))
                ground = _GroundInHeading.rotated(ground, yaw_filter_rad - float(ground.yaw_rad))
                if measurement.rack_ok:
                    ground = ground.with_pipes_in_view(self.ground_pipes_in_view_rel_std, GROUND_PIPES_YAW_STD_RAD)
            nav_filter.add_ground(ground, measurement.stamp_s)
        return nav_filter.estimate()

    def _along_pipe_outer(self, T_rack_cam: FloatArray) -> FloatArray:
        """u u^T (6x6, camera-frame twist (v, w)) of the pose error the pipes' edges do not see.

        Sliding along the pipes by s looks, for the texture on the pipes at depth h, like tilting the
        camera by s / h about the axis across the pipes: u = (d, (d x z) / h), d the pipes' direction and
        z the optical axis in the camera frame (the motion field -v + p x w vanishes at p = h z).
        """
        d_cam = T_rack_cam[:3, :3].T @ np.array([0.0, 1.0, 0.0])
        depth_m = max(float(T_rack_cam[2, 3]) - self._pipe_top_m, 0.5)
        u = np.concatenate([d_cam, np.cross(d_cam, np.array([0.0, 0.0, 1.0])) / depth_m])
        out: FloatArray = np.outer(u, u)
        return out

    def _along_pipe_std(self, nav_filter: Any) -> float:
        """Standard deviation (m) of the filter's current position along the pipes (rack +y in NED)."""
        P = np.asarray(nav_filter.estimate_latest().pose_covariance, dtype=np.float64)[:3, :3]
        d_ned = self.T_ned_rack[:3, :3] @ np.array([0.0, 1.0, 0.0])
        var = float(d_ned @ P @ d_ned)
        return math.sqrt(var) if math.isfinite(var) and var > 0.0 else 0.0


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


@dataclass(frozen=True)
class _GroundInHeading:
    """A ground estimate as the filter reads it (ok, dx_m, dy_m, dyaw_rad, covariance, dt_s) with its
    horizontal increment re-expressed in the filter's heading.

    The odometer turns its increments into NED with its own accumulated heading, which drifts on its
    own (and fast over the rack, whose pipes break its ground-plane model) while the rack tracker is the
    source; the filter's heading is the one the rest of the estimate lives in.
    """

    ok: bool
    dx_m: float
    dy_m: float
    dyaw_rad: float
    covariance: FloatArray
    dt_s: float | None

    def with_pipes_in_view(self, rel_std: float, yaw_std_rad: float) -> _GroundInHeading:
        """The same increment with its standard deviations raised by `rel_std` times its size (and the
        yaw one by `yaw_std_rad` more): features on pipes metres above the ground move faster than the
        ground the odometer assumes (about 2x at 5 m over this rack) and turn its yaw."""
        extra = np.array([rel_std * abs(self.dx_m), rel_std * abs(self.dy_m),
                          rel_std * abs(self.dyaw_rad) + yaw_std_rad])
        cov = self.covariance + np.diag(extra**2)
        return _GroundInHeading(self.ok, self.dx_m, self.dy_m, self.dyaw_rad, cov, self.dt_s)

    @classmethod
    def rotated(cls, est: Any, angle_rad: float) -> _GroundInHeading:
        """`est`'s increment rotated about NED down by `angle_rad` (filter heading - odometer heading)."""
        c, s = math.cos(angle_rad), math.sin(angle_rad)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        d = R @ np.array([float(est.dx_m), float(est.dy_m), float(est.dyaw_rad)])
        cov = R @ np.asarray(est.covariance, dtype=np.float64) @ R.T
        dt_s = getattr(est, "dt_s", None)
        return cls(True, float(d[0]), float(d[1]), float(d[2]), cov, None if dt_s is None else float(dt_s))


def rack_std_floor_from_config(vision: Any) -> tuple[float, ...]:
    """`VisionPipeline`'s ``rack_std_floor`` from the ``[vision]`` config section (m, m, m, rad, rad, rad)."""
    floor_m = float(vision.rack_std_floor_m)
    floor_rad = math.radians(float(vision.rack_std_floor_deg))
    return (floor_m, floor_m, floor_m, floor_rad, floor_rad, floor_rad)


def _default_rack_path() -> str:
    from companion.data import data_path

    return str(data_path("racks/sweep_5pipe.toml"))
