"""Persistent map of texture points on the pipes' surfaces (3-D, rack frame).

Points are found with Shi-Tomasi corners inside the pipes' image regions, back-projected by
intersecting the pixel's ray with the pipe cylinders (nearest hit), and stored relative to
their pipe's axis start so they follow the pipe when the gap estimates change. Each frame they
are tracked from the previous image with pyramidal Lucas-Kanade, seeded with the projection at
the predicted pose, so only a small window around each prediction is searched.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.corners import strong_corners
from companion.vision.rack.crossing_edges import on_crossing_edge
from companion.vision.rack.limbs import IntArray, ray_cylinder_hits
from companion.vision.rack.model import PipeArrays

MODELLED_MARGIN_M = 0.5  # corners this close to a pipe's end or a crossing pipe: modelled edges


@dataclass
class TextureMap:
    """Mutable map owned by one `RackTracker` (K points)."""

    pipe: IntArray
    offset_rack: FloatArray  # (K, 3) point minus its pipe's axis start, rack frame (m)
    uv_last: FloatArray  # (K, 2) last measured pixel
    n_obs: FloatArray  # (K,) number of observations averaged into offset_rack
    # Reference of each point for drift-free tracking (`templates.py`): the patch around the
    # point in the image it was (re-)referenced in, and that image's camera pose.
    ref_patch: np.ndarray[Any, np.dtype[np.float32]]  # (K, S, S) grey levels
    ref_R: FloatArray  # (K, 3, 3) R_rack_cam of the reference image
    ref_o: FloatArray  # (K, 3) camera centre of the reference image, rack frame (m)
    point_id: IntArray  # (K,) unique, increasing over the map's life (for diagnostics)
    age: IntArray  # (K,) frames each point has been tracked and kept since it was found
    next_id: int = 0

    @classmethod
    def empty(cls, patch_size: int = 1) -> TextureMap:
        return cls(pipe=np.zeros(0, dtype=np.intp), offset_rack=np.zeros((0, 3)), uv_last=np.zeros((0, 2)),
                   n_obs=np.zeros(0), ref_patch=np.zeros((0, patch_size, patch_size), dtype=np.float32),
                   ref_R=np.zeros((0, 3, 3)), ref_o=np.zeros((0, 3)), point_id=np.zeros(0, dtype=np.intp),
                   age=np.zeros(0, dtype=np.intp))

    def __len__(self) -> int:
        return int(self.pipe.size)

    def points_rack(self, pipes: PipeArrays) -> FloatArray:
        return np.asarray(pipes.starts[self.pipe] + self.offset_rack)

    def keep(self, mask: Any) -> None:
        self.pipe = self.pipe[mask]
        self.offset_rack = self.offset_rack[mask]
        self.uv_last = self.uv_last[mask]
        self.n_obs = self.n_obs[mask]
        self.ref_patch = self.ref_patch[mask]
        self.ref_R = self.ref_R[mask]
        self.ref_o = self.ref_o[mask]
        self.point_id = self.point_id[mask]
        self.age = self.age[mask]

    def add(
        self, pipe: IntArray, offset_rack: FloatArray, uv: FloatArray,
        ref_patch: np.ndarray[Any, np.dtype[np.float32]], T_rack_cam: FloatArray,
    ) -> None:
        """Append points (J): pipe, offset from the pipe's axis start (m), pixel, reference patch
        (J, S, S) and the pose of the image they were found in."""
        j = pipe.size
        self.pipe = np.concatenate([self.pipe, pipe])
        self.offset_rack = np.vstack([self.offset_rack, offset_rack])
        self.uv_last = np.vstack([self.uv_last, uv])
        self.n_obs = np.concatenate([self.n_obs, np.ones(j)])
        self.ref_patch = np.concatenate([self.ref_patch, ref_patch.astype(np.float32)])
        self.ref_R = np.concatenate([self.ref_R, np.broadcast_to(T_rack_cam[:3, :3], (j, 3, 3))])
        self.ref_o = np.vstack([self.ref_o, np.broadcast_to(T_rack_cam[:3, 3], (j, 3))])
        self.point_id = np.concatenate([self.point_id, np.arange(self.next_id, self.next_id + j, dtype=np.intp)])
        self.age = np.concatenate([self.age, np.zeros(j, dtype=np.intp)])
        self.next_id += j

    def normals_rack(self, pipes: PipeArrays) -> FloatArray:
        """Unit surface normals (K, 3) at the points, rack frame (radial from the pipe's axis)."""
        v = pipes.directions[self.pipe]
        radial = self.offset_rack - np.einsum("ni,ni->n", self.offset_rack, v)[:, None] * v
        return np.asarray(radial / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12))

    def refine(
        self, T_rack_cam: FloatArray, camera: PinholeCamera, pipes: PipeArrays, uv: FloatArray, max_obs: float
    ) -> None:
        """Average each point with the back-projection of its pixel `uv` (K, 2) onto its own pipe.

        A running mean over up to `max_obs` observations: the map then carries the average of
        the poses it was seen from instead of the error of the single pose it was created at.
        """
        if self.pipe.size == 0:
            return
        d = camera.unproject(uv) @ T_rack_cam[:3, :3].T
        t = ray_cylinder_hits(T_rack_cam[:3, 3], d, pipes)[np.arange(self.pipe.size), self.pipe]
        ok = np.isfinite(t)
        new = T_rack_cam[:3, 3] + t[ok, None] * d[ok] - pipes.starts[self.pipe[ok]]
        n = np.minimum(self.n_obs[ok] + 1.0, max_obs)
        self.offset_rack[ok] += (new - self.offset_rack[ok]) / n[:, None]
        self.n_obs[ok] = n


def track_points(
    prev: np.ndarray[Any, np.dtype[np.uint8]],
    cur: np.ndarray[Any, np.dtype[np.uint8]],
    uv_prev: FloatArray,
    uv_guess: FloatArray,
    window_px: int,
    levels: int,
) -> tuple[FloatArray, np.ndarray[Any, np.dtype[np.bool_]]]:
    """Lucas-Kanade from `prev` to `cur`, starting at `uv_guess`; returns (uv (K, 2), ok (K,))."""
    if uv_prev.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    p0 = uv_prev.astype(np.float32).reshape(-1, 1, 2)
    p1 = uv_guess.astype(np.float32).reshape(-1, 1, 2).copy()
    p1_out, status, _err = cv2.calcOpticalFlowPyrLK(
        prev,
        cur,
        p0,
        p1,
        winSize=(window_px, window_px),
        maxLevel=levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.02),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    uv = np.asarray(p1_out, dtype=np.float64).reshape(-1, 2)
    ok = status.ravel().astype(bool) & np.all(np.isfinite(uv), axis=1)
    return uv, ok


def detect_points(
    gray: np.ndarray[Any, np.dtype[np.uint8]],
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    pipes: PipeArrays,
    pipe_polygons: list[FloatArray],
    existing_uv: FloatArray,
    max_new: int,
    min_distance_px: float,
    min_incidence_cos: float,
    min_corner_ratio: float = 0.0,
    crossing_edge_fraction: float = 0.0,
) -> tuple[IntArray, FloatArray, FloatArray]:
    """New texture points: (pipe (J,), offset from the pipe's axis start (J, 3), uv (J, 2)).

    With `crossing_edge_fraction` > 0 a corner next to a straight edge that steps the grey level over that
    fraction of its pipe's width is not taken (`crossing_edges.py`: an unmodelled occluder's outline, whose
    corners slide along the pipe); junctions with modelled crossing pipes are kept (`_on_crossing_edges`).

    With `min_corner_ratio` > 0 a corner's minimum structure-tensor eigenvalue must reach that
    multiple of the median inside the pipes' regions (their noise floor): Shi-Tomasi's quality
    level is relative to the strongest corner, so on plain cladding it accepts noise and JPEG
    blocks as points.
    """
    empty = (np.zeros(0, dtype=np.intp), np.zeros((0, 3)), np.zeros((0, 2)))
    if max_new <= 0 or not pipe_polygons:
        return empty
    mask = np.zeros(gray.shape[:2], dtype=np.uint8)
    for poly in pipe_polygons:
        cv2.fillConvexPoly(mask, np.rint(poly).astype(np.int32), 255)
    for q in existing_uv:
        cv2.circle(mask, (round(q[0]), round(q[1])), int(min_distance_px), 0, -1)
    x, y, w, h = cv2.boundingRect(mask)
    if w < 8 or h < 8:
        return empty
    roi, roi_mask = gray[y : y + h, x : x + w], mask[y : y + h, x : x + w]
    # With a floor: one eigenvalue pass, only the corners above the floor ordered and thinned (`corners.py`;
    # the same corners as OpenCV's detector then the floor).
    corners = strong_corners(roi, roi_mask, int(2 * max_new), float(min_distance_px), 0.02, 7, min_corner_ratio) \
        if min_corner_ratio > 0 else None
    if corners is None:
        found = cv2.goodFeaturesToTrack(roi, maxCorners=int(2 * max_new), qualityLevel=0.02,
                                        minDistance=float(min_distance_px), mask=roi_mask, blockSize=7)
        if found is None:
            return empty
        corners = np.asarray(found, dtype=np.float32).reshape(-1, 2)
        if min_corner_ratio > 0:
            ev = np.asarray(cv2.cornerMinEigenVal(roi, 7, ksize=3))
            inside = roi_mask > 0
            floor = float(np.median(ev[inside])) if np.any(inside) else 0.0
            c = np.rint(corners).astype(np.intp)
            corners = corners[ev[np.clip(c[:, 1], 0, h - 1), np.clip(c[:, 0], 0, w - 1)]
                          >= min_corner_ratio * floor]
    uv = corners.astype(np.float64) + np.array([x, y], dtype=np.float64)
    if uv.shape[0] == 0:
        return empty
    rays_cam = camera.unproject(uv)
    R = T_rack_cam[:3, :3]
    o = T_rack_cam[:3, 3]
    d = rays_cam @ R.T
    t = ray_cylinder_hits(o, d, pipes)
    best = np.argmin(t, axis=1)
    tb = t[np.arange(t.shape[0]), best]
    hit = np.isfinite(tb)
    p = o + tb[:, None] * d
    rel = p - pipes.starts[best]
    ax = np.einsum("ni,ni->n", rel, pipes.directions[best])
    radial = rel - ax[:, None] * pipes.directions[best]
    nrm = radial / pipes.radii[best][:, None]
    cosang = np.abs(np.einsum("ni,ni->n", nrm, d))
    good = hit & (cosang >= min_incidence_cos)
    if crossing_edge_fraction > 0.0 and np.any(good):
        g = np.flatnonzero(good)
        good[g[_on_crossing_edges(gray, T_rack_cam, camera, pipes, best[g], pipes.starts[best[g]], ax[g], d[g],
                                  uv[g], crossing_edge_fraction)]] = False
    idx = np.flatnonzero(good)[:max_new]
    return best[idx].astype(np.intp), rel[idx], uv[idx]


def _on_crossing_edges(
    gray: np.ndarray[Any, np.dtype[np.uint8]], T_rack_cam: FloatArray, camera: PinholeCamera, pipes: PipeArrays,
    pipe: IntArray, start_rack: FloatArray, s_axial: FloatArray, d_rack: FloatArray, uv: FloatArray,
    min_fraction: float,
) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """`crossing_edges.on_crossing_edge` for corners (J) on pipes `pipe` (J,) at `s_axial` (J,) m along them from
    their axis starts `start_rack` (J, 3), seen along the rays `d_rack` (J, 3): the pipe's image axis, centre
    line and width there from the model at the pose.

    Only where the model explains no edge across the pipe: corners within `MODELLED_MARGIN_M` of their pipe's
    ends or of a modelled pipe crossing it are left to the tracker as before. A pipe's end is a fixed place on
    it (on the sim's frames of the paper's rack its corners are the along-pipe anchors of the take-off), and
    on those 360x240 frames the crossing pipe's junctions carry much of the along-pipe information while it is
    in view; judged too, a track with the attitude prior ran away (`bench/rack_field_loop.py --library --seed
    1`, 2026-11-28: 462 cm RMS, 3.5 without the test). The margin covers a pose 30 cm off along the pipes: with
    25 cm, seed 2's track (20-30 cm off from frame 250 with or without the test) ran away once the crossing
    pipe's junctions fell outside it (72 cm RMS against 20.65).
    """
    near_end = (s_axial < MODELLED_MARGIN_M) | (s_axial > pipes.lengths[pipe] - MODELLED_MARGIN_M)
    hits = ray_cylinder_hits(T_rack_cam[:3, 3], d_rack, pipes, MODELLED_MARGIN_M)  # (J, M)
    crossing = np.abs(pipes.directions @ pipes.directions.T) < 0.9  # (M, M): pipes not parallel to each other
    modelled = near_end | np.any(crossing[pipe] & np.isfinite(hits), axis=1)
    out = np.zeros(pipe.size, dtype=bool)
    judge = np.flatnonzero(~modelled)
    if judge.size == 0:
        return out
    pipe, d_rack, uv = pipe[judge], d_rack[judge], uv[judge]
    R, o = T_rack_cam[:3, :3], T_rack_cam[:3, 3]
    v = pipes.directions[pipe]
    r = pipes.radii[pipe][:, None]
    centre = start_rack[judge] + s_axial[judge][:, None] * v
    across = np.cross(v, d_rack)
    across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-12)
    # the axis point abeam the corner, 5 cm further along, and the limbs across the view (one projection)
    q = camera.project((np.concatenate([centre, centre + 0.05 * v, centre + r * across, centre - r * across])
                        - o) @ R).reshape(4, -1, 2)
    axis = q[1] - q[0]
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    offset = np.einsum("ni,ni->n", uv - q[0], np.stack([-axis[:, 1], axis[:, 0]], axis=1))
    out[judge] = on_crossing_edge(gray, uv, axis, offset, np.linalg.norm(q[2] - q[3], axis=1), min_fraction)
    return out
