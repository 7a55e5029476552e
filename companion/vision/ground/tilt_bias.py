"""Slowly varying roll/pitch bias of the attitude input, estimated from the ground points.

Beyond the paper. An IMU's roll/pitch error has a white part and a slowly wandering part (gyro
bias, accelerometer misalignment; modelled as first-order Gauss-Markov: standard deviation
`bias_std_rad`, correlation time `tau_s`). A tilt error e warps a frame's back-projected ground
points non-rigidly (`refine.tilt_fields`: field 0 has coefficient -e_roll, field 1 +e_pitch, in
the level frame, to first order). The white part differs between the two frames of a pair and
shows as a strong warp difference, which the per-pair refinement already fits. The slow part is
shared by both frames: it only shows through the field difference between the two point sets,
about e * |q| * |motion| / h per pair -- weak in one pair, but it acts on every pair the same
way. Left alone it leaks into the yaw and translation increments by ~ e * motion / h per frame
and, because it wanders, accumulates. So the odometer keeps a Kalman state of the bias and
refines each pair with a correlated prior:

    nuisance z = (beta_0, beta_1, wb_0, wb_1, sb, wa_0, wa_1, sa)
    warp coefficients of the current frame b: (beta_0 + wb_0, beta_1 + wb_1, sb)
    warp coefficients of the reference frame a: (beta_0 + wa_0, beta_1 + wa_1, sa)

beta: the shared slow bias (propagated from the last pair by the Gauss-Markov model); wb, sb: the
current frame's white tilt and relative height errors (fresh, zero-mean prior); wa, sa: the
reference frame's (the posterior of the previous pair when the reference is that pair's current
frame, so each frame's white error is carried, not double-counted). The posterior of
(beta, wb, sb) becomes the state of the current frame (`state_after`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.checks import FloatArray

NUM_NUISANCE = 8
# Rows: warp coefficients (tilt field 0, tilt field 1, height scale); columns: z.
MAP_B: FloatArray = np.array(
    [
        [1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
    ]
)
MAP_A: FloatArray = np.array(
    [
        [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
    ]
)
MAP_B.flags.writeable = False  # constants (refine caches their stack)
MAP_A.flags.writeable = False
_MIN_STD = 1e-9
# Indices in z of (beta_0, beta_1, wa_0, wa_1, sa): the reference frame's state; of (beta, wb, sb): the
# current frame's. Precomputed open meshes of both (hot path).
_REF_IDX = np.array([0, 1, 5, 6, 7])
_REF_IX = np.ix_(_REF_IDX, _REF_IDX)
_CUR_IDX = np.array([0, 1, 2, 3, 4])
_CUR_IX = np.ix_(_CUR_IDX, _CUR_IDX)
_EYE2 = np.eye(2)


@dataclass(frozen=True)
class TiltState:
    """The bias and the white errors of one frame (the last good frame), Gaussian.

    mean:     (5,) beta_0, beta_1 (slow tilt bias, rad, coefficients of `refine.tilt_fields` 0 and 1),
              w_0, w_1 (the frame's white tilt error, rad), s (its relative height error).
    cov:      (5, 5) covariance.
    stamp_s:  the frame's time (s).
    """

    mean: FloatArray
    cov: FloatArray
    stamp_s: float

    @property
    def bias_rad(self) -> FloatArray:
        """(2,) the slow tilt bias estimate (beta_0, beta_1), rad."""
        out: FloatArray = self.mean[:2].copy()
        return out


def pair_prior(
    state: TiltState | None,
    ref_stamp_s: float,
    cur_stamp_s: float,
    bias_std_rad: float,
    tau_s: float,
    white_std_rad: float,
    height_rel_std_ref: float,
    height_rel_std_cur: float,
) -> tuple[FloatArray, FloatArray]:
    """Prior mean (8,) and covariance (8, 8) of z for the pair (reference, current).

    `state`: the last good frame's state (None: nothing known yet). When it belongs to the
    reference frame (same stamp) its white errors are carried; otherwise only its bias is.
    The bias is propagated from the state's time to `cur_stamp_s` (Gauss-Markov, `tau_s`).
    """
    sb2 = max(bias_std_rad, _MIN_STD) ** 2
    sw2 = max(white_std_rad, _MIN_STD) ** 2
    mean = np.zeros(NUM_NUISANCE)
    cov = np.zeros((NUM_NUISANCE, NUM_NUISANCE))
    ref_mean = np.zeros(5)
    ref_cov = np.diag([sb2, sb2, sw2, sw2, max(height_rel_std_ref, _MIN_STD) ** 2])
    if state is not None:
        dt = max(cur_stamp_s - state.stamp_s, 0.0)
        phi = math.exp(-dt / tau_s)
        if state.stamp_s == ref_stamp_s:
            ref_mean = state.mean.copy()
            ref_cov = state.cov.copy()
        else:
            ref_mean[:2] = state.mean[:2]
            ref_cov[:2, :2] = state.cov[:2, :2]
        # Propagate the bias: beta <- phi beta + noise (cross terms scale by phi).
        ref_mean[:2] *= phi
        ref_cov[:2, :] *= phi
        ref_cov[:, :2] *= phi
        ref_cov[:2, :2] += _EYE2 * (1.0 - phi * phi) * sb2
    mean[_REF_IDX] = ref_mean
    cov[_REF_IX] = ref_cov
    cov[2, 2] = cov[3, 3] = sw2
    cov[4, 4] = max(height_rel_std_cur, _MIN_STD) ** 2
    return mean, 0.5 * (cov + cov.T)


def state_after(nuisance_mean: FloatArray, nuisance_cov: FloatArray, cur_stamp_s: float) -> TiltState:
    """The current frame's state from the pair posterior of z: (beta, wb, sb) marginal."""
    cov = nuisance_cov[_CUR_IX]
    return TiltState(nuisance_mean[_CUR_IDX].copy(), 0.5 * (cov + cov.T), float(cur_stamp_s))
