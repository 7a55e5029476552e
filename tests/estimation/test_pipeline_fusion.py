"""How the daemon's vision pipeline hands the trackers' outputs to the navigation filter."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.daemon.pipeline import Measurement, VisionPipeline
from companion.estimation import ImuSample, NavFilterConfig, NavigationFilter
from companion.geometry import frames, se3
from companion.vision.ground import GroundEstimate


def odometer_output(ok: bool, x_m: float, y_m: float, yaw_rad: float, dx_m: float, dy_m: float, dyaw_rad: float,
                    covariance: np.ndarray, dt_s: float) -> GroundEstimate:
    """A `GroundEstimate` with the fields the pipeline reads."""
    return GroundEstimate(ok, x_m, y_m, yaw_rad, dx_m, dy_m, dyaw_rad, covariance, num_matches=100,
                          num_inliers=80 if ok else 0, dt_s=dt_s)


@dataclass(frozen=True)
class Latest:
    T_ned_body: np.ndarray
    pose_covariance: np.ndarray


@dataclass(frozen=True)
class RackOutput:
    """What `RackTracker.track` returns, as far as the pipeline reads it."""

    ok: bool
    T_rack_cam: np.ndarray
    covariance: np.ndarray


@dataclass
class RecordingFilter:
    """Stands in for NavigationFilter: records what the pipeline feeds it."""

    yaw_rad: float
    position_std_ned_m: tuple[float, float, float] = (0.01, 0.01, 0.01)
    ground: list[Any] = field(default_factory=list)
    rack: list[Any] = field(default_factory=list)

    def add_rack(self, est: Any, stamp_s: float) -> None:
        self.rack.append(est)

    def add_ground(self, est: Any, stamp_s: float) -> None:
        self.ground.append(est)

    def estimate_latest(self) -> Latest:
        P = np.diag([*(s**2 for s in self.position_std_ned_m), 1e-4, 1e-4, 1e-4])
        return Latest(se3.make(frames.rotation_from_euler_zyx(0.02, -0.01, self.yaw_rad), np.zeros(3)), P)

    def estimate(self) -> Latest:
        return self.estimate_latest()


def ground_pipeline() -> VisionPipeline:
    cam = PinholeCamera(width=240, height=160, fx=210.0, fy=210.0, cx=120.0, cy=80.0)
    return VisionPipeline(source="ground", camera=cam, T_body_cam=frames.default_T_body_cam(),
                          T_ned_rack=frames.default_T_ned_rack())


@pytest.mark.parametrize(("odometer_yaw_rad", "filter_yaw_rad"), [(math.pi / 2, 0.0), (0.3, 0.3), (-2.9, 2.5)])
def test_ground_increments_are_turned_into_the_filters_heading(odometer_yaw_rad: float, filter_yaw_rad: float) -> None:
    """The odometer's own heading drifts (fast over the pipes): its NED increment is re-expressed with the
    filter's heading, i.e. the same body-frame motion; the yaw increment and the time span are kept."""
    nav = RecordingFilter(filter_yaw_rad)
    # The vehicle moved 3 cm forward and 1 cm right in the body frame; the odometer writes that in NED
    # with its own heading.
    fwd, right = 0.03, 0.01
    c, s = math.cos(odometer_yaw_rad), math.sin(odometer_yaw_rad)
    cov_body = np.diag([0.004**2, 0.001**2, 0.002**2])
    R_odo = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = odometer_output(True, 5.0, -2.0, odometer_yaw_rad, c * fwd - s * right, s * fwd + c * right, 0.004,
                         R_odo @ cov_body @ R_odo.T, dt_s=0.0667)
    ground_pipeline().fuse(Measurement(stamp_s=1.0, seq=0, rack=None, ground=out, process_s=0.0), nav)
    (fed,) = nav.ground
    cf, sf = math.cos(filter_yaw_rad), math.sin(filter_yaw_rad)
    np.testing.assert_allclose([fed.dx_m, fed.dy_m], [cf * fwd - sf * right, sf * fwd + cf * right], atol=1e-12)
    assert fed.dyaw_rad == pytest.approx(0.004) and fed.dt_s == pytest.approx(0.0667) and fed.ok
    R_f = np.array([[cf, -sf, 0.0], [sf, cf, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(fed.covariance, R_f @ cov_body @ R_f.T, atol=1e-15)


def test_failed_ground_frames_pass_through_unchanged() -> None:
    nav = RecordingFilter(0.0)
    out = odometer_output(False, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, np.zeros((3, 3)), dt_s=0.0)
    ground_pipeline().fuse(Measurement(stamp_s=1.0, seq=0, rack=None, ground=out, process_s=0.0), nav)
    assert nav.ground == [out]


def test_rotated_increments_drive_the_real_filter_along_the_body_motion() -> None:
    """End to end with NavigationFilter at heading 0 and an odometer that believes it faces east."""
    f = NavigationFilter(NavFilterConfig())
    f.initialize(0.0, np.eye(4), covariance=np.diag([1e-4] * 3 + [1e-2] * 3 + [1e-6] * 3 + [1e-8] * 3 + [1e-6] * 3))
    pipeline = ground_pipeline()
    gravity = np.array([0.0, 0.0, -9.80665])
    t = 0.0
    for k in range(1, 11):
        for _ in range(5):
            t = round(t + 0.01, 10)
            f.add_imu(ImuSample(t, np.zeros(3), gravity))
        # odometer heading +90 deg: forward (north for the filter) is east in its NED
        out = odometer_output(True, 0.0, 0.0, math.pi / 2, 0.0, 0.0 if k == 1 else 0.02, 0.0,
                             np.diag([0.002**2, 0.002**2, 0.001**2]), dt_s=0.0 if k == 1 else 0.05)
        pipeline.fuse(Measurement(stamp_s=t, seq=k, rack=None, ground=out, process_s=0.0), f)
    est = f.estimate()
    assert est.source == "ground"
    assert est.position_ned_m[0] > 0.05 and abs(est.position_ned_m[1]) < 0.01



def test_rack_seeded_from_the_estimate_keeps_its_along_pipe_uncertainty() -> None:
    """After a re-initialisation from the filter's estimate, the rack pose is as uncertain along the pipes
    (rack +y = NED north by default) as that estimate was; across the pipes it keeps its floor."""
    pipeline = VisionPipeline(source="rack", camera=PinholeCamera(width=240, height=160, fx=210.0, fy=210.0,
                                                                  cx=120.0, cy=80.0),
                              T_body_cam=frames.default_T_body_cam(), T_ned_rack=frames.default_T_ned_rack())
    nav = RecordingFilter(0.0, position_std_ned_m=(0.12, 0.03, 0.02))
    T_rack_cam = frames.T_rack_cam_from_T_ned_body(se3.make(np.eye(3), np.array([3.0, 1.0, -2.0])),
                                                   frames.default_T_ned_rack(), frames.default_T_body_cam())
    rack = RackOutput(True, T_rack_cam, np.eye(6) * 1e-8)
    d_cam = T_rack_cam[:3, :3].T @ np.array([0.0, 1.0, 0.0])  # the pipes' direction in the camera frame

    def along_and_across_std(rack_reset: bool) -> tuple[float, float]:
        pipeline.fuse(Measurement(1.0, 0, rack, None, 0.0, rack_reset=rack_reset), nav)
        C = np.asarray(nav.rack[-1].covariance)[:3, :3]
        across = np.cross(d_cam, [0.0, 0.0, 1.0])
        across /= np.linalg.norm(across)
        return math.sqrt(d_cam @ C @ d_cam), math.sqrt(across @ C @ across)

    along, across = along_and_across_std(False)  # seeded at the start pose: the floor only
    assert along == pytest.approx(0.01, rel=1e-3) and across == pytest.approx(0.01, rel=1e-3)
    along, across = along_and_across_std(True)
    assert along == pytest.approx(math.hypot(0.01, 0.12), rel=1e-3) and across == pytest.approx(0.01, rel=1e-3)
    nav.position_std_ned_m = (0.5, 0.5, 0.5)  # later growth of the estimate's uncertainty does not matter
    along, _ = along_and_across_std(False)
    assert along == pytest.approx(math.hypot(0.01, 0.12), rel=1e-3)


def test_ground_increment_with_the_pipes_in_view_is_barely_trusted() -> None:
    """A frame on which the rack tracker finds the pipes: the odometer also tracked features on them."""
    cam = PinholeCamera(width=240, height=160, fx=210.0, fy=210.0, cx=120.0, cy=80.0)
    pipeline = VisionPipeline(source="auto", camera=cam, T_body_cam=frames.default_T_body_cam(),
                              T_ned_rack=frames.default_T_ned_rack(),
                              rack_model=_small_rack(), initial_T_ned_body=np.eye(4))
    nav = RecordingFilter(0.0)
    cov = np.diag([0.002**2, 0.002**2, 0.001**2])
    out = odometer_output(True, 0.0, 0.0, 0.0, 0.03, -0.01, 0.002, cov, dt_s=0.0667)
    T_rack_cam = frames.T_rack_cam_from_T_ned_body(np.eye(4), frames.default_T_ned_rack(),
                                                   frames.default_T_body_cam())
    for rack_ok in (False, True):
        rack = RackOutput(rack_ok, T_rack_cam, np.eye(6) * 1e-6)
        pipeline.fuse(Measurement(1.0, 0, rack, out, 0.0), nav)
    clear, in_view = nav.ground
    np.testing.assert_allclose(clear.covariance, cov, atol=1e-15)
    np.testing.assert_allclose(np.diag(in_view.covariance),
                               np.diag(cov) + np.array([0.03, 0.01, 0.002 + 0.005]) ** 2, atol=1e-15)
    assert (in_view.dx_m, in_view.dy_m, in_view.dyaw_rad) == pytest.approx((0.03, -0.01, 0.002))


def _small_rack() -> Any:
    from companion.vision.rack import RackModel

    return RackModel.parallel(radii=[0.15, 0.2], gaps=[0.1], length=10.0)
