"""The navigation filter's measurement entry points: rack poses, ground increments, rangefinder readings.

Each input is checked and expressed as the filter measures it (body pose T_ned_body and its body-frame
covariance, NED increments in m / rad, slant range in m), then buffered on the timeline at its stamp (s).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError
from companion.estimation.filter_timeline import FilterTimeline
from companion.estimation.types import GroundEstimateLike, RackEstimateLike


class FilterInputs(FilterTimeline):
    """The public `add_*` measurement methods: input checks and conversions before buffering."""

    # ------------------------------------------------------------------ measurements: entry points

    def add_rack(self, est: RackEstimateLike, stamp_s: float, *, reset: bool = False) -> None:
        """Absolute pose from the rack tracker, captured at `stamp_s`.

        T_ned_body = T_ned_rack @ T_rack_cam @ inverse(T_body_cam); the camera-frame
        right-perturbation covariance maps to the body frame with Ad(T_body_cam).
        `reset`: the tracker was just moved to a pose found independently of the estimate (rack
        acquisition, the rack's end): taken like a switch to the rack, a reset when it disagrees.
        """
        if not bool(est.ok):
            self.add_absolute_pose(stamp_s, np.eye(4), np.eye(6), source="rack", ok=False)
            return
        T_rack_cam = _matrix(est.T_rack_cam, 4, "est.T_rack_cam")
        cov_cam = _matrix(est.covariance, 6, "est.covariance")
        T_ned_body = self._T_ned_rack @ T_rack_cam @ self._T_cam_body
        cov_body = self._Ad_body_cam @ cov_cam @ self._Ad_body_cam.T
        self.add_absolute_pose(stamp_s, T_ned_body, cov_body, source="rack", ok=True, reset=reset)

    def add_ground(self, est: GroundEstimateLike, stamp_s: float, *, restart: bool = False) -> None:
        """Planar increment (NED dx, dy, dyaw since the odometer's previous frame) captured at `stamp_s`.

        Feed every odometer output, ok or not, in order: the increment is applied
        between the clone (taken at the previous ground frame) and now.
        `restart=True` marks the odometer's first frame after its own reset (the
        increment is ignored and only the clone is taken). When the estimate
        carries `dt_s` (the time spanned by the increment, as
        `companion.vision.ground.GroundEstimate` does), dt_s == 0 means a first
        frame and stamp_s - dt_s must match the clone's stamp (the odometer may
        keep an older reference frame after a failure): see `add_relative_pose`.
        """
        ok = bool(est.ok)
        cov = _matrix(est.covariance, 3, "est.covariance") if ok else np.eye(3)
        dt_s = getattr(est, "dt_s", None)
        reference = None
        if ok and dt_s is not None:
            dt = float(dt_s)
            if dt <= 0.0:
                restart = True
            else:
                reference = float(stamp_s) - dt
        self.add_relative_pose(
            stamp_s, float(est.dx_m), float(est.dy_m), float(est.dyaw_rad), cov, source="ground", ok=ok,
            restart=restart, reference_stamp_s=reference,
        )

    def add_absolute_pose(
        self, stamp_s: float, T_ned_body: Any, covariance_6x6: Any, source: str = "rack", *, ok: bool = True,
        reset: bool = False,
    ) -> None:
        """Absolute body pose T_ned_body (4x4) at `stamp_s`.

        `covariance_6x6`: right perturbation of T_ned_body in the body frame, twist
        order (v, w): T_true = T_ned_body @ exp(d), d ~ N(0, cov). `ok=False`
        reports a failed frame (counts towards switching away from the source).
        `reset=True`: taken like a switch to the source (a reset when it disagrees, see `add_rack`).
        """
        if source != "rack":
            raise InputError(f"source: absolute poses come from 'rack', got {source!r}")
        T = _matrix(T_ned_body, 4, "T_ned_body")
        C = _matrix(covariance_6x6, 6, "covariance_6x6")
        if ok:
            R = T[:3, :3]
            if (
                not (np.isfinite(T).all() and np.isfinite(C).all())
                or np.abs(R.T @ R - np.eye(3)).max() > 1e-6
                or np.linalg.det(R) <= 0.0
                or not _is_pd(C)
            ):
                self._count("invalid")
                return
            data: tuple[Any, ...] = (R.copy(), T[:3, 3].copy(), 0.5 * (C + C.T), bool(reset))
        else:
            data = ()
        self._add("rack", float(stamp_s), ok, data)

    def add_relative_pose(
        self,
        stamp_s: float,
        dx_m: float,
        dy_m: float,
        dyaw_rad: float,
        covariance_3x3: Any,
        source: str = "ground",
        ok: bool = True,
        *,
        restart: bool = False,
        reference_stamp_s: float | None = None,
    ) -> None:
        """Planar increment (NED metres, rad) since the previous ground update; covariance (3, 3) of it.

        Applied as a relative-pose measurement between the clone (the pose at the
        previous ground update, ok or not) and the pose at `stamp_s`; afterwards
        the clone is reset to the pose at `stamp_s`. `ok=False`: no correction,
        clone reset. `restart=True`: no correction (the odometer restarted), clone
        reset. `reference_stamp_s` (optional): capture time of the frame the
        increment starts from; when it differs from the clone's stamp by more than
        1 ms the increment is not applied (counted as `unanchored_ground`).
        """
        if source != "ground":
            raise InputError(f"source: relative poses come from 'ground', got {source!r}")
        C = _matrix(covariance_3x3, 3, "covariance_3x3")
        if ok:
            finite = math.isfinite(dx_m) and math.isfinite(dy_m) and math.isfinite(dyaw_rad) and np.isfinite(C).all()
            if not finite or not _is_pd(C):
                self._count("invalid")
                return
            ref = math.nan if reference_stamp_s is None else float(reference_stamp_s)
            data: tuple[Any, ...] = (float(dx_m), float(dy_m), float(dyaw_rad), 0.5 * (C + C.T), bool(restart), ref)
        else:
            data = ()
        self._add("ground", float(stamp_s), ok, data)

    def add_range(self, height_m: float, stamp_s: float) -> None:
        """Downward rangefinder reading (m along body +z, i.e. slant range) at `stamp_s`.

        Modelled as (ground_z_ned_m - z_ned) / cos(tilt) over flat ground.
        """
        h = float(height_m)
        if not math.isfinite(h):
            self._count("invalid")
            return
        cfg = self.config
        if not cfg.range_min_m <= h <= cfg.range_max_m:
            self._count("out_of_range")
            return
        if not cfg.use_range:
            self._count("ignored_range")
            return
        self._add("range", float(stamp_s), True, (h,))


def _matrix(a: Any, n: int, name: str) -> FloatArray:
    """`a` as a float64 (n, n) array; raises InputError on a wrong shape, lets NaN through (counted later)."""
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric ({n}, {n}) array") from exc
    if arr.shape != (n, n):
        raise InputError(f"{name}: expected shape ({n}, {n}), got {arr.shape}")
    return arr


def _is_pd(C: FloatArray) -> bool:
    try:
        np.linalg.cholesky(0.5 * (C + C.T))
    except np.linalg.LinAlgError:
        return False
    return True
