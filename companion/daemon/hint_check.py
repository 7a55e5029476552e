"""Check a rack lock that came from the start hint against the image (issue #16: a wrong lock is worse than none).

The rack tracker starts from the configured start pose (`DaemonOptions.initial_T_ned_body`), a hint. Put down
about one pipe pitch sideways from it, the tracker can lock straight onto the neighbouring pipe (the limbs of a
neighbour fit about as well), and nothing afterwards would tell: the daemon would send confident poses one pipe
off. So while that lock is unverified, every `every_frames` frames the daemon runs `acquire_rack` on the frame
(the deck prior: the configured start's height, y and heading) and compares a confident result with the
tracker's pose on the same frame, across the pipes (rack x), in height (rack z) and in heading:

* within the limits: the lock is verified, the checks stop;
* beyond them on two consecutive confident attempts that agree with each other (the first one carried to the
  second by the tracker's motion in between): the tracker is moved to the acquired pose (`re-acquire`);
* no confident result (e.g. over an outer pipe, where the close-range deck pattern does not exist): the lock
  stays unverified and the checks go on at the same rate.

Limits: max(floor, 3 std of the two poses' covariances), capped so that a lock one pipe off (a pitch is 0.4 m
or more on the racks flown) is always beyond them. Pure: arrays in, a frozen record out; no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray

__all__ = ["HintCheck", "HintChecker", "lock_difference"]

ACROSS_FLOOR_M = 0.05  # rack x and z: the acquisition and a right lock agree within ~1 cm at the deck's 0.6 m
ACROSS_CAP_M = 0.15  # below half the smallest pipe pitch: one pipe off is always a disagreement
HEADING_FLOOR_RAD = math.radians(3.0)
HEADING_CAP_RAD = math.radians(10.0)
SIGMAS = 3.0


@dataclass(frozen=True)
class HintCheck:
    """One check of the hint lock.

    outcome: "agrees" (verified), "disagrees" (first of two), "re-acquire" (two consistent disagreements: move
    the tracker), "no-confident-pose" (acquisition not confident; `status` says why);
    dx_m, dz_m: acquired minus tracked camera position across the pipes (rack x) and in height (rack z), m;
    dyaw_rad: acquired minus tracked heading about rack z (rad); limit_*: the thresholds they were held to.
    """

    outcome: str
    dx_m: float = 0.0
    dz_m: float = 0.0
    dyaw_rad: float = 0.0
    limit_x_m: float = 0.0
    limit_z_m: float = 0.0
    limit_yaw_rad: float = 0.0
    status: str = ""


def _rack_variances(T_rack_cam: FloatArray, cov_cam: FloatArray) -> tuple[float, float, float]:
    """Variances of rack x, rack z (m^2) and heading about rack z (rad^2) of a pose whose covariance is a right
    perturbation in the camera frame, twist (v, w): p_rack moves by R v, the attitude by R w."""
    R = np.asarray(T_rack_cam, dtype=np.float64)[:3, :3]
    cov = np.asarray(cov_cam, dtype=np.float64)
    P = R @ cov[:3, :3] @ R.T
    W = R @ cov[3:, 3:] @ R.T
    return max(float(P[0, 0]), 0.0), max(float(P[2, 2]), 0.0), max(float(W[2, 2]), 0.0)


def lock_difference(T_rack_cam_a: FloatArray, T_rack_cam_b: FloatArray) -> tuple[float, float, float]:
    """a minus b: camera position across the pipes (rack x, m), in height (rack z, m) and heading about rack z
    (rad, wrapped), the three things the image pins; the position along the pipes (rack y) is left out."""
    a = np.asarray(T_rack_cam_a, dtype=np.float64)
    b = np.asarray(T_rack_cam_b, dtype=np.float64)
    R = a[:3, :3] @ b[:3, :3].T  # rotation from b's attitude to a's, in the rack frame
    dyaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return float(a[0, 3] - b[0, 3]), float(a[2, 3] - b[2, 3]), dyaw


def _limit(var: float, floor: float, cap: float) -> float:
    return min(max(floor, SIGMAS * math.sqrt(var)), cap)


class HintChecker:
    """State of the checks of one hint lock (see the module docstring): `due` every `every_frames` frames (`tick`
    counts them) while `pending`; `check` takes one attempt's result."""

    def __init__(self, every_frames: int = 8) -> None:
        self.every_frames = max(int(every_frames), 1)
        self.pending = True  # the tracker's lock comes from the start hint and has not been checked yet
        self.verdict = "unverified"  # "unverified", "verified" (an attempt agreed), "re-acquired", "acquired"
        self.attempts = 0
        self._since_attempt = self.every_frames  # the first locked frame is checked at once
        self._candidate: tuple[FloatArray, FloatArray] | None = None  # (acquired, tracked) of a disagreement
        self.last: HintCheck | None = None

    @property
    def due(self) -> bool:
        """The next locked frame should get a check."""
        return self.pending and self._since_attempt >= self.every_frames

    def tick(self) -> None:
        """Count one frame since the last check."""
        self._since_attempt += 1

    def settle(self, verdict: str) -> None:
        """The lock no longer comes from the hint (e.g. an acquisition moved the tracker): stop checking."""
        self.pending = False
        self.verdict = verdict
        self._candidate = None

    def check(self, T_rack_cam_tracked: FloatArray, cov_tracked: FloatArray, T_rack_cam_acquired: FloatArray | None,
              cov_acquired: FloatArray | None, status: str = "") -> HintCheck:
        """One attempt: the tracker's pose on this frame and the confident acquisition's (None: not confident)."""
        self._since_attempt = 1  # this frame counts: the next check `every_frames` frames later
        self.attempts += 1
        if T_rack_cam_acquired is None or cov_acquired is None:
            self.last = HintCheck("no-confident-pose", status=status)
            return self.last
        dx, dz, dyaw = lock_difference(T_rack_cam_acquired, T_rack_cam_tracked)
        vx_t, vz_t, vyaw_t = _rack_variances(T_rack_cam_tracked, cov_tracked)
        vx_a, vz_a, vyaw_a = _rack_variances(T_rack_cam_acquired, cov_acquired)
        lim_x = _limit(vx_t + vx_a, ACROSS_FLOOR_M, ACROSS_CAP_M)
        lim_z = _limit(vz_t + vz_a, ACROSS_FLOOR_M, ACROSS_CAP_M)
        lim_yaw = _limit(vyaw_t + vyaw_a, HEADING_FLOOR_RAD, HEADING_CAP_RAD)
        limits = (lim_x, lim_z, lim_yaw)
        if abs(dx) <= lim_x and abs(dz) <= lim_z and abs(dyaw) <= lim_yaw:
            self.settle("verified")
            self.last = HintCheck("agrees", dx, dz, dyaw, *limits)
            return self.last
        outcome = "disagrees"
        if self._candidate is not None:
            # the previous disagreement, carried to this frame by the tracker's motion since, must agree with this
            # one: a single confident answer does not move a lock (docs/acquire.md, Limits: field appearance)
            T_acq_prev, T_trk_prev = self._candidate
            T_expected = T_acq_prev @ np.linalg.inv(T_trk_prev) @ np.asarray(T_rack_cam_tracked, dtype=np.float64)
            ex, ez, eyaw = lock_difference(T_rack_cam_acquired, T_expected)
            if abs(ex) <= ACROSS_FLOOR_M and abs(ez) <= ACROSS_FLOOR_M and abs(eyaw) <= HEADING_FLOOR_RAD:
                outcome = "re-acquire"
        if outcome == "re-acquire":
            self.settle("re-acquired")
        else:
            self._candidate = (np.array(T_rack_cam_acquired, dtype=np.float64),
                               np.array(T_rack_cam_tracked, dtype=np.float64))
        self.last = HintCheck(outcome, dx, dz, dyaw, *limits)
        return self.last
