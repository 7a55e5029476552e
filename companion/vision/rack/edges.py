"""1-D edge search along the image normal of rendered limbs, all samples in one `cv2.remap`.

For every sample the image is read along its normal at integer offsets k = -R..R px (tangent-
averaged over three parallel lines), the derivative g_k = I(k+1) - I(k-1) is formed, candidates
of the expected polarity are scored by |g| times a Gaussian prior on the distance, and the best
one is refined to sub-pixel precision with a parabola. The measurement is the signed distance
(px) along the normal from the rendered sample to the image edge. A bounded range and the
polarity keep the search from jumping to a neighbouring pipe (the facing limb across a gap has
the opposite polarity). Pixels follow OpenCV (integer coordinates are pixel centres).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.vision.rack.rack_jit import EINSUM_LANES_M, kernels

BoolArray = np.ndarray[Any, np.dtype[np.bool_]]
Float32Array = np.ndarray[Any, np.dtype[np.float32]]


@dataclass(frozen=True)
class EdgeMeasurements:
    """Per sample (N): signed offset along the normal (px), found flag, gradient sign and strength."""

    offset_px: FloatArray
    found: BoolArray
    sign: FloatArray
    strength: FloatArray
    # (N, M) zero-mean, unit-norm image profile on the inner side of the chosen edge (M = 0 unless asked).
    inner: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))


@functools.lru_cache(maxsize=64)
def _search_constants(R: int, prior_sigma_px: float | None) -> tuple[Float32Array, Float32Array]:
    """Read-only float32 offsets k = -R-1..R+1 (2R+3,) and the Gaussian distance prior (2R+1,)."""
    k = np.arange(-R - 1, R + 2, dtype=np.float32)
    sigma = float(prior_sigma_px) if prior_sigma_px is not None else max(float(R), 1.0)
    kk = np.arange(-R, R + 1, dtype=np.float32)
    prior: Float32Array = np.exp(-0.5 * (kk / sigma) ** 2)
    k.flags.writeable = False
    prior.flags.writeable = False
    return k, prior


def search_edges(
    image_f32: np.ndarray[Any, np.dtype[np.float32]],
    uv: FloatArray,
    normal: FloatArray,
    polarity: FloatArray,
    range_px: int,
    threshold: float,
    prior_sigma_px: float | None = None,
    tangent_offset_px: float = 0.0,
    forward_difference: bool = False,
    inner_ref: FloatArray | None = None,
    innermost_ratio: float = 0.0,
) -> EdgeMeasurements:
    """Search edges for N samples at `uv` (N, 2) along unit `normal` (N, 2).

    `polarity` (N,) is +1/-1 to accept only gradients of that sign along the normal (intensity
    increasing / decreasing outward), 0 to accept both. `threshold` is the minimum |g| (grey
    levels per 2 px). With `tangent_offset_px` > 0 the profile is the mean of three parallel
    lines that far apart (noise reduction without pre-blurring the image). With
    `forward_difference` the derivative is I(k+1) - I(k), located at k + 1/2 (less biased by
    shading ramps next to a sharp silhouette than the central difference).

    Expected edge profile: with `inner_ref` (N, M) each candidate's M samples on its inner side
    (k-M..k-1, towards the pipe) are compared with the sample's reference (zero-mean, unit-norm;
    a zero row = no reference) by normalised correlation c, and its score is multiplied by
    ((1 + c) / 2)^2. The pipe's own shading next to its limb is stable from frame to frame (and
    gain-invariant after normalisation); a ground or shadow edge a few pixels outside the limb
    has the limb and the ground in that window instead. The chosen candidates' inner profiles
    are returned in `inner` (for learning the reference).

    Innermost edge: with `innermost_ratio` > 0 a sample without a reference takes the innermost
    candidate (the one nearest the pipe's inside) whose score is at least that fraction of its best,
    not the best (`pick_in_gradients`). Inside its silhouette the cladding is smooth; beyond it the
    ground may carry stronger edges, e.g. a grating whose contrast against a shaded limb changes sign
    from sample to sample, so the limb's step is weaker than the grating's next one a few pixels out.
    """
    n = uv.shape[0]
    R = int(range_px)
    if n == 0:
        z = np.zeros(0)
        return EdgeMeasurements(offset_px=z, found=np.zeros(0, dtype=bool), sign=z, strength=z)
    k, prior = _search_constants(R, prior_sigma_px)
    M = 0 if inner_ref is None else int(inner_ref.shape[1])
    if M:
        k = np.arange(-R - 1 - M, R + 2, dtype=np.float32)  # M more samples on the inner side
    jit = kernels()
    if tangent_offset_px > 0:
        nrm = normal.astype(np.float32)
        base = uv.astype(np.float32)
        taps = np.array([-tangent_offset_px, 0.0, tangent_offset_px], dtype=np.float32)
        n_taps = taps.size
        tan = np.stack([-nrm[:, 1], nrm[:, 0]], axis=1)
        # positions (N, 3, 2R+3, 2)
        pos = (
            base[:, None, None, :]
            + taps[None, :, None, None] * tan[:, None, None, :]
            + k[None, None, :, None] * nrm[:, None, None, :]
        )
        mx = np.ascontiguousarray(pos[..., 0].reshape(n * n_taps, -1))
        my = np.ascontiguousarray(pos[..., 1].reshape(n * n_taps, -1))
    else:
        # One line per sample: base + k n (the same float32 arithmetic as the three-tap form).
        n_taps = 1
        if jit is not None:
            mx, my = jit.profile_maps(np.ascontiguousarray(uv, dtype=np.float64),
                                          np.ascontiguousarray(normal, dtype=np.float64), k)
        else:
            nrm = normal.astype(np.float32)
            base = uv.astype(np.float32)
            mx = base[:, 0:1] + k[None, :] * nrm[:, 0:1]
            my = base[:, 1:2] + k[None, :] * nrm[:, 1:2]
    prof = cv2.remap(image_f32, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if n_taps > 1:
        prof = prof.reshape(n, n_taps, -1).mean(axis=1)
    ks = jit if not forward_difference and R >= 1 and M in (0, EINSUM_LANES_M) else None
    if ks is not None:
        # The same arithmetic in one compiled call (`rack_jit.py`).
        ref32 = np.ascontiguousarray(inner_ref, dtype=np.float32) if M else np.zeros((n, 0), dtype=np.float32)
        ratio = np.broadcast_to(np.asarray(innermost_ratio, dtype=np.float32), (n,))
        offset, found, _b, g_b, inner = ks.pick_edges(
            np.ascontiguousarray(prof, dtype=np.float32), M, R, np.asarray(polarity, dtype=np.float32), prior,
            np.float32(threshold), ref32, M > 0, np.ascontiguousarray(ratio))
        return EdgeMeasurements(offset_px=offset, found=found, sign=np.sign(g_b).astype(np.float64),
                                strength=np.abs(g_b).astype(np.float64), inner=inner if M else np.zeros((n, 0)))
    windows = None
    if M:
        windows = _inner_windows(np.asarray(prof, dtype=np.float32), M, 2 * R + 1)
        prof = prof[:, M:]
    if forward_difference:
        g = prof[:, 2:] - prof[:, 1:-1]  # (N, 2R+1) at k + 1/2, k = -R..R
    else:
        g = prof[:, 2:] - prof[:, :-2]  # (N, 2R+1) at k = -R..R
    factor = None
    if windows is not None and inner_ref is not None:
        ref = np.asarray(inner_ref, dtype=np.float32)
        has_ref = _pairwise_sum([ref[:, m] * ref[:, m] for m in range(M)]) > 0.25  # = (ref * ref).sum(axis=1)
        ncc = np.einsum("ncm,nm->nc", windows, ref)  # windows is C-contiguous (N, 2R+1, M)
        # fit = clip(0.5 + 0.5 ncc, 0, 1), squared: the same float32 steps done in place on the fresh
        # (N, 2R+1) array (each step an allocation less; np.clip without its overhead).
        fit = np.multiply(ncc, np.float32(0.5), out=ncc)
        fit += np.float32(0.5)
        np.maximum(fit, np.float32(0.0), out=fit)
        np.minimum(fit, np.float32(1.0), out=fit)
        fit *= fit
        factor = fit if has_ref.all() else np.where(has_ref[:, None], fit, np.float32(1.0))
    innermost: Any = innermost_ratio
    if innermost_ratio > 0.0 and factor is not None:
        # a learnt inner profile already tells the limb from an edge beyond it: the rule is for the rest
        innermost = np.where(has_ref, 0.0, innermost_ratio)
    offset, found, b, g_b = pick_in_gradients(g, polarity, prior, R, threshold, factor, innermost)
    if forward_difference:
        offset = offset + 0.5
    inner = np.zeros((n, 0)) if windows is None else windows[np.arange(n), b].astype(np.float64)
    return EdgeMeasurements(
        offset_px=offset,
        found=found,
        sign=np.sign(g_b).astype(np.float64),
        strength=np.abs(g_b).astype(np.float64),
        inner=inner,
    )


def _pairwise_sum(slabs: list[Float32Array]) -> Float32Array:
    """Sum of M equal-shape arrays in the order numpy's `add.reduce` sums a contiguous axis of length M.

    That order (numpy's pairwise summation: M < 8 left to right; 8 <= M <= 128 eight running sums
    r_j += a[i + j] combined as ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)), then the
    remainder) makes the result bit-identical to `a.sum(axis=-1)`, while each step is one
    vectorised add over all samples and candidates instead of a reduction over a short axis.
    """
    m = len(slabs)
    if m < 8:
        acc = slabs[0]
        for s in slabs[1:]:
            acc = acc + s
        return acc
    if m > 128:
        raise ValueError(f"_pairwise_sum: at most 128 slabs (numpy splits longer axes), got {m}")
    r = list(slabs[:8])
    i = 8
    while i < m - m % 8:
        r = [r[j] + slabs[i + j] for j in range(8)]
        i += 8
    acc = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    for s in slabs[i:]:
        acc = acc + s
    return acc


def _inner_windows(prof: Float32Array, M: int, n_cand: int) -> Float32Array:
    """Zero-mean, unit-norm inner windows (N, n_cand, M) of every candidate, C-contiguous.

    Candidate k = -R + c (c < n_cand) has the inner window k-M..k-1 = prof[:, c+1 : c+1+M] (prof
    starts at -R-1-M). Computed per window position m on (N, n_cand) slabs (each step an add over
    all samples and candidates, not a reduction over a length-M axis: 2-3x faster at M = 8) with
    the sums in numpy's order (`_pairwise_sum`), so the values equal the direct
    `w - w.mean(axis=2)`, `w / max(sqrt((w * w).sum(axis=2)), 1e-3)` bit for bit.
    """
    slabs = [prof[:, 1 + m : 1 + m + n_cand] for m in range(M)]
    mean = _pairwise_sum(slabs) / np.float32(M)
    dev = [s - mean for s in slabs]
    norm = np.maximum(np.sqrt(_pairwise_sum([d * d for d in dev])), np.float32(1e-3))
    out = np.empty((prof.shape[0], n_cand, M), dtype=np.float32)
    for m in range(M):
        np.divide(dev[m], norm, out=out[:, :, m])
    return out


def pick_in_gradients(
    g: np.ndarray[Any, np.dtype[np.float32]],
    polarity: FloatArray,
    prior: Float32Array,
    R: int,
    threshold: float,
    factor: Any = None,
    innermost_ratio: float | FloatArray = 0.0,
) -> tuple[FloatArray, BoolArray, np.ndarray[Any, np.dtype[np.intp]], Float32Array]:
    """The edge of each sample in its gradient profile `g` (N, 2R+1) (offsets k = -R..R along the normal).

    `polarity` (N,) +1/-1 accepts only gradients of that sign, 0 either; candidates below `threshold` are
    ignored; the score is the signed gradient times the distance `prior` (2R+1,) (and `factor` (N, 2R+1)
    when given); the best one is refined by a parabola. With `innermost_ratio` > 0 (a scalar or one per
    sample, 0 = off for that sample) the innermost local maximum (lowest k) scoring at least that fraction
    of the best is taken instead of the best. Returns the offset (px, before any half-pixel
    shift of a forward difference), found, the chosen index b (1..2R-1) and the gradient there.
    """
    n = g.shape[0]
    pol = np.asarray(polarity, dtype=np.float32)[:, None]
    has_pol = pol != 0.0
    if has_pol.all():
        signed = g * pol
    elif not has_pol.any():
        signed = np.abs(g)
    else:
        signed = np.where(has_pol, g * pol, np.abs(g))
    score = np.where(signed >= threshold, signed, 0.0) * prior[None, :]
    if factor is not None:
        score = score * factor
    best = score.argmax(axis=1)
    if np.any(np.asarray(innermost_ratio) > 0.0):
        # The innermost local maximum scoring at least `innermost_ratio` x the best: inside its silhouette a
        # pipe's cladding is smooth, while the ground beyond may carry stronger edges (a grating whose
        # contrast against a shaded limb changes sign from sample to sample).
        # Interior candidates only (k = -R+1..R-1): a maximum at the range's end may be the flank of an edge
        # beyond it.
        top = score[np.arange(n), best][:, None]
        ratio = np.asarray(innermost_ratio, dtype=np.float32).reshape(-1, 1)
        mid = score[:, 1:-1]
        cand = (mid >= score[:, :-2]) & (mid >= score[:, 2:]) & (mid > 0.0) & (mid >= ratio * top) & (ratio > 0.0)
        best = np.where(cand.any(axis=1), cand.argmax(axis=1) + 1, best)
    width = 2 * R + 1
    row0 = np.arange(n) * width  # flat index of each row's k = -R
    found = np.asarray((score.ravel()[row0 + best] > 0.0) & (best > 0) & (best < 2 * R))
    b = np.minimum(np.maximum(best, 1), 2 * R - 1) if R >= 1 else best
    i_b = row0 + b
    flat = signed.ravel()
    s_m, s_0, s_p = flat[i_b - 1], flat[i_b], flat[i_b + 1]
    den = s_m - 2.0 * s_0 + s_p
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(den < -1e-6, 0.5 * (s_m - s_p) / den, 0.0)
    frac = np.minimum(np.maximum(frac, -0.5), 0.5)
    offset = (b - R).astype(np.float64) + frac
    return offset, found, b, g.ravel()[i_b]


# Candidate silhouette positions tried by `refine_silhouette`, relative to the rounded gradient peak (px).
_REFINE_STEP_PX = 0.25
_REFINE_DELTAS = np.arange(-1.5, 3.0 + 1e-9, _REFINE_STEP_PX)


@functools.lru_cache(maxsize=8)
def _silhouette_bases(w_in: int, w_out: int, blur_px: float) -> tuple[FloatArray, FloatArray]:
    """Offsets j = -w_in..w_out (K,) and orthonormal model bases Q (K, D * 4), four columns per candidate.

    Model of the profile across a cylinder's limb (j along the outward normal, silhouette at d):
    inside, a + b sqrt(d - j) -- near its silhouette a cylinder's normal turns as the square root of
    the distance, so any smooth shading of the normal rises (or falls) that way, steepest at the
    silhouette itself --; outside, the background c + e (j - d). Both are blurred by a Gaussian of
    `blur_px` (optics, pixel area). The least-squares residual of profile P at candidate d is
    |P|² - |Q_dᵀ P|² (Q_d an orthonormal basis of the model's columns), so all candidates of all
    samples cost one matrix product.
    """
    j = np.arange(-w_in, w_out + 1, dtype=np.float64)
    fine = np.linspace(-4.0 * blur_px, 4.0 * blur_px, 81)
    g = np.exp(-0.5 * (fine / blur_px) ** 2)
    g /= g.sum()
    Q = np.empty((j.size, _REFINE_DELTAS.size * 4))
    for i, d in enumerate(_REFINE_DELTAS):
        t = (j[:, None] + fine[None, :]) - d
        inside = t < 0.0
        cols = (inside * 1.0, np.sqrt(np.maximum(-t, 0.0)), (~inside) * 1.0, np.where(inside, 0.0, t))
        B = np.stack([(c * g[None, :]).sum(axis=1) for c in cols], axis=1)
        U, sv, _ = np.linalg.svd(B, full_matrices=False)
        U[:, sv < 1e-9 * sv[0]] = 0.0  # rank-deficient candidates (silhouette beyond the window)
        Q[:, 4 * i : 4 * i + 4] = U
    j.flags.writeable = False
    Q.flags.writeable = False
    return j, Q


def refine_silhouette(
    image_f32: np.ndarray[Any, np.dtype[np.float32]],
    uv: FloatArray,
    normal: FloatArray,
    offset_px: FloatArray,
    inner_px: int = 6,
    outer_px: int = 5,
    blur_px: float = 0.9,
    max_rel_rms: float = 0.0,
) -> FloatArray:
    """Silhouette offsets (N,) (px along the outward `normal`) near gradient-peak edges `offset_px`.

    The gradient peak of a shaded limb is not its silhouette: the shading of a cylinder changes
    fastest just inside it, so on pale cladding over a ground of similar brightness the peak lies
    1-2 px inside the pipe and moves with the ground's brightness and the view (a bias that
    differs from limb to limb, which a few parallel pipes turn into a roll / sideways-slide error
    of about a degree). Here the profile from `inner_px` inside to `outer_px` outside the rounded
    peak is fitted, for silhouette positions from 1.5 px inside to 3 px outside it in steps of
    0.25 px, by the limb model of `_silhouette_bases`; the best position (least squares,
    refined by a parabola) is returned. With `max_rel_rms` > 0 a sample keeps `offset_px` where
    the fit's rms residual exceeds that fraction of the profile's range. Vectorized over samples:
    one `cv2.remap` and one matrix product.
    """
    n = uv.shape[0]
    if n == 0:
        return np.zeros(0)
    j, Q = _silhouette_bases(int(inner_px), int(outer_px), float(blur_px))
    p = np.round(np.asarray(offset_px, dtype=np.float64))
    ks = kernels()
    if ks is not None:
        mx, my = ks.silhouette_maps(np.ascontiguousarray(uv, dtype=np.float64),
                                    np.ascontiguousarray(normal, dtype=np.float64), p, j)
    else:
        steps = p[:, None] + j[None, :]  # (N, K)
        mx = (uv[:, 0:1] + steps * normal[:, 0:1]).astype(np.float32)
        my = (uv[:, 1:2] + steps * normal[:, 1:2]).astype(np.float32)
    prof = cv2.remap(image_f32, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    proj = prof @ Q  # (N, D * 4)
    if ks is not None:
        # The rest in one compiled call (`rack_jit.py`), the same arithmetic.
        return np.asarray(ks.fit_silhouettes(prof, proj, p, _REFINE_DELTAS, _REFINE_STEP_PX,
                                             np.asarray(offset_px, dtype=np.float64), float(max_rel_rms),
                                             float(max(j.size - 4, 1))))
    sq = proj * proj
    # Each candidate's |Q_dᵀ P|²: its four columns added left to right (as a sum over a length-4 axis
    # does, bit for bit), as three adds of (N, D) slabs (a reduction over a short axis is slow).
    sse = np.sum(prof * prof, axis=1)[:, None] - (((sq[:, 0::4] + sq[:, 1::4]) + sq[:, 2::4]) + sq[:, 3::4])
    best = sse.argmin(axis=1)
    b = np.minimum(np.maximum(best, 1), _REFINE_DELTAS.size - 2)  # np.clip, without its overhead
    rows = np.arange(n)
    s_m, s_0, s_p = sse[rows, b - 1], sse[rows, b], sse[rows, b + 1]
    den = s_m - 2.0 * s_0 + s_p
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(den > 1e-9, 0.5 * (s_m - s_p) / den, 0.0)
    frac = np.minimum(np.maximum(frac, -0.5), 0.5)
    out = p + _REFINE_DELTAS[b] + frac * _REFINE_STEP_PX
    if max_rel_rms > 0.0:
        # Keep the gradient peak where the limb model does not explain the profile (a grating or a
        # beam next to the limb): its fit there is arbitrary.
        rms = np.sqrt(np.maximum(s_0, 0.0) / max(j.size - 4, 1))
        # The range per sample, reduced along the long axis of a transposed copy (a reduction over the
        # short axis of `prof` is 5x slower); max and min are exact, so the order does not matter.
        prof_t = prof.T.copy()
        contrast = prof_t.max(axis=0) - prof_t.min(axis=0)
        out = np.where(rms <= max_rel_rms * np.maximum(contrast, 1e-6), out, offset_px)
    return np.asarray(out)
