"""Layout of the navigation filter's nominal state (33,) and error state (21,), and the [+] / [-] operators.

Slices and index arrays into both vectors (see `companion.estimation.model` for the layout: NED
positions / velocity in m and m/s, attitudes R_ned_body, biases body FRD); attitude errors are right
perturbations in the body frame.
"""

from __future__ import annotations

import numpy as np

from companion.checks import FloatArray
from companion.estimation.model_so3 import exp_and_right_jacobian
from companion.geometry import so3

STATE_SIZE = 33
ERROR_SIZE = 21
NAV_ERROR_SIZE = 15

# Slices into the nominal state.
P_SL = slice(0, 3)
V_SL = slice(3, 6)
R_SL = slice(6, 15)
BG_SL = slice(15, 18)
BA_SL = slice(18, 21)
PC_SL = slice(21, 24)
RC_SL = slice(24, 33)

# Slices into the error state.
EP = slice(0, 3)
EV = slice(3, 6)
ETH = slice(6, 9)
EBG = slice(9, 12)
EBA = slice(12, 15)
EPC = slice(15, 18)
ETHC = slice(18, 21)
# The 6 error coordinates of the current pose (dp, dtheta) and of the clone.
POSE_IDX = np.array([0, 1, 2, 6, 7, 8])
CLONE_IDX = np.arange(15, 21)


def new_state(
    p_ned_m: FloatArray,
    v_ned_m_s: FloatArray,
    R_ned_body: FloatArray,
    b_gyro_rad_s: FloatArray,
    b_accel_m_s2: FloatArray,
) -> FloatArray:
    """A nominal state (33,) with the clone equal to the current pose."""
    x = np.empty(STATE_SIZE)
    x[P_SL] = p_ned_m
    x[V_SL] = v_ned_m_s
    x[R_SL] = np.asarray(R_ned_body).ravel()
    x[BG_SL] = b_gyro_rad_s
    x[BA_SL] = b_accel_m_s2
    x[PC_SL] = p_ned_m
    x[RC_SL] = x[R_SL]
    return x


def rotation(x: FloatArray) -> FloatArray:
    """R_ned_body (3, 3) view of the current attitude in state `x`."""
    return x[R_SL].reshape(3, 3)


def clone_rotation(x: FloatArray) -> FloatArray:
    """R_ned_body (3, 3) view of the cloned attitude in state `x`."""
    return x[RC_SL].reshape(3, 3)


def boxplus(x: FloatArray, dx: FloatArray) -> FloatArray:
    """x [+] dx: a new state with the error `dx` (21,) injected (right perturbation on attitudes)."""
    y = x.copy()
    inject_in_place(y, dx)
    return y


def inject_in_place(x: FloatArray, dx: FloatArray) -> None:
    """x <- x [+] dx for the filter's own state buffer (the only in-place writer besides propagation)."""
    x[P_SL] += dx[EP]
    x[V_SL] += dx[EV]
    x[R_SL] = (rotation(x) @ exp_and_right_jacobian(dx[6], dx[7], dx[8])[0]).ravel()
    x[BG_SL] += dx[EBG]
    x[BA_SL] += dx[EBA]
    x[PC_SL] += dx[EPC]
    x[RC_SL] = (clone_rotation(x) @ exp_and_right_jacobian(dx[18], dx[19], dx[20])[0]).ravel()


def boxminus(x1: FloatArray, x0: FloatArray) -> FloatArray:
    """x1 [-] x0: the error (21,) with x1 = x0 [+] dx."""
    dx = np.empty(ERROR_SIZE)
    dx[EP] = x1[P_SL] - x0[P_SL]
    dx[EV] = x1[V_SL] - x0[V_SL]
    dx[ETH] = so3.log(rotation(x0).T @ rotation(x1))
    dx[EBG] = x1[BG_SL] - x0[BG_SL]
    dx[EBA] = x1[BA_SL] - x0[BA_SL]
    dx[EPC] = x1[PC_SL] - x0[PC_SL]
    dx[ETHC] = so3.log(clone_rotation(x0).T @ clone_rotation(x1))
    return dx
