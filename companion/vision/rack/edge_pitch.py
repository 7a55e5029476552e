"""The edges' own pitch, fed slowly into a vision-only track (a complementary filter on the rotation about rack x).

Flying over parallel pipes, the rotation about the axis across them (rack x, "pitch" below) and the translation
along them form a valley (`texture_check.py`). The texture points on the pipes and the ground points fix it
frame to frame, but only relative to the poses they were placed from: each is back-projected once, from the
pose of the frame it was found in, and the ground points from the last frame. So a pitch error present when
they were placed stays: after the issue's start (0.5 deg off), the stress bench's two-pipe rack kept its start
pitch error for 200-250 frames (scratch notes in docs/rack.md, "Twentieth session"), while the limbs alone
(their convergence in perspective) bring pitch back within 20 frames, as an edge-only track does.

The limbs do see pitch absolutely, but weakly and noisily: at the final pose of a frame, the Gauss-Newton step
that the edge rows alone ask for (`edge_pitch_step_rad`) corrects about half of the pitch error, with a
frame-to-frame spread of about 0.2 deg on that rack. In the frame's solve that information is outweighed by
the texture and ground rows (15-60 times more information about pitch), so the error never decays. Here a
fraction `gain` of that step is applied after each accepted frame, to the pose and to everything placed from
earlier poses together (the texture points, their reference patches' poses, the ground points' rays and
anchors): one rigid rotation of the whole estimate about the camera centre, which leaves this frame's residuals
as they were. Over many frames the edges' pitch then wins at a rate of about gain / 2 per frame (time constant
200 frames at 0.01), while the texture and ground keep the frame-to-frame motion: odometry for the fast part,
the limbs for the slow one.

Pure: arrays in, arrays out (the tracker owns the state it rotates, `tracker_maps.py`).
"""

from __future__ import annotations

import numpy as np

from companion.checks import FloatArray
from companion.vision.rack.model import PipeArrays
from companion.vision.rack.texture_check import valley_step_rad

__all__ = ["edge_pitch_step_rad", "rotate_about_centre", "rotate_on_pipes", "rotation_about_rack_x"]


def edge_pitch_step_rad(A: FloatArray, w: FloatArray, r: FloatArray, n_edge: int, R_rack_cam: FloatArray) -> float:
    """The rotation about rack x (rad) of the Gauss-Newton step that the first `n_edge` rows (the edges) of a
    solve ask for from its final pose: `A` (N, P) the rows (pose twist first: v, then w, camera frame), `w` (N,)
    their final weights, `r` (N,) the residuals at the final pose (px), `R_rack_cam` the final attitude."""
    return valley_step_rad(A, w, r, np.arange(int(n_edge)), R_rack_cam)


def rotation_about_rack_x(angle_rad: float) -> FloatArray:
    """Rotation matrix (3, 3) by `angle_rad` about the rack's x axis (right-handed)."""
    c, s = float(np.cos(angle_rad)), float(np.sin(angle_rad))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotate_about_centre(points: FloatArray, centre: FloatArray, R: FloatArray) -> FloatArray:
    """Points (K, 3) rotated by `R` (3, 3) about `centre` (3,), all in the rack frame (m)."""
    return np.asarray(centre + (points - centre) @ R.T)


def rotate_on_pipes(
    offset_rack: FloatArray, pipe: np.ndarray, pipes: PipeArrays, centre: FloatArray, R: FloatArray
) -> FloatArray:
    """Offsets (K, 3) from their pipes' axis starts (rack frame, m) of points on pipe surfaces, rotated by `R`
    about `centre` and put back on their pipe's surface (same axial position and azimuth, the pipe's radius):
    a texture point stays on its cylinder as the tracker's model requires."""
    if offset_rack.shape[0] == 0:
        return offset_rack.copy()
    starts = pipes.starts[pipe]
    moved = rotate_about_centre(starts + offset_rack, centre, R) - starts
    v = pipes.directions[pipe]
    axial = np.einsum("ni,ni->n", moved, v)
    radial = moved - axial[:, None] * v
    norm = np.maximum(np.linalg.norm(radial, axis=1), 1e-12)
    return np.asarray(axial[:, None] * v + radial * (pipes.radii[pipe] / norm)[:, None])
