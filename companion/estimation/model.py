"""State layout, IMU propagation and measurement models of the navigation filter.

Nominal state `x` (33 floats, one flat array so a snapshot is one copy):

    x[0:3]    p_ned_m        position of the body origin in NED
    x[3:6]    v_ned_m_s      velocity in NED
    x[6:15]   R_ned_body     attitude, row-major 3x3
    x[15:18]  b_gyro_rad_s   gyroscope bias, body FRD
    x[18:21]  b_accel_m_s2   accelerometer bias, body FRD
    x[21:24]  p_clone_ned_m  cloned (delayed) position, NED
    x[24:33]  R_clone        cloned attitude R_ned_body, row-major 3x3

Error state `dx` (21): dp (0:3), dv (3:6), dtheta (6:9), dbg (9:12), dba (12:15),
dp_clone (15:18), dtheta_clone (18:21). Positions, velocity and biases are
additive; attitudes use a RIGHT perturbation in the body frame:
R_true = R_est @ exp(dtheta). `boxplus` / `boxminus` implement exactly this.

Every function returning a Jacobian `H` follows r(x_est [+] eps) ~= r(x_est) - H eps,
i.e. r ~= H dx_true + noise with dx_true = x_true [-] x_est. The tests check each
one against central differences.
"""

from __future__ import annotations

# One module per concern, re-exported here: model_state (layout, [+] / [-]), model_so3 (scalar SO(3)
# helpers), model_propagation (IMU step and F), model_measurements (residuals and Jacobians),
# model_covariance (pose covariance conversions).
from companion.estimation.model_covariance import (
    body_to_error_pose_covariance,
    euler_rate_matrix,
    pose_covariance_xyz_rpy,
)
from companion.estimation.model_measurements import (
    absolute_pose_residual,
    range_residual,
    relative_pose_residual,
    wrap,
)
from companion.estimation.model_propagation import (
    new_transition,
    propagate_in_place,
)
from companion.estimation.model_so3 import (
    exp_and_right_jacobian,
    left_jacobian_inverse_so3,
    log_so3,
)
from companion.estimation.model_state import (
    BA_SL,
    BG_SL,
    CLONE_IDX,
    EBA,
    EBG,
    EP,
    EPC,
    ERROR_SIZE,
    ETH,
    ETHC,
    EV,
    NAV_ERROR_SIZE,
    P_SL,
    PC_SL,
    POSE_IDX,
    R_SL,
    RC_SL,
    STATE_SIZE,
    V_SL,
    boxminus,
    boxplus,
    clone_rotation,
    inject_in_place,
    new_state,
    rotation,
)

__all__ = [
    "BA_SL",
    "BG_SL",
    "CLONE_IDX",
    "EBA",
    "EBG",
    "EP",
    "EPC",
    "ERROR_SIZE",
    "ETH",
    "ETHC",
    "EV",
    "NAV_ERROR_SIZE",
    "PC_SL",
    "POSE_IDX",
    "P_SL",
    "RC_SL",
    "R_SL",
    "STATE_SIZE",
    "V_SL",
    "absolute_pose_residual",
    "body_to_error_pose_covariance",
    "boxminus",
    "boxplus",
    "clone_rotation",
    "euler_rate_matrix",
    "exp_and_right_jacobian",
    "inject_in_place",
    "left_jacobian_inverse_so3",
    "log_so3",
    "new_state",
    "new_transition",
    "pose_covariance_xyz_rpy",
    "propagate_in_place",
    "range_residual",
    "relative_pose_residual",
    "rotation",
    "wrap",
]
