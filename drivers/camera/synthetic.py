"""The synthetic camera: renders the simulator's scene from a truth pose source.

Every 1/fps s of the injected clock the source samples
`pose_source() -> (stamp_s, T_ned_body) | None` on the event-loop thread (the
daemon feeds it from the link's SIM_STATE, so any autopilot simulator that
publishes SIM_STATE works), renders `render(T_ned_body) -> image` in the
capture thread, and stamps the frame with the clock's time of the tick.
`Frame.source_stamp_s` is the pose's stamp. No pose, or a pose older than
`max_pose_age_s`, gives no frame (the source goes LOST after `lost_after_s`).
`render` raising `CameraError` is a failed read (LOST, backoff, reopen): the
simulator injects a camera unplug that way. Any other exception is fatal
and surfaces from `next_frame` as `CameraError`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.clock import Clock
from companion.errors import CameraError
from drivers.camera.base import CameraSource, Capture

Render = Callable[[np.ndarray[Any, np.dtype[np.float64]]], Any]
PoseSource = Callable[[], "tuple[float, Any] | None"]


class SyntheticCamera(CameraSource):
    """Frames rendered from truth poses (see the module docstring)."""

    def __init__(
        self,
        clock: Clock,
        render: Render,
        pose_source: PoseSource,
        *,
        fps: float = 30.0,
        max_pose_age_s: float = 0.5,
        color: str = "gray",
        lost_after_s: float = 0.5,
        reopen_backoff_s: float = 0.2,
        reopen_backoff_max_s: float = 5.0,
    ) -> None:
        if not fps > 0:
            raise CameraError(f"fps: must be > 0, got {fps}")
        super().__init__(
            clock,
            name="synthetic",
            color=color,
            lost_after_s=lost_after_s,
            reopen_backoff_s=reopen_backoff_s,
            reopen_backoff_max_s=reopen_backoff_max_s,
        )
        self._render = render
        self._pose_source = pose_source
        self._period_s = 1.0 / float(fps)
        self._max_pose_age_s = float(max_pose_age_s)
        self._next_tick_s: float | None = None
        self.pose_misses = 0  # ticks without a fresh pose

    def _open(self) -> None:
        self._next_tick_s = None

    async def _tick(self) -> tuple[float, tuple[float, Any] | None]:
        now_s = self._clock.now()
        if self._next_tick_s is None:
            self._next_tick_s = now_s
        elif self._next_tick_s > now_s:
            await self._clock.sleep(self._next_tick_s - now_s)
        stamp_s = self._clock.now()
        # next tick on the 1/fps grid; ticks missed while rendering are skipped
        self._next_tick_s += self._period_s * max(1, math.floor((stamp_s - self._next_tick_s) / self._period_s) + 1)
        return stamp_s, self._pose_source()

    def _read(self) -> Capture | None:
        stamp_s, sample = self._run_on_loop(self._tick())
        if sample is None:
            self.pose_misses += 1
            return None
        pose_stamp_s, T_ned_body = sample
        if stamp_s - float(pose_stamp_s) > self._max_pose_age_s:
            self.pose_misses += 1
            return None
        T = np.asarray(T_ned_body, dtype=np.float64)
        if T.shape != (4, 4):
            raise TypeError(f"pose_source: T_ned_body must be 4x4, got shape {T.shape}")
        image = self._render(T)
        return Capture(np.asarray(image), stamp_s=stamp_s, source_stamp_s=float(pose_stamp_s))
