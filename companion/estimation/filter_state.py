"""The navigation filter's state (base of its mixins) and the records its history buffer holds.

Nominal state (33,) and error-state covariance (21, 21) in the layout of `companion.estimation.model`;
frames NED world, body FRD; stamps in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import chi2

from companion.checks import FloatArray, check_transform
from companion.estimation import model
from companion.estimation.types import ImuSample, NavFilterConfig
from companion.geometry import frames, se3

_POSE_IX = np.ix_(model.POSE_IDX, model.POSE_IDX)
_KINDS = ("rack", "ground", "range")


@dataclass(frozen=True)
class _SourceState:
    """Source-selection state; immutable so snapshots share it by reference."""

    source: str = "none"
    rack_good: int = 0
    rack_bad: int = 0
    rack_unsettled: int = 0
    ground_bad: int = 0
    last_rack_ok_s: float = -math.inf
    last_ground_ok_s: float = -math.inf
    clone_valid: bool = False
    clone_stamp_s: float = -math.inf


@dataclass(frozen=True)
class _Output:
    """The posterior right after the latest applied visual correction."""

    stamp_s: float
    x: FloatArray
    P_pose: FloatArray
    P_vel: FloatArray
    source: str


@dataclass
class _Measurement:
    """A buffered measurement (mutable only for its bookkeeping flags)."""

    stamp_s: float
    seq: int
    kind: str
    ok: bool
    data: tuple[Any, ...]
    counted: bool = False
    reset_counted: bool = False


@dataclass(frozen=True)
class _Snapshot:
    stamp_s: float
    gyro: tuple[float, ...]
    accel: tuple[float, ...]
    x: FloatArray
    P: FloatArray
    src: _SourceState
    output: _Output | None


class FilterState:
    """State of a `NavigationFilter` (see `__init__`), shared by its mixins (one module per concern)."""

    def __init__(
        self,
        config: NavFilterConfig | None = None,
        *,
        T_ned_rack: Any = None,
        T_body_cam: Any = None,
    ) -> None:
        self.config = config if config is not None else NavFilterConfig()
        cfg = self.config
        self._T_ned_rack = frames.default_T_ned_rack() if T_ned_rack is None else check_transform(
            T_ned_rack, "T_ned_rack"
        )
        self._T_body_cam = frames.default_T_body_cam() if T_body_cam is None else check_transform(
            T_body_cam, "T_body_cam"
        )
        self._T_cam_body = se3.inverse(self._T_body_cam)
        self._Ad_body_cam = se3.adjoint(self._T_body_cam)
        self._gate = {dof: float(chi2.ppf(cfg.gate_probability, dof)) for dof in (1, 2, 3, 6)}
        imu = cfg.imu
        # Continuous process noise on the diagonal of the 21 error states (per second).
        self._qdiag = np.concatenate(
            [
                np.zeros(3),
                np.full(3, imu.accel_noise_density_m_s2_sqrt_hz**2),
                np.full(3, imu.gyro_noise_density_rad_s_sqrt_hz**2),
                np.full(3, imu.gyro_bias_random_walk_rad_s2_sqrt_hz**2),
                np.full(3, imu.accel_bias_random_walk_m_s3_sqrt_hz**2),
                np.zeros(6),
            ]
        )
        self._x = np.zeros(model.STATE_SIZE)
        # The covariance is never modified in place (every writer rebinds it), so
        # snapshots share it by reference.
        self._P = np.zeros((model.ERROR_SIZE, model.ERROR_SIZE))
        self._F = model.new_transition()
        self._gyro: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._accel: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._t = -math.inf
        self._initialized = False
        self._imu: list[ImuSample] = []
        self._snaps: list[_Snapshot] = []
        self._snap_t: list[float] = []
        self._meas: list[_Measurement] = []
        self._meas_key: list[tuple[float, int]] = []
        self._seq = 0
        self._src = _SourceState()
        self._output: _Output | None = None
        self._counts: dict[str, int] = {}
        self._reset_counter = 0
        self._imu_count = 0
        self._last_stamp: dict[str, float] = dict.fromkeys(_KINDS, -math.inf)
        self._prune_countdown = 0

    def _count(self, key: str) -> None:
        self._counts[key] = self._counts.get(key, 0) + 1
