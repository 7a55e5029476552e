"""Drift-free texture point tracking: align each point's reference patch, warped into the current view.

Frame-to-frame Lucas-Kanade drifts: every frame it re-centres on a patch that the changing
viewpoint has slightly deformed (foreshortening across a cylinder changes quickly as the camera
slides sideways), and the small per-frame biases add up (about 1.5 px after 80 frames over a
two-pipe rack at 2-3 m, mostly across the pipes: exactly the sideways-slide / roll direction
that few pipes leave weakly observed). Here each point keeps the image patch it was detected in
(its *reference*) with the camera pose of that image; each frame the reference is warped into
the current view through the plane tangent to the pipe at the point (an affine warp, exact to
first order over a small window), and only a 2-D translation (plus a brightness gain and
offset) is solved by Gauss-Newton, starting from the frame-to-frame estimate. The tracked pixel
is then always the image of the same surface point.

All functions are vectorized over the K points (one `cv2.remap` per iteration for all patches).
Pixels follow OpenCV (integer coordinates are pixel centres).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray

_REMAP_STEPS = 32.0  # cv2.remap's sub-pixel resolution (INTER_TAB_SIZE)
Float32Array = np.ndarray[Any, np.dtype[np.float32]]
BoolArray = np.ndarray[Any, np.dtype[np.bool_]]


@functools.lru_cache(maxsize=8)
def _grid(half: int) -> FloatArray:
    """Integer offsets (S*S, 2) as (du, dv) of a (2*half+1)^2 window, row-major (v outer)."""
    k = np.arange(-half, half + 1, dtype=np.float64)
    dv, du = np.meshgrid(k, k, indexing="ij")
    g = np.stack([du.ravel(), dv.ravel()], axis=1)
    g.flags.writeable = False
    return g


def sample_patches(image_f32: Float32Array, uv: FloatArray, half: int) -> Float32Array:
    """Bilinear patches (K, S, S), S = 2*half+1, centred on `uv` (K, 2) of a float32 image."""
    k = uv.shape[0]
    s = 2 * half + 1
    if k == 0:
        return np.zeros((0, s, s), dtype=np.float32)
    g = _grid(half)
    mx = (uv[:, 0:1] + g[None, :, 0]).astype(np.float32)
    my = (uv[:, 1:2] + g[None, :, 1]).astype(np.float32)
    out = cv2.remap(image_f32, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(out, dtype=np.float32).reshape(k, s, s)


def tangent_plane_warps(
    T_rack_cam: FloatArray,
    camera: PinholeCamera,
    uv_cur: FloatArray,
    point_rack: FloatArray,
    normal_rack: FloatArray,
    ref_R_rack_cam: FloatArray,
    ref_o_rack: FloatArray,
) -> FloatArray:
    """Affine warps A (K, 2, 2): d(reference pixel) / d(current pixel) at `uv_cur` (K, 2).

    The current pixel's ray (camera pose `T_rack_cam`) meets the plane through `point_rack`
    (K, 3) with unit normal `normal_rack` (K, 3), both rack frame (m); the hit is projected into
    each point's reference camera (rotation `ref_R_rack_cam` (K, 3, 3), centre `ref_o_rack`
    (K, 3)). The columns are the reference-image displacements of a 1 px step in u and in v
    (finite differences of that exact chain). Points whose plane is seen edge-on get NaN.
    """
    k = uv_cur.shape[0]
    if k == 0:
        return np.zeros((0, 2, 2))
    R = T_rack_cam[:3, :3]
    o = T_rack_cam[:3, 3]
    steps = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    pix = (uv_cur[:, None, :] + steps[None, :, :]).reshape(-1, 2)  # (3K, 2)
    d = camera.unproject(pix) @ R.T  # rays, rack frame
    n3 = np.repeat(normal_rack, 3, axis=0)
    X3 = np.repeat(point_rack, 3, axis=0)
    den = np.einsum("ni,ni->n", n3, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("ni,ni->n", n3, X3 - o) / den
    hit = o + t[:, None] * d
    Rr = np.repeat(ref_R_rack_cam, 3, axis=0)
    p_ref = np.einsum("nji,nj->ni", Rr, hit - np.repeat(ref_o_rack, 3, axis=0))  # R^T (p - o)
    q = camera.project(p_ref).reshape(k, 3, 2)
    A = np.stack([q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]], axis=2)  # columns: du, dv
    bad = ~np.isfinite(A).all(axis=(1, 2)) | (np.abs(den.reshape(k, 3)) < 1e-9).any(axis=1)
    A[bad] = np.nan
    return np.asarray(A)


@dataclass(frozen=True)
class TemplateAlignment:
    """Per point (K): aligned pixel `uv` (K, 2), zero-mean normalized cross-correlation `ncc`
    of the final patches, `inside` false where the warped window leaves the stored reference
    (the view changed too much: re-reference the point)."""

    uv: FloatArray
    ncc: FloatArray
    inside: BoolArray


def align_templates(
    image_f32: Float32Array,
    uv0: FloatArray,
    warps: FloatArray,
    ref_patches: Float32Array,
    half_window: int,
    iterations: int = 4,
) -> TemplateAlignment:
    """Align the warped references to the current image, translation + brightness gain/offset.

    `uv0` (K, 2) start pixels (e.g. frame-to-frame Lucas-Kanade), `warps` (K, 2, 2) from
    `tangent_plane_warps`, `ref_patches` (K, S, S) the stored references (centred on the point
    in their own image, S = 2*H+1 with H >= half_window + 1). Inverse-compositional
    Gauss-Newton on the translation: the template and its gradient are fixed, only the current
    window is re-sampled (one remap for all points per iteration).
    """
    k = uv0.shape[0]
    if k == 0:
        return TemplateAlignment(uv=np.zeros((0, 2)), ncc=np.zeros(0), inside=np.zeros(0, dtype=bool))
    S = ref_patches.shape[1]
    H = (S - 1) // 2
    w = int(half_window)
    g1 = _grid(w + 1)  # one extra ring for the template gradient
    P1 = 2 * w + 3
    finite: BoolArray = np.asarray(np.isfinite(warps).all(axis=(1, 2)))
    A = np.where(finite[:, None, None], warps, 0.0)
    pos = A @ g1.T  # reference offsets (K, 2, P1*P1)
    inside = finite & (np.abs(pos).max(axis=(1, 2)) <= H - 1.0)
    # Sample the warped templates from the stack of reference patches (one atlas, one remap).
    atlas = ref_patches.reshape(k * S, S)
    # np.clip as maximum then minimum (the same values without np.clip's overhead)
    mx = np.minimum(np.maximum(H + pos[:, 0], 0.0), S - 1.0).astype(np.float32)
    my = (np.minimum(np.maximum(H + pos[:, 1], 0.0), S - 1.0) + (np.arange(k) * S)[:, None]).astype(np.float32)
    tpl = cv2.remap(atlas, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE).reshape(k, P1, P1)
    # Template gradient (central differences) stacked as (K, 2, P) rows for one batched product.
    grad = np.stack([0.5 * (tpl[:, 1:-1, 2:] - tpl[:, 1:-1, :-2]).reshape(k, -1),
                     0.5 * (tpl[:, 2:, 1:-1] - tpl[:, :-2, 1:-1]).reshape(k, -1)], axis=1)
    t = tpl[:, 1:-1, 1:-1].reshape(k, -1)
    t = t - t.mean(axis=1, keepdims=True)
    tt = (t * t).sum(axis=1)
    # The Hessian of the template (inverse compositional): fixed over the iterations.
    Hs = (grad @ grad.transpose(0, 2, 1)).astype(np.float64)  # (K, 2, 2)
    det = Hs[:, 0, 0] * Hs[:, 1, 1] - Hs[:, 0, 1] ** 2
    ok_h = det > 1e-9 * np.maximum(Hs[:, 0, 0] + Hs[:, 1, 1], 1e-12) ** 2
    Hinv = np.zeros_like(Hs)
    Hinv[ok_h] = np.linalg.inv(Hs[ok_h])
    gw = _grid(w).astype(np.float32)
    uv = uv0.astype(np.float64).copy()
    cur = np.zeros_like(t)
    cc = np.zeros(k)
    for _ in range(max(int(iterations), 1)):
        # cv2.remap resolves positions to 1/32 px: sample exactly there and step from there, so
        # that rounding does not bias the result (the window shares one fractional offset).
        uv = np.round(uv * _REMAP_STEPS) / _REMAP_STEPS
        uv32 = uv.astype(np.float32)
        cur = cv2.remap(image_f32, uv32[:, 0:1] + gw[None, :, 0], uv32[:, 1:2] + gw[None, :, 1], cv2.INTER_CUBIC,
                        borderMode=cv2.BORDER_REPLICATE)
        cur = cur - cur.mean(axis=1, keepdims=True)
        # Gain: the current window scaled to the template's contrast (exposure changes); its
        # energy, unlike its correlation with the template, does not shrink when misaligned.
        cc = (cur * cur).sum(axis=1)
        gain = np.sqrt(tt / np.maximum(cc, 1e-12))
        r = cur * gain[:, None] - t
        b = (grad @ r[:, :, None]).astype(np.float64)  # (K, 2, 1)
        step = np.minimum(np.maximum((Hinv @ b)[:, :, 0], -1.5), 1.5)
        uv = uv - step
    ncc = (cur * t).sum(axis=1) / np.sqrt(np.maximum(cc * tt, 1e-12))  # cc: the last window's energy
    return TemplateAlignment(uv=uv, ncc=np.asarray(ncc), inside=np.asarray(inside & ok_h))
