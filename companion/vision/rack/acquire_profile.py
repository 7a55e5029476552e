"""Rack acquisition, robust hypotheses: the image's edge profile across the pencil of pipe lines.

Every line parallel to the pipes passes through their vanishing point; in the cross-section
plane of `acquire_lines` each such image line is one angle `theta`. Averaging, for every angle,
the image gradient across those lines (its component along the gradient of theta) over the
pixels of the line gives a 1-D profile in which every straight limb is a peak, however its
intensity step looks: a sharp silhouette, a limb darkened by shading, a pipe darker or brighter
than the ground. Camera positions (x, z) along the rack cross-section are then swept: each
predicts the model's limb angles (with occlusion and the field of view), and is scored by the
evidence under its limbs times the share of the profile's peaks it explains. Unlike limbs
grouped from line segments, this needs no polarity and no precise segment ends, and it offers
every placement of the pattern, so ambiguous placements are never missed. Pixels follow OpenCV;
angles in radians; lengths in metres.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray
from companion.vision.rack.acquire_edges import percentile
from companion.vision.rack.acquire_lines import LimbClusters
from companion.vision.rack.acquire_match import predict_limb_angles, refine_sections

GrayImage = np.ndarray[Any, np.dtype[np.uint8]]
Float32Image = np.ndarray[Any, np.dtype[np.float32]]


@functools.lru_cache(maxsize=8)
def _pixel_rays(camera: PinholeCamera, width: int, height: int) -> FloatArray:
    """Unit-depth rays (H, W, 3) (cam frame) of the pixel centres of the image resized to width x height."""
    sx, sy = camera.width / width, camera.height / height
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    uv = np.stack([(uu.ravel() + 0.5) * sx - 0.5, (vv.ravel() + 0.5) * sy - 0.5], axis=1)
    xy = camera.normalized(uv)
    rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1).reshape(height, width, 3)
    rays.flags.writeable = False
    return rays


@dataclass(frozen=True)
class PencilProfile:
    """Mean cross-line gradient (grey levels per px) `value` (B,) in angle bins starting at
    `theta0` (rad) of width `bin_rad`; `peak_theta` (P,) / `peak_value` (P,) its local maxima above
    half the reference level `ref` (the 99th percentile of the profile); `floor` its median (gravel,
    speckle or a grating raise the whole profile)."""

    theta0: float
    bin_rad: float
    value: FloatArray
    ref: float
    peak_theta: FloatArray
    peak_value: FloatArray
    floor: float = 0.0
    _dilated: dict[int, FloatArray] = field(default_factory=dict, compare=False, repr=False)

    def at(self, theta: FloatArray, tol_bins: int) -> FloatArray:
        """Largest profile value within `tol_bins` bins of each angle (0 outside the profile)."""
        b = np.round((theta - self.theta0) / self.bin_rad).astype(np.intp)
        n = self.value.size
        v = self._dilated.get(tol_bins)
        if v is None:  # the running maximum, once per profile and tolerance
            v = self.value
            if tol_bins > 0:
                pad = np.concatenate([np.zeros(tol_bins), v, np.zeros(tol_bins)])
                stack = np.stack([pad[k : k + n] for k in range(2 * tol_bins + 1)])
                v = stack.max(axis=0)
            self._dilated[tol_bins] = v
        inside = (b >= 0) & (b < n)
        return np.where(inside, v[np.clip(b, 0, n - 1)], 0.0)

    def claimed_peaks(self, theta: FloatArray, use: Any, tol_rad: float) -> Any:
        """(C, P) whether each peak lies within `tol_rad` of one of the angles `theta` (C, L) where `use` (C, L).

        Peaks are local maxima, at least two bins apart: only the few nearest each angle are compared."""
        P = self.peak_theta.size
        C = theta.shape[0]
        if P == 0:
            return np.zeros((C, P), dtype=bool)
        n_side = int(tol_rad / (2.0 * self.bin_rad)) + 2
        idx = np.searchsorted(self.peak_theta, theta)[None, :, :] + np.arange(-n_side, n_side)[:, None, None]
        ok = use[None, :, :] & (idx >= 0) & (idx < P)
        ok &= np.abs(self.peak_theta[np.clip(idx, 0, P - 1)] - theta[None, :, :]) <= tol_rad
        flat = (np.arange(C)[None, :, None] * P + idx)[ok]
        return np.bincount(flat, minlength=C * P).reshape(C, P) > 0


def image_gradient(small: GrayImage) -> tuple[Float32Image, Float32Image]:
    """The grey-level gradient (x, y) of `small` (levels per px, Sobel), shared by the directions' profiles."""
    img = small.astype(np.float32)
    return cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) * 0.125, cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) * 0.125


def pencil_profile(small: GrayImage, camera: PinholeCamera, limbs: LimbClusters, bin_rad: float,
                   gradient: tuple[Float32Image, Float32Image] | None = None) -> PencilProfile:
    """The profile of `small` (the image resized, any scale) for the pipe direction and basis of `limbs`;
    `gradient` its `image_gradient` when already computed."""
    h, w = small.shape
    rays = _pixel_rays(camera, w, h)
    # The angle of a pixel's ray in the cross-section; its component along the pipes does not matter.
    theta = np.arctan2(rays @ limbs.e_z, rays @ limbs.e_x).astype(np.float32)
    gx, gy = image_gradient(small) if gradient is None else gradient
    tx = cv2.Sobel(theta, cv2.CV_32F, 1, 0, ksize=3)
    ty = cv2.Sobel(theta, cv2.CV_32F, 0, 1, ksize=3)
    tn = np.sqrt(tx * tx + ty * ty) + np.float32(1e-12)
    across = np.abs(gx * tx + gy * ty) / tn  # gradient component across the pencil lines
    theta0 = float(theta.min())
    b = ((theta - theta0) / bin_rad).astype(np.intp).ravel()
    n_bins = int(b.max()) + 1
    cnt = np.bincount(b, minlength=n_bins).astype(np.float64)
    tot = np.bincount(b, weights=across.ravel().astype(np.float64), minlength=n_bins)
    # Lines that cross only a corner of the image have few pixels: weak evidence, not a peak.
    value = np.where(cnt >= 0.25 * min(h, w), tot / np.maximum(cnt, 1.0), 0.0)
    value = np.asarray(np.convolve(value, np.array([0.25, 0.5, 0.25]), mode="same"))
    ref = percentile(value[value > 0], 99) if np.any(value > 0) else 0.0
    floor = percentile(value[value > 0], 50) if np.any(value > 0) else 0.0
    is_peak = np.zeros(n_bins, dtype=bool)
    is_peak[1:-1] = (value[1:-1] >= value[:-2]) & (value[1:-1] > value[2:]) & (value[1:-1] >= 0.5 * ref)
    pk = np.flatnonzero(is_peak)
    return PencilProfile(theta0=theta0, bin_rad=bin_rad, value=value, ref=max(ref, 1e-9),
                         peak_theta=np.asarray(theta0 + (pk + 0.5) * bin_rad, dtype=np.float64), peak_value=value[pk],
                         floor=floor)


@dataclass(frozen=True)
class SweptHypothesis:
    """A camera position from the sweep: `x_m`, `z_m` (rack frame), `sign` (+1 along rack +y),
    `score` = evidence × explained, `evidence` (mean profile under the predicted limbs, relative
    to the reference, capped at 1), `explained` (share of the peak mass near predicted limbs)."""

    x_m: float
    z_m: float
    sign: int
    score: float
    evidence: float
    explained: float


def profile_scores(
    profile: PencilProfile, X: FloatArray, Z: FloatArray, S: FloatArray, x_axes: FloatArray, radii: FloatArray,
    theta_range: tuple[float, float], visible_length: Any, tol_bins: int, min_length_px: float,
    alpha: FloatArray | None = None, footprint_pitches: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Evidence and explained share (C,) of camera positions X, Z (C,) travelling along S (C,) x rack +y,
    rolled by `alpha` (C,) (rad, default 0) about the pipes relative to the profile's basis.

    Evidence: the profile under the predicted limbs relative to the reference (capped at 1),
    weighted by their visible length; explained: the share of the profile's peak mass within the
    tolerance of a predicted limb (peaks nothing predicts count against the position). With
    `footprint_pitches` the share is of the peaks over the rack's footprint only: between the
    outermost predicted limbs in view, widened on each side by that many mean pipe pitches (in
    angle). A pose one pipe off leaves a real pipe unexplained within a pitch of its footprint;
    stripes, kerbs and gravel further out are ground the model says nothing about. Peaks in the
    middle half of a pipe shown with both limbs (its highlight, its shading) do not count either,
    and the others count by their height above the profile's floor when at least a quarter of the way from
    it to the reference (on gravel every bin is a local maximum of the grain).
    """
    th, vis = predict_limb_angles(X, Z, np.zeros(X.size) if alpha is None else alpha, S, x_axes, radii)
    in_view = vis & (th > theta_range[0]) & (th < theta_range[1])
    L = np.where(in_view, visible_length(th.ravel()).reshape(th.shape), 0.0)
    L = np.where(min_length_px <= L, L, 0.0)
    ev = np.minimum(profile.at(th.ravel(), tol_bins).reshape(th.shape) / profile.ref, 1.0)
    tot_L = L.sum(axis=1)
    evidence = np.where(tot_L > 0, (ev * L).sum(axis=1) / np.maximum(tot_L, 1e-9), 0.0)
    if profile.peak_theta.size == 0:
        return evidence, np.zeros(X.size)
    claimed = profile.claimed_peaks(th, in_view, (tol_bins + 1) * profile.bin_rad)  # (C, P)
    mass = np.broadcast_to(profile.peak_value[None, :], claimed.shape)
    if footprint_pitches is not None:
        # Peaks counted by their height above the clutter floor, those a quarter of the way to the reference.
        fl = profile.floor
        above = profile.peak_value - fl
        mass = np.broadcast_to(np.where(above >= 0.25 * (profile.ref - fl), above, 0.0)[None, :], claimed.shape)
        use = in_view & (L > 0)
        lo = np.where(use, th, np.inf).min(axis=1)
        hi = np.where(use, th, -np.inf).max(axis=1)
        n_pipes = use.reshape(use.shape[0], -1, 2).any(axis=2).sum(axis=1)
        pitch = np.where(n_pipes > 1, (hi - lo) / np.maximum(n_pipes - 1, 1), hi - lo)
        margin = footprint_pitches * np.where(np.isfinite(pitch), pitch, 0.0)
        pt = profile.peak_theta[None, :]
        keep = (pt >= (lo - margin)[:, None]) & (pt <= (hi + margin)[:, None])
        # A pipe's own shading (the highlight, the terminator) lies well inside its silhouette.
        left, right = th[:, 0::2], th[:, 1::2]
        quarter = 0.25 * (right - left)
        shown = use[:, 0::2] & use[:, 1::2]
        inner = ((pt[:, :, None] > (left + quarter)[:, None, :]) & (pt[:, :, None] < (right - quarter)[:, None, :])
                 & shown[:, None, :]).any(axis=2)
        mass = np.where(keep & ~inner, mass, 0.0)
    total = mass.sum(axis=1)
    explained = np.where(total > 0, (claimed * mass).sum(axis=1) / np.maximum(total, 1e-12), 0.0)
    return evidence, explained


def sweep_section(
    profile: PencilProfile, x_axes: FloatArray, radii: FloatArray, height_m: float, height_std_m: float,
    signs: tuple[int, ...], theta_range: tuple[float, float], visible_length: Any, x_step_m: float,
    tol_bins: int, min_length_px: float, max_hypotheses: int, separation_m: float,
) -> list[SweptHypothesis]:
    """Score camera positions on a grid (x every `x_step_m` over the rack ± the ground footprint,
    z at the height ± 2 std) and return the best local maxima, at least `separation_m` apart."""
    slope = max(abs(np.tan(theta_range[0] + np.pi / 2)), abs(np.tan(theta_range[1] + np.pi / 2)))
    half_view = 1.2 * height_m * min(slope, 3.0)
    xs = np.arange(x_axes.min() - half_view, x_axes.max() + half_view + x_step_m, x_step_m)
    zs = height_m + height_std_m * np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    X, Z, S = (a.ravel() for a in np.meshgrid(xs, zs, np.asarray(signs, dtype=np.float64), indexing="ij"))
    evidence, explained = profile_scores(profile, X, Z, S, x_axes, radii, theta_range, visible_length, tol_bins,
                                         min_length_px)
    score = evidence * explained
    # Best z per (x, sign), then local maxima along x.
    n_x, n_z, n_s = xs.size, zs.size, len(signs)
    sc = score.reshape(n_x, n_z, n_s)
    iz = sc.argmax(axis=1)  # (n_x, n_s)
    best = np.take_along_axis(sc, iz[:, None, :], axis=1)[:, 0, :]
    ix_l, si_l = [], []
    for si in range(n_s):
        col = best[:, si]
        peak = np.zeros(n_x, dtype=bool)
        peak[1:-1] = (col[1:-1] >= col[:-2]) & (col[1:-1] > col[2:]) & (col[1:-1] > 0)
        at = np.flatnonzero(peak)
        ix_l.append(at)
        si_l.append(np.full(at.size, si))
    ix_all, si_all = np.concatenate(ix_l), np.concatenate(si_l)
    peak_score = best[ix_all, si_all]
    kept: list[SweptHypothesis] = []
    # Best first (ties in sign-then-x order, as a stable sort of the peaks), at least separation_m apart.
    for j in np.argsort(-peak_score, kind="stable"):
        if len(kept) >= max_hypotheses:
            break
        ix, si = int(ix_all[j]), int(si_all[j])
        x, sign = float(xs[ix]), int(signs[si])
        if all(sign != k.sign or abs(x - k.x_m) >= separation_m for k in kept):
            flat = (ix * n_z + iz[ix, si]) * n_s + si
            kept.append(SweptHypothesis(x_m=x, z_m=float(zs[iz[ix, si]]), sign=sign, score=float(peak_score[j]),
                                        evidence=float(evidence[flat]), explained=float(explained[flat])))
    return kept


def refine_on_peaks(
    profile: PencilProfile, hyps: list[SweptHypothesis], x_axes: FloatArray, radii: FloatArray,
    theta_range: tuple[float, float], height_m: float, height_std_m: float, alpha_std_rad: float, tol_rad: float,
    angle_std_rad: float,
) -> FloatArray:
    """(x, z, alpha) (C, 3) of swept positions refined by Gauss-Newton on the profile peaks their limbs
    fall on (all C at once).

    The sweep's grid is coarse in height (one std); the limb widths, hence the distance, need the
    peaks' positions, and a start a few centimetres off in height sends the edge check astray.
    """
    P = np.array([[h.x_m, h.z_m, 0.0] for h in hyps], dtype=np.float64).reshape(-1, 3)
    peaks = profile.peak_theta
    if peaks.size == 0 or not hyps:
        return P
    S = np.array([float(h.sign) for h in hyps])
    # Coarse to fine: a height a few per cent off moves the outer limbs by more than the final tolerance.
    for tol in (2.5 * tol_rad, tol_rad):
        th, vis = predict_limb_angles(P[:, 0], P[:, 1], P[:, 2], S, x_axes, radii)
        err = np.abs(th[:, :, None] - peaks[None, None, :])  # (C, 2M, P)
        k = np.argmin(err, axis=2)
        e = np.take_along_axis(err, k[:, :, None], axis=2)[:, :, 0]
        ok = vis & (th > theta_range[0]) & (th < theta_range[1]) & (e <= tol)
        matches = np.where(ok, k, -1).astype(np.intp)
        P = refine_sections(P, S, matches, peaks, x_axes, radii, height_m, height_std_m, alpha_std_rad,
                            angle_std_rad)
    return P
