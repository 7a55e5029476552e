"""A check of the texture points against the edges and the ground in the rack's weakest direction.

Flying over parallel pipes, the translation along them and the rotation about the axis across them (rack x)
form a valley:
- the limbs do not change when the camera moves along the pipes, and they see that rotation only through
  perspective (the limbs' convergence), which is weak;
- the ground points see one combination of the two (rotation minus translation over the ground's depth);
- the texture points on the pipes, at another depth, fix the other combination, and so decide the valley
  alone (one point carries about 15 times the limbs' information on that rotation, stress bench).

A point at the wrong depth then carries the pose along the valley, and nothing else in the solve objects.
Examples are a corner of an overhead beam that is not in the model but is seen over a pipe, or a point
placed during such a drift. On the stress bench's beam cell the pose went 40 cm / 3 deg off this way within
three seconds, while the edges and the ground alone held it within 0.3 deg (docs/rack.md, "Eighteenth
session").

The check: after each accepted frame, the Gauss-Newton step that the edge and ground rows alone ask for from
the final pose, about rack x (`valley_step_rad`), averaged over `AVERAGE_FRAMES` frames. In a consistent
solve it averages out: it stayed within 0.2 deg in every run of the stress bench's tuning half but the beam
cell's, and within 0.25 deg on the held-back beam runs. Beyond the threshold
(`RackTrackerConfig.texture_check_deg`), the texture is muted:
- its points are dropped;
- new points are tracked, but their rows get no weight, for at least `MUTE_FRAMES` frames and until the
  average is back under half the threshold.

Without the texture the edges and ground bring the pose back within a second. For `SUSPICION_FRAMES`
frames afterwards, a new point counts only once it has been tracked for `PROBATION_FRAMES` frames. In that
time a corner at the wrong depth drifts off its predicted position and the residual gate drops it. The
probation is not the default everywhere: it cost more than it saved while nothing was wrong (the same
notes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray

__all__ = ["AVERAGE_FRAMES", "MUTE_FRAMES", "PROBATION_FRAMES", "SUSPICION_FRAMES", "TextureCheck",
           "valley_step_rad"]

AVERAGE_FRAMES = 10.0  # time constant (frames) of the step's exponential average
MUTE_FRAMES = 25  # the texture stays muted at least this long once the check fires
SUSPICION_FRAMES = 150  # after a mute, new points are on probation for this many frames
PROBATION_FRAMES = 5  # frames a new point is tracked without weight while on probation
_RIDGE = 1.0  # keeps the edge + ground normal matrix invertible (parameters they do not see); px^2 units


def valley_step_rad(
    A: FloatArray, w: FloatArray, r: FloatArray, rows: np.ndarray, R_rack_cam: FloatArray
) -> float:
    """The rotation about rack x (rad) of the Gauss-Newton step that the rows `rows` of a solve ask for.

    `A` (N, P) the solve's rows (pose twist in the first six columns: v, then w in the camera frame),
    `w` (N,) their final weights, `r` (N,) the residuals at the final pose (px), `rows` the indices of the
    rows to use (the edges and the ground points), `R_rack_cam` the final attitude.
    """
    A_s = A[rows]
    Aw = A_s * w[rows, None]
    H = Aw.T @ A_s + _RIDGE * np.eye(A.shape[1])
    x = np.linalg.solve(H, Aw.T @ r[rows])
    return float(R_rack_cam[0, :] @ x[3:6])


@dataclass
class TextureCheck:
    """State of the check (mutable, one per tracker; a reset makes a new one). Frame indices count the
    tracker's frames."""

    mean_rad: float = 0.0  # exponential average of `valley_step_rad`
    muted: bool = False
    mute_start: int | None = None  # frame the last mute began

    def update(self, step_rad: float, frame: int, threshold_rad: float) -> bool:
        """Fold in one accepted frame's step (rad). Returns True when the texture becomes muted on this frame.

        A step that is not finite is left out: once in the average it would switch the check off for good.
        """
        if np.isfinite(step_rad):
            self.mean_rad += (step_rad - self.mean_rad) / AVERAGE_FRAMES
        size = abs(self.mean_rad)
        if self.muted:
            held = self.mute_start is not None and frame - self.mute_start < MUTE_FRAMES
            self.muted = held or size > 0.5 * threshold_rad
            return False
        if size > threshold_rad:
            self.muted, self.mute_start = True, frame
            return True
        return False

    def probation_frames(self, frame: int) -> int:
        """Frames a point must have been tracked before its rows count (0: from the start)."""
        if self.muted or self.mute_start is None or frame - self.mute_start >= SUSPICION_FRAMES:
            return 0
        return PROBATION_FRAMES

    def point_weights(self, age: np.ndarray, frame: int) -> FloatArray:
        """Weight factor (K,) of the texture points of this frame, from their ages (frames tracked)."""
        if self.muted:
            return np.zeros(age.shape[0])
        need = self.probation_frames(frame)
        if need == 0:
            return np.ones(age.shape[0])
        return np.asarray(age >= need, dtype=np.float64)
