"""The state the daemon's tasks share, and the helpers more than one task uses.

`DaemonState` holds every attribute of `companion.daemon.app.Daemon`, so that each task module (a mixin
of `DaemonState`) sees them all: `wiring` (build and open), `imu_task`, `vision_task`, `control_task`,
`missions`, `watchdog` and `health`. Shared here: the event log, the GCS text, the hold command and the
landed / mission-active tests. `FrameRecord` is what the vision task hands to frame observers.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from companion.checks import FloatArray, check_transform
from companion.clock import Clock, SystemClock
from companion.daemon.arming import ModeOwner
from companion.daemon.flight import FlightFolder
from companion.daemon.options import DaemonOptions
from companion.daemon.pipeline import Measurement, VisionPipeline
from companion.errors import CompanionError

__all__ = ["DaemonState", "FrameRecord"]


@dataclass(frozen=True)
class FrameRecord:
    """What happened to one frame (for observers: the simulator's report, tests)."""

    seq: int
    capture_s: float
    source_stamp_s: float | None
    process_s: float
    nav: Any
    sent: bool
    sent_s: float
    sent_perf_s: float
    measurement: Measurement


@dataclass
class _Counters:
    frames: int = 0
    poses_sent: int = 0
    poses_withheld: int = 0
    vision_errors: int = 0
    imu_samples: int = 0
    control_steps: int = 0
    watchdog_steps: int = 0
    health_reports: int = 0


@dataclass
class _SafetyView:
    """The safety state the daemon acts on (filled from the SafetyManager's decisions)."""

    send_poses: bool = True
    allow_mission: bool = True
    last_action: str = "none"
    events: list[dict[str, Any]] = field(default_factory=list)


class DaemonState:
    """The daemon's attributes and shared helpers; `companion.daemon.app.Daemon` adds the tasks."""

    def __init__(self, config: Any, *, clock: Clock | None = None, options: DaemonOptions | None = None) -> None:
        self.config = config
        self.clock: Clock = clock if clock is not None else SystemClock()
        self.options = options or DaemonOptions()
        self.link: Any | None = None
        self.camera: Any | None = None
        self.camera_model: Any | None = None
        self.pipeline: VisionPipeline | None = None
        self.nav_filter: Any | None = None
        self.safety: Any | None = None
        self.api_server: Any | None = None
        self.flight: FlightFolder | None = None
        self.executor: Any | None = None
        self.mission_id: str | None = None
        self.counters = _Counters()
        self.frame_observers: list[Callable[[FrameRecord], None]] = []
        self.event_observers: list[Callable[[str, dict[str, Any]], None]] = []
        self.last_nav: Any | None = None
        self.last_pose_sent_s: float | None = None
        self.camera_ok = True
        self._tasks: list[asyncio.Task[None]] = []
        self._worker: concurrent.futures.ThreadPoolExecutor | None = None
        self._shutdown = asyncio.Event()
        self._stopped = asyncio.Event()
        self._shutdown_reason = ""
        self._started = False
        self._start_s = self.clock.now()
        self._notifier: Any | None = None
        self._servo: Any | None = None
        self._request_task: asyncio.Task[None] | None = None
        self._safety_view = _SafetyView()
        self._rack_reset_pending = False
        self._rack_fail_streak = 0
        self._rack_reset_reason = ""  # why the next re-seed of the rack tracker from the filter (flight log)
        # after an acquisition, until the filter takes the rack pose: no re-seed from its (older) estimate
        self._hold_rack_reseed = False
        self._unsubscribe: list[Callable[[], Any]] = []
        self._home_T_ned_body: FloatArray | None = None
        self._last_command: Any | None = None
        self._photo_index = 0
        self._pending_photo: tuple[int, Any] | None = None
        self._latest_frame: Any | None = None
        self._imu_sample_cls: Any | None = None
        self._watcher: asyncio.Task[None] | None = None
        self._stopping = False
        self._safety_retry_s = 0.0
        self._turn_key: tuple[int, str] | None = None
        self._turn_pivot: FloatArray | None = None
        self._last_acq_text_s = float("-inf")  # last 'acquiring the rack' STATUSTEXT (clock s)
        self.mode_owner = ModeOwner()
        self._last_health_line = ""
        self._latency_ms: collections.deque[float] = collections.deque(maxlen=100)
        self._vision_ms: collections.deque[float] = collections.deque(maxlen=100)  # measure() per frame
        self._safety_paused = False  # the running mission was paused by a safety hold
        self._mode_task: asyncio.Task[None] | None = None
        self._health_prev: tuple[int, int, int, int, float] = (0, 0, 0, 0, self.clock.now())
        self._range_stamp_s: float | None = None
        self.last_fresh_pose_s: float | None = None
        self.safety_output: Any | None = None
        self.mission_refused: dict[str, Any] | None = None
        self.mission_limits: Any | None = None
        # the position along the pipes is still the configured start's (mirrored from the pipeline after each
        # fusion; companion.daemon.along_pipe_task), and the mission's rack-end search (None: not started)
        self.along_pipe_from_start_hint = False
        # how the rack tracker's lock was established (`HintCheckTask.rack_lock_state`, mirrored after each frame)
        self.rack_lock = "unchecked"
        self._along_pipe_search: Any | None = None
        self._along_pipe_report_s = float("-inf")
        opts = self.options
        self.turn_first_rad = (math.radians(config.mission.turn_first_deg) if opts.turn_first_rad is None
                               else float(opts.turn_first_rad))
        self.record_frames = bool(config.logging.record_frames if opts.record_frames is None else opts.record_frames)
        self.rack_along_pipe_std_m = float(config.vision.rack_along_pipe_std_m if opts.rack_along_pipe_std_m is None
                                           else opts.rack_along_pipe_std_m)
        self.frame_gap_reset_s = float(config.vision.frame_gap_reset_s if opts.frame_gap_reset_s is None
                                       else opts.frame_gap_reset_s)
        vg = opts.visual_ground_z_ned_m if opts.visual_ground_z_ned_m is not None else \
            config.camera.sim_ground_z_ned_m
        self.visual_ground_z_ned_m: float | None = None if vg is None else float(vg)

    @property
    def T_body_cam(self) -> FloatArray:
        return check_transform(self.config.mount.T_body_cam, "mount.T_body_cam")

    @property
    def T_ned_rack(self) -> FloatArray:
        return check_transform(self.config.rack.T_ned_rack, "rack.T_ned_rack")

    # ================================================================ shared by the tasks
    def _event(self, name: str, level: int = logging.INFO, **fields: Any) -> None:
        if self.flight is not None:
            self.flight.log.event(name, level=level, **fields)
        for obs in list(self.event_observers):
            with contextlib.suppress(Exception):
                obs(name, fields)

    def _gcs_text(self, text: str, severity: str = "info") -> None:
        """A "companion: ..." STATUSTEXT to the GCS (best effort)."""
        if self.link is not None:
            with contextlib.suppress(Exception):
                self.link.statustext(f"companion: {text}"[:200], severity)

    async def _hold(self) -> None:
        """Put the autopilot in its hold mode; if refused (no position), in its altitude-hold mode."""
        link = self.link
        assert link is not None
        try:
            await link.hold()
        except CompanionError as exc:
            fallback = {"ardupilot": "ALT_HOLD", "px4": "ALTCTL"}.get(str(link.state.autopilot or ""))
            if fallback is None:
                raise
            self._event("hold-refused", level=logging.WARNING, error=str(exc), fallback=fallback)
            await link.set_mode(fallback)

    def _mission_active(self) -> bool:
        from companion.mission import State

        return self.executor is not None and self.executor.state in (State.RUNNING, State.PAUSED)

    def _landed(self) -> bool:
        """Disarmed, or armed with EXTENDED_SYS_STATE saying on the ground (unknown landed state: airborne)."""
        state = self.link.state if self.link is not None else None
        if state is None or not state.armed:
            return True
        return bool(state.landed_state == "on_ground")

    if TYPE_CHECKING:
        # Implemented by the task mixins and called across them (at run time they exist on `Daemon` only);
        # declared here so that mypy checks those calls.
        def _on_imu(self, sample: Any) -> None: ...  # imu_task
        def _on_message(self, msg: Any) -> None: ...  # imu_task
        def _on_camera_lost(self, reason: str) -> None: ...  # vision_task
        def _on_camera_recovered(self) -> None: ...  # vision_task
        def _take_photo_now(self, frame: Any, nav: Any) -> None: ...  # missions
        def _mission_event(self, ev: Any) -> None: ...  # missions
        def _start_request(self, request: Any) -> None: ...  # missions
        async def _enter_guided(self) -> None: ...  # missions
        def _safety_inputs(self) -> Any: ...  # watchdog
        def _along_pipe_known(self) -> bool: ...  # along_pipe_task
        def _along_pipe_resumed_by_operator(self) -> None: ...  # along_pipe_task
        def _along_pipe_goal(self, ex: Any, out: Any, snap: Any, now_s: float) -> Any | None: ...  # along_pipe_task
