"""The companion daemon: one asyncio loop wiring camera, vision, filter, MAVLink, missions and safety.

Tasks (DESIGN.md "Data flow"), all sleeping on the injected `Clock`:

- vision: takes the newest frame from the camera source (queue of one in the driver), runs the
  trackers in a worker thread (or inline with ``vision_inline=True`` for deterministic tests),
  fuses the result in the navigation filter on the loop thread, and sends the pose;
- IMU: the link's IMU callback feeds the filter (loop thread);
- control (20 Hz): mission executor -> servo law -> `SafetyManager.filter` -> link setpoint;
- safety watchdog (10 Hz): battery, GCS, vision, autopilot link, ceiling -> hold / land / stop poses;
- health (every ``logging.health_period_s``): summary to the log and a STATUSTEXT to the GCS;
- systemd notifier: READY once running, WATCHDOG pings, STOPPING on shutdown;
- control API: upload / start / pause / resume / abort / status.

Shutdown (SIGTERM/SIGINT or `request_shutdown`): the mission stops, the setpoint stream stops,
the vehicle is put in its hold mode when it is armed, then tasks, camera, API and link close
and the flight folder is flushed.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import dataclasses
import logging
import math
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.checks import FloatArray, check_transform
from companion.clock import Clock, SystemClock
from companion.daemon.arming import ModeDecision, ModeOwner, arm_when_ready, enter_guided
from companion.daemon.flight import FlightFolder
from companion.daemon.pipeline import FrameInputs, Measurement, VisionPipeline, rack_std_floor_from_config
from companion.errors import CameraError, CompanionError, ConfigError, InputError, LinkError, MissionError
from companion.geometry import frames

__all__ = ["Daemon", "DaemonOptions", "FrameRecord", "run_daemon"]

_log = logging.getLogger("companion.daemon")


@dataclass
class DaemonOptions:
    """How the daemon is wired (beyond the config file).

    vision_inline: run the trackers on the loop thread (deterministic tests) instead of a worker.
    flight_root / flight_name: where the flight folder goes (default ``logging.flight_root``).
    render / pose_source: the synthetic camera's renderer and truth source (None: built from the
        config's rack model, and the link's SIM_STATE).
    camera_source: a ready `CameraSource` to use instead of opening the configured one.
    initial_T_ned_body: the start pose prior for the filter and the rack tracker (default: origin).
    api / sdnotify: enable the control API server and the systemd notifier.
    The options below override the config key named in brackets when given (None: the config's value).

    record_frames: keep every processed frame in the flight folder (``frames/`` + ``timestamps.txt``)
        for `companion replay` [logging.record_frames].
    turn_first_rad: heading errors above this (rad) are turned out in place before moving (0 = off)
        [mission.turn_first_deg].
    rack_along_pipe_std_m: standard deviation (m) added to the rack pose along the pipes, which the
        pipe edges do not observe (see `VisionPipeline.fuse`); 0 trusts the tracker's covariance
        [vision.rack_along_pipe_std_m].
    frame_gap_reset_s: a longer gap between frames restarts the rack tracker [vision.frame_gap_reset_s].
    visual_ground_z_ned_m: the NED z of the ground the camera sees, when it differs from what the
        rangefinder measures to (the simulator's deck); the ground odometer's height then comes from
        the estimate. None: rangefinder (or the filter's ground) as usual [camera.sim_ground_z_ned_m].
    """

    vision_inline: bool = False
    flight_root: Path | None = None
    flight_name: str | None = None
    render: Callable[[Any], Any] | None = None
    pose_source: Callable[[], Any] | None = None
    camera_source: Any | None = None
    initial_T_ned_body: FloatArray | None = None
    api: bool = True
    sdnotify: bool = True
    control_period_s: float = 0.05
    watchdog_period_s: float = 0.1
    photo_folder: Path | None = None
    visual_ground_z_ned_m: float | None = None
    frame_gap_reset_s: float | None = None
    record_frames: bool | None = None
    rack_along_pipe_std_m: float | None = None
    turn_first_rad: float | None = None


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


class Daemon:
    """The companion daemon (an async context manager; see the module docstring)."""

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
        self.mode_owner = ModeOwner()
        self._last_health_line = ""
        self._latency_ms: collections.deque[float] = collections.deque(maxlen=100)
        self._safety_paused = False  # the running mission was paused by a safety hold
        self._mode_task: asyncio.Task[None] | None = None
        self._health_prev: tuple[int, int, int, int, float] = (0, 0, 0, 0, self.clock.now())
        self._range_stamp_s: float | None = None
        self.last_fresh_pose_s: float | None = None
        self.safety_output: Any | None = None
        self.mission_refused: dict[str, Any] | None = None
        self.mission_limits: Any | None = None
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

    # ================================================================ lifecycle
    async def __aenter__(self) -> Daemon:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop("context exit")

    @property
    def T_body_cam(self) -> FloatArray:
        return check_transform(self.config.mount.T_body_cam, "mount.T_body_cam")

    @property
    def T_ned_rack(self) -> FloatArray:
        return check_transform(self.config.rack.T_ned_rack, "rack.T_ned_rack")

    async def start(self) -> None:
        """Open everything and start the tasks; raises a `CompanionError` naming what is missing."""
        if self._started:
            raise CompanionError("daemon already started")
        self._started = True
        cfg = self.config
        root = self.options.flight_root or Path(cfg.logging.flight_root)
        try:
            photo_root = self.options.photo_folder or Path(cfg.mission.photo_folder)
            self.flight = FlightFolder.create(root, self.clock.now, self.options.flight_name, photo_root=photo_root)
        except OSError as exc:
            raise ConfigError(f"logging.flight_root: cannot create a flight folder in {root}: {exc}") from exc
        self._event("daemon-starting", flight=str(self.flight.path), camera=cfg.camera.kind,
                    mavlink=cfg.mavlink.url, vision=cfg.vision.source)
        try:
            from companion.config import mission_limits

            self.mission_limits = mission_limits(cfg)
            self._build_estimation()
            self._build_safety()
            await self._open_link()
            await self._open_camera()
            self._build_pipeline()
            if self.options.api and cfg.api.enabled:
                await self._open_api()
        except BaseException:
            await self._close_resources()
            raise
        if not self.options.vision_inline:
            self._worker = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="vision")
        for name, coro in (
            ("vision", self._vision_loop()),
            ("control", self._control_loop()),
            ("watchdog", self._watchdog_loop()),
            ("health", self._health_loop()),
            ("notify", self._notify_loop()),
        ):
            self._tasks.append(asyncio.create_task(coro, name=f"daemon-{name}"))
        self._watcher = asyncio.create_task(self._shutdown_watcher(), name="daemon-shutdown")
        # READY=1 once the autopilot is heard (the notify loop), not before: systemd shows what it waits for
        self._notify(f"waiting for the autopilot on {cfg.mavlink.url}")
        self._event("daemon-started")

    async def _shutdown_watcher(self) -> None:
        """Runs `stop` once a shutdown was requested (signal handler, API, request_shutdown)."""
        await self._shutdown.wait()
        await self.stop(self._shutdown_reason)

    async def wait_stopped(self) -> None:
        """Wait until the daemon has stopped (after a shutdown request)."""
        await self._stopped.wait()

    @property
    def stopped(self) -> bool:
        return self._stopped.is_set()

    def request_shutdown(self, reason: str = "requested") -> None:
        """Ask the daemon to stop (signal handlers call this); `wait_shutdown` returns afterwards."""
        if not self._shutdown.is_set():
            self._shutdown_reason = reason
            self._shutdown.set()

    async def wait_shutdown_requested(self) -> str:
        await self._shutdown.wait()
        return self._shutdown_reason

    def install_signal_handlers(self) -> None:
        """SIGTERM and SIGINT request a graceful shutdown (asyncio loop signal handlers)."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.request_shutdown, sig.name)

    def remove_signal_handlers(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(Exception):
                loop.remove_signal_handler(sig)

    async def stop(self, reason: str = "stop") -> None:
        """Graceful shutdown: stop motion, hold, close everything, flush the flight folder."""
        if self._stopped.is_set() or not self._started:
            return
        if self._stopping:
            await self._stopped.wait()
            return
        self._stopping = True
        self.request_shutdown(reason)
        self._event("daemon-stopping", reason=self._shutdown_reason)
        self._notify("stopping")
        await self._leave_vehicle_safe()
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._tasks.clear()
        if self._request_task is not None:
            self._request_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._request_task
        await self._close_resources()
        self._stopped.set()
        watcher = self._watcher
        if watcher is not None and watcher is not asyncio.current_task() and not watcher.done():
            watcher.cancel()

    async def _leave_vehicle_safe(self) -> None:
        if self.executor is not None and self._mission_active():
            with contextlib.suppress(CompanionError):
                self.executor.abort(self.clock.now(), "daemon shutting down")
        link = self.link
        if link is None:
            return
        link.set_velocity_command(None)
        state = link.state
        if state.armed:
            try:
                await asyncio.wait_for(self._hold(), timeout=5.0) if isinstance(self.clock, SystemClock) else \
                    await self._hold()
                self._event("shutdown-hold", mode=link.state.mode)
            except (TimeoutError, LinkError) as exc:
                self._event("shutdown-hold-failed", level=logging.ERROR, error=str(exc))
        with contextlib.suppress(Exception):
            link.statustext(f"companion: stopping ({self._shutdown_reason})", "warning")
            await self.clock.sleep(0.05)  # let the writer put the last frames on the wire

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

    async def _close_resources(self) -> None:
        for unsub in self._unsubscribe:
            with contextlib.suppress(Exception):
                unsub()
        self._unsubscribe.clear()
        if self.api_server is not None:
            with contextlib.suppress(Exception):
                await self.api_server.__aexit__(None, None, None)
            self.api_server = None
        if self.camera is not None and self.options.camera_source is None:
            with contextlib.suppress(Exception):
                await self.camera.__aexit__(None, None, None)
        self.camera = None
        if self._worker is not None:
            self._worker.shutdown(wait=True, cancel_futures=True)
            self._worker = None
        if self.link is not None:
            with contextlib.suppress(Exception):
                await self.link.close()
            self.link = None
        if self.flight is not None:
            self._event("daemon-stopped", reason=self._shutdown_reason, **dataclasses.asdict(self.counters))
            self.flight.close()

    # ================================================================ construction
    def _build_estimation(self) -> None:
        from companion.config import build_dataclass
        from companion.estimation import ImuSample, NavFilterConfig, NavigationFilter

        params = dict(self.config.filter.params)
        nav_cfg = build_dataclass(NavFilterConfig, params, "filter")
        self.nav_filter = NavigationFilter(nav_cfg, T_ned_rack=self.T_ned_rack, T_body_cam=self.T_body_cam)
        T0 = self.options.initial_T_ned_body
        if T0 is not None:
            self.nav_filter.initialize(self.clock.now(), T0)
        self._imu_sample_cls = ImuSample

    def _build_safety(self) -> None:
        from companion.control.servo import ServoController, ServoGains
        from companion.safety import SafetyConfig, SafetyManager

        lim = self.config.safety
        self.safety = SafetyManager(SafetyConfig(
            ceiling_m=lim.ceiling_m,
            min_ceiling_clearance_m=lim.ceiling_clearance_m if lim.ceiling_clearance_m > 0 else None,
            battery_low_v=lim.battery_low_v,
            battery_low_pct=lim.battery_low_pct,
            battery_critical_v=lim.battery_critical_v,
            battery_critical_pct=lim.battery_critical_pct,
            battery_low_debounce_s=max(lim.battery_debounce_s, 1e-3),
            gcs_timeout_s=lim.gcs_loss_hover_s if lim.gcs_loss_hover_s > 0 else None,
            gcs_land_timeout_s=lim.gcs_loss_land_s if lim.gcs_loss_land_s > 0 else None,
            vision_timeout_s=lim.vision_loss_hover_ms / 1000.0,
            vision_land_timeout_s=lim.vision_loss_land_s if lim.vision_loss_land_s > 0 else None,
            vision_auto_resume_s=lim.vision_resume_s if lim.vision_resume_s > 0 else None,
            gcs_auto_resume_s=lim.gcs_resume_s if lim.gcs_resume_s > 0 else None,
            geofence_min_ned_m=lim.geofence_min_ned_m,
            geofence_max_ned_m=lim.geofence_max_ned_m,
        ))
        speed = min(lim.max_speed_m_s, self.config.mission.speed_limit_m_s)
        self._servo = ServoController(ServoGains(max_speed_m_s=min(0.5, speed)))

    def _link_config(self) -> Any:
        from drivers.mavlink import LinkConfig

        cfg = self.config
        kwargs: dict[str, Any] = {
            "url": cfg.mavlink.url,
            "component_id": cfg.mavlink.component_id,
            "system_id": cfg.mavlink.system_id or None,
            "autopilot_profile": None if cfg.mavlink.profile == "auto" else cfg.mavlink.profile,
            "autopilot_timeout_s": cfg.mavlink.heartbeat_timeout_s,
            "command_timeout_s": cfg.mavlink.command_timeout_s,
            "command_retries": cfg.mavlink.command_retries,
            "request_sim_state": cfg.camera.kind == "synthetic" and self.options.pose_source is None,
            "pose_message": {True: "odometry", False: "vision"}.get(cfg.mavlink.odometry, "auto"),
            "pose_stamp_base": cfg.mavlink.pose_stamp_base,
            "forward_urls": tuple(cfg.mavlink.gcs_forward),
        }
        if cfg.ekf_origin.enabled:
            kwargs.update(origin_lat_deg=cfg.ekf_origin.lat_deg, origin_lon_deg=cfg.ekf_origin.lon_deg,
                          origin_alt_m=cfg.ekf_origin.alt_m)
        return LinkConfig(**kwargs)

    async def _open_link(self) -> None:
        from drivers.mavlink import MavLink

        assert self.flight is not None
        tlog = self.flight.tlog_path if self.config.mavlink.tlog else None
        link = MavLink(self._link_config(), clock=self.clock, tlog_path=tlog)
        await link.__aenter__()
        self.link = link
        self._unsubscribe.append(link.on_imu(self._on_imu))
        self._unsubscribe.append(link.on_message(self._on_message))

    def _truth_pose(self) -> tuple[float, FloatArray] | None:
        link = self.link
        if link is None:
            return None
        truth = link.state.sim_truth
        if truth is None:
            return None
        return float(truth.stamp_s), np.asarray(truth.T_ned_body)

    async def _open_camera(self) -> None:
        from drivers.camera import load_camera_model, open_camera

        cfg = self.config
        self.camera_model = load_camera_model(cfg.camera)
        if self.options.camera_source is not None:
            self.camera = self.options.camera_source
        else:
            render = self.options.render
            pose_source = self.options.pose_source
            if cfg.camera.kind == "synthetic":
                if render is None:
                    render = self._default_render()
                if pose_source is None:
                    pose_source = self._truth_pose
            source = open_camera(cfg.camera, self.clock, render=render, pose_source=pose_source)
            await source.__aenter__()
            self.camera = source
        cam = self.camera
        if hasattr(cam, "on_lost"):
            cam.on_lost(self._on_camera_lost)
            cam.on_recovered(self._on_camera_recovered)

    def _default_render(self) -> Callable[[Any], Any]:
        from companion.sim.render import SceneRenderer

        if self.camera_model is None:
            raise ConfigError("camera: no camera model for the synthetic renderer")
        return SceneRenderer.from_config(self.config, self.camera_model)

    def _rack_model(self) -> Any | None:
        path = self.config.rack.model
        if not path:
            return None
        from companion.vision.rack import RackModel

        return RackModel.load(path)

    def _build_pipeline(self) -> None:
        from companion.config import build_dataclass

        cfg = self.config
        rack_cfg = None
        ground_cfg = None
        if cfg.vision.source in ("rack", "auto"):
            from companion.vision.rack import RackTrackerConfig

            rack_cfg = build_dataclass(RackTrackerConfig, dict(cfg.vision.rack_tracker), "vision.rack_tracker")
        if cfg.vision.source in ("ground", "auto"):
            from companion.vision.ground import GroundOdometerConfig

            ground_cfg = build_dataclass(GroundOdometerConfig, dict(cfg.vision.ground_odometer),
                                         "vision.ground_odometer")
        assert self.camera_model is not None
        self.pipeline = VisionPipeline(
            source=cfg.vision.source,
            camera=self.camera_model,
            T_body_cam=self.T_body_cam,
            T_ned_rack=self.T_ned_rack,
            rack_model=self._rack_model(),
            rack_config=rack_cfg,
            ground_config=ground_cfg,
            initial_T_ned_body=self.options.initial_T_ned_body,
            rack_std_floor=rack_std_floor_from_config(cfg.vision),
            rack_along_pipe_std_m=self.rack_along_pipe_std_m,
        )

    async def _open_api(self) -> None:
        from drivers.api import ApiServer, default_validator

        cfg = self.config
        server = ApiServer(cfg.api, store_dir=cfg.mission.upload_folder,
                           validate=default_validator(self.mission_limits), controller=_Controller(self),
                           status_provider=self.status)
        await server.__aenter__()
        self.api_server = server
        self._event("api-listening", url=server.url)

    # ================================================================ events, notifier
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

    def _notify(self, what: str) -> None:
        if not self.options.sdnotify:
            return
        if self._notifier is None:
            try:
                from drivers.sdnotify import SdNotifier

                self._notifier = SdNotifier()
            except ImportError:
                return
        n = self._notifier
        with contextlib.suppress(Exception):
            if what == "ready":
                n.ready()
            elif what == "stopping":
                n.stopping()
            elif what == "watchdog":
                n.watchdog()
            else:
                n.status(what)

    async def _notify_loop(self) -> None:
        self._notify("watchdog")
        interval = None
        if self._notifier is not None:
            interval = getattr(self._notifier, "watchdog_interval_s", None)
        period = min(interval / 2.0 if interval else 5.0, 1.0)
        ready = False
        last_status = ""
        while True:
            await self.clock.sleep(period)
            self._notify("watchdog")
            heard = self.link is not None and self.link.state.last_autopilot_heartbeat_s is not None
            if heard and not ready:
                ready = True
                self._notify("ready")
            line = self.status_line() if heard else last_status
            if line and line != last_status:
                last_status = line
                self._notify(line)

    def status_line(self) -> str:
        """One short line of what the daemon is doing (systemd STATUS=, the GCS on a change)."""
        st = self.status()
        link, est, cam = st["link"], st["estimator"], st["camera"]
        mission = st["mission"]
        m = mission["state"] if "done" not in mission else f"{mission['state']} {mission['done']}/{mission['actions']}"
        armed = "armed" if link["armed"] else "disarmed"
        return (f"{link['autopilot'] or 'no autopilot'} {link['mode'] or '-'} {armed}"
                f"; camera {cam['state']}; vision {est['source']}{'' if est['ok'] else ' (not ok)'}"
                f"; mission {m}; safety {st['safety']['action']}")

    # ================================================================ IMU + vision
    def _on_imu(self, sample: Any) -> None:
        if self.nav_filter is None or self._imu_sample_cls is None:
            return
        self.counters.imu_samples += 1
        try:
            self.nav_filter.add_imu(self._imu_sample_cls(sample.stamp_s, sample.gyro_rad_s, sample.accel_m_s2))
        except CompanionError as exc:
            self._event("imu-rejected", level=logging.DEBUG, error=str(exc))

    def _on_camera_lost(self, reason: str) -> None:
        self.camera_ok = False
        self._event("camera-lost", level=logging.WARNING, reason=reason)

    def _on_camera_recovered(self) -> None:
        self.camera_ok = True
        self._event("camera-recovered")

    def _frame_inputs(self) -> FrameInputs:
        link = self.link
        state = link.state if link is not None else None
        roll = pitch = 0.0
        if state is not None and state.attitude_rpy_rad is not None:
            roll, pitch = float(state.attitude_rpy_rad[0]), float(state.attitude_rpy_rad[1])
        height = None
        z_cam_body = float(self.T_body_cam[2, 3])
        nf = self.nav_filter
        use_range = bool(getattr(nf.config, "use_range", True)) if nf is not None else True
        vg = self.visual_ground_z_ned_m
        if vg is None and use_range and state is not None and state.rangefinder_m is not None:
            height = float(state.rangefinder_m) * math.cos(roll) * math.cos(pitch) - z_cam_body
        elif nf is not None:
            est = nf.estimate_latest()
            if math.isfinite(float(est.stamp_s)):
                gz = float(getattr(nf.config, "ground_z_ned_m", 0.0)) if vg is None else float(vg)
                height = gz - float(est.position_ned_m[2]) - z_cam_body
        reset = None
        if self._rack_reset_pending and nf is not None:
            latest = nf.estimate_latest()
            pos_std = math.sqrt(max(float(np.max(np.diag(np.asarray(latest.pose_covariance))[:3])), 0.0))
            if math.isfinite(float(latest.stamp_s)) and pos_std < 0.3:
                reset = np.asarray(latest.T_ned_body)
                self._rack_reset_pending = False
                self._event("rack-tracker-reset", level=logging.DEBUG, position_std_m=pos_std)
        return FrameInputs(height_m=height, roll_rad=roll, pitch_rad=pitch, reset_T_ned_body=reset)

    async def _vision_loop(self) -> None:
        assert self.pipeline is not None and self.camera is not None
        loop = asyncio.get_running_loop()
        while True:
            try:
                frame = await self.camera.next_frame(timeout_s=0.25)
            except CameraError as exc:
                self._event("camera-error", level=logging.ERROR, error=str(exc))
                self.camera_ok = False
                await self.clock.sleep(0.5)
                continue
            if frame is None:
                if getattr(self.camera, "ended", False):
                    self._event("camera-ended", level=logging.WARNING)
                    return
                continue
            prev = self._latest_frame
            if prev is not None and float(frame.stamp_s) - float(prev.stamp_s) > self.frame_gap_reset_s:
                # the tracker's own motion model is stale after a gap: restart it from the IMU-propagated filter
                self._rack_reset_pending = True
            self._latest_frame = frame
            inputs = self._frame_inputs()
            try:
                if self._worker is None:
                    m = self.pipeline.measure(frame.image, frame.stamp_s, frame.seq, inputs)
                else:
                    m = await loop.run_in_executor(self._worker, self.pipeline.measure, frame.image, frame.stamp_s,
                                                   frame.seq, inputs)
            except CompanionError as exc:
                self.counters.vision_errors += 1
                self._event("vision-error", level=logging.WARNING, error=str(exc))
                continue
            self._after_measure(frame, m)

    def _after_measure(self, frame: Any, m: Measurement) -> None:
        assert self.nav_filter is not None and self.pipeline is not None
        self.counters.frames += 1
        try:
            nav = self.pipeline.fuse(m, self.nav_filter)
        except CompanionError as exc:
            self.counters.vision_errors += 1
            self._event("fusion-error", level=logging.WARNING, error=str(exc))
            return
        self.last_nav = nav
        fresh = bool(nav.ok) and abs(float(nav.stamp_s) - float(frame.stamp_s)) < 1e-6
        if m.rack is not None:
            # a rack pose the filter did not accept (gated) counts as a tracker failure too
            accepted = m.rack_ok and fresh and str(nav.source) == "rack"
            self._rack_fail_streak = 0 if accepted or (m.rack_ok and str(nav.source) != "rack") else \
                self._rack_fail_streak + 1
            if self._rack_fail_streak >= 2:
                self._rack_reset_pending = True
                self._rack_fail_streak = 0
        sent = False
        if fresh:
            self.last_fresh_pose_s = float(frame.stamp_s)
        if fresh and self._safety_view.send_poses and self.link is not None:
            from drivers.mavlink import PoseOut

            pose = PoseOut(
                stamp_s=float(nav.stamp_s),
                T_ned_body=np.asarray(nav.T_ned_body),
                pose_covariance=np.asarray(nav.pose_covariance),
                velocity_ned_m_s=np.asarray(nav.velocity_ned_m_s),
                velocity_covariance=np.asarray(nav.velocity_covariance),
                reset_counter=int(nav.reset_counter),
            )
            sent = bool(self.link.send_pose(pose))
        if sent:
            self.counters.poses_sent += 1
            self.last_pose_sent_s = float(frame.stamp_s)
            self._latency_ms.append((self.clock.now() - float(frame.stamp_s)) * 1e3)
            if self.flight is not None:
                self.flight.tum.write(float(nav.stamp_s), np.asarray(nav.T_ned_body))
        else:
            self.counters.poses_withheld += 1
        if self._pending_photo is not None:
            self._take_photo_now(frame, nav)
        if self.record_frames and self.flight is not None:
            with contextlib.suppress(OSError):
                self.flight.save_frame(frame.image, int(frame.seq), float(frame.stamp_s))
        record = FrameRecord(
            seq=int(frame.seq), capture_s=float(frame.stamp_s), source_stamp_s=frame.source_stamp_s,
            process_s=m.process_s, nav=nav, sent=sent, sent_s=self.clock.now(), sent_perf_s=time.perf_counter(),
            measurement=m,
        )
        for obs in list(self.frame_observers):
            obs(record)

    # ================================================================ missions
    def _mission_active(self) -> bool:
        from companion.mission import State

        return self.executor is not None and self.executor.state in (State.RUNNING, State.PAUSED)

    async def start_mission(self, mission: Any, mission_id: str = "mission") -> None:
        """Start a parsed `Mission` (refused while another one runs or when safety forbids it)."""
        from companion.mission import MissionExecutor

        if self._mission_active():
            raise MissionError(f"mission '{self.mission_id}' is still running; abort it first")
        reason = None
        if not self._safety_view.allow_mission:
            reason = f"safety forbids starting a mission ({self._safety_view.last_action})"
        elif self.link is None or self.link.state.last_autopilot_heartbeat_s is None:
            reason = "no autopilot on the link"
        else:
            reason = self.takeoff_refusal()
        if reason is not None:
            self._refuse_mission(mission_id, reason)
            raise MissionError(f"mission '{mission_id}' refused: {reason}")
        self.mission_refused = None
        self.executor = MissionExecutor(mission, T_ned_rack=self.T_ned_rack)
        self.mission_id = mission_id
        self._servo.reset() if self._servo is not None else None
        self.executor.start(self.clock.now())
        self.mode_owner.claim()  # motion starts (even while airborne): the guided mode is ours to set
        self._event("mission-start", mission=mission.name, id=mission_id, actions=len(mission.actions))

    def _active_executor(self, mission_id: str | None) -> Any:
        ex = self.executor
        if ex is None:
            raise MissionError("no mission")
        if mission_id is not None and mission_id != self.mission_id:
            raise MissionError(f"mission '{mission_id}' is not the active one ('{self.mission_id}')")
        return ex

    def pause_mission(self, mission_id: str | None = None) -> None:
        """Operator pause: the vehicle holds (autopilot hold mode); `resume_mission` continues."""
        self._active_executor(mission_id).pause(self.clock.now())

    def resume_mission(self, mission_id: str | None = None) -> None:
        """Operator resume. After an operator pause the mission continues and the daemon switches the
        autopilot back to its guided mode; during a safety hold it ends the hold (refused while the cause
        persists) and the watchdog resumes the mission."""
        ex = self._active_executor(mission_id)
        if self.safety is not None and self._safety_view.last_action not in ("none", ""):
            if not self.safety.operator_resume(self.clock.now()):
                raise MissionError(f"resume refused: safety hold ({self._safety_view.last_action}) still needed")
            return
        ex.resume(self.clock.now())
        self.mode_owner.claim()  # motion resumes: the guided mode is ours to set again

    def abort_mission(self, mission_id: str | None = None) -> None:
        """Operator abort: the mission ends, the vehicle holds where it is."""
        self._active_executor(mission_id).abort(self.clock.now(), "operator abort")

    def takeoff_refusal(self) -> str | None:
        """Why arming / taking off must not happen now, or None when it may.

        The safety manager's ``allow_takeoff`` (autopilot link, battery low/critical, GCS link) from the
        watchdog's last step, and a vision pose sent to the autopilot within ``safety.vision_loss_hover_ms``.
        """
        out = self.safety_output
        if out is None:
            return "safety watchdog has not evaluated the vehicle yet"
        if not bool(out.allow_takeoff):
            reasons = sorted(str(getattr(f, "value", f)) for f in out.faults)
            state = self.link.state if self.link is not None else None
            lim = self.config.safety
            if state is not None and not any(r.startswith("battery") for r in reasons):
                v, pct = state.battery_voltage_v, state.battery_remaining_pct
                if (v is not None and v < lim.battery_low_v) or (pct is not None and pct < lim.battery_low_pct):
                    # below the threshold but not yet debounced into a fault: still no take-off
                    reasons.append(f"battery low ({'?' if v is None else f'{v:.2f}'} V, "
                                   f"{'?' if pct is None else f'{pct:.0f}'} %)")
            return f"safety forbids take-off ({', '.join(reasons) or out.message})"
        max_age_s = float(self.config.safety.vision_loss_hover_ms) / 1000.0
        sent = self.last_pose_sent_s
        if sent is None or self.clock.now() - sent > max_age_s:
            age = "never" if sent is None else f"{self.clock.now() - sent:.2f} s ago"
            return f"no fresh vision pose (last sent {age}, limit {max_age_s:g} s)"
        return None

    def _refuse_mission(self, mission_id: str | None, reason: str) -> None:
        """Record, log and tell the GCS why a mission (or its take-off) was refused."""
        self.mission_refused = {"id": mission_id, "time_s": self.clock.now(), "reason": reason}
        self._event("mission-refused", level=logging.WARNING, id=mission_id, reason=reason)
        if self.link is not None:
            with contextlib.suppress(Exception):
                self.link.statustext(f"companion: mission refused: {reason}"[:200], "warning")

    def _nav_snapshot(self) -> Any:
        from companion.mission import NavSnapshot

        nav = self.last_nav
        state = self.link.state if self.link is not None else None
        armed = bool(state.armed) if state is not None else False
        landed = self._landed()
        now = self.clock.now()
        fresh = nav is not None and bool(nav.ok) and self.last_pose_sent_s is not None and \
            now - self.last_pose_sent_s <= 0.5
        T = np.asarray(nav.T_ned_body) if nav is not None else np.eye(4)
        return NavSnapshot(stamp_s=now, T_ned_body=T, ok=bool(fresh), armed=armed, landed=landed,
                           home_T_ned_body=self._home_T_ned_body)

    async def _control_loop(self) -> None:
        from companion.control.types import VelocityCommand

        period = self.options.control_period_s
        while True:
            await self.clock.sleep(period)
            self.counters.control_steps += 1
            if self.link is None:
                continue
            ex = self.executor
            if ex is None:
                continue
            now = self.clock.now()
            snap = self._nav_snapshot()
            if self._home_T_ned_body is None and snap.ok:
                self._home_T_ned_body = np.asarray(snap.T_ned_body).copy()
                snap = dataclasses.replace(snap, home_T_ned_body=self._home_T_ned_body)
            out = ex.step(now, snap)
            for ev in out.events:
                self._mission_event(ev)
            if out.request is not None:
                self._start_request(out.request)
            if not self._mission_active():
                if self._last_command is not None:
                    self.link.set_velocity_command(None)
                    self._last_command = None
                continue
            cmd: Any = None
            if out.goal is not None and snap.ok and self._safety_view.allow_mission:
                assert self._servo is not None
                speed = min(out.goal.max_speed_m_s, self.config.safety.max_speed_m_s)
                goal_T = self._turn_first(out.goal, np.asarray(snap.T_ned_body))
                cmd = self._servo.update(snap.T_ned_body, goal_T, now, max_speed_m_s=speed)
            elif out.goal is not None and self._safety_view.allow_mission and out.pending_request is None:
                cmd = VelocityCommand.zero()
            if cmd is not None and self.safety is not None:
                cmd = self.safety.filter(cmd, self._safety_inputs(), now)
            self._own_mode(ex, now, moving=out.goal is not None and self._safety_view.allow_mission,
                           request_pending=out.pending_request is not None)
            if cmd is not None and out.pending_request is None:
                self.link.set_velocity_command(cmd)
                self._last_command = cmd
            elif self._last_command is not None and out.pending_request is None:
                self.link.set_velocity_command(None)
                self._last_command = None
            if self._servo is not None:
                # rate limiting continues from what the autopilot was actually given (post-filter), so a
                # clamp that releases does not make the next command jump; nothing sent = at rest
                sent = cmd if cmd is not None and out.pending_request is None else None
                self._servo.record_sent(sent, now)

    def _own_mode(self, ex: Any, now: float, *, moving: bool, request_pending: bool) -> None:
        """Apply the mode-ownership rule (`companion.daemon.arming.ModeOwner`) for this control step."""
        from companion.mission import State

        link = self.link
        profile = None if link is None else link.profile
        if link is None or profile is None or ex.state is not State.RUNNING:
            return
        busy = request_pending or (self._request_task is not None and not self._request_task.done())
        decision = self.mode_owner.decide(moving=moving, armed=bool(link.state.armed), airborne=not self._landed(),
                                          mode=link.state.mode, guided_mode=profile.guided_mode,
                                          request_pending=busy,
                                          mode_stamp_s=link.state.last_autopilot_heartbeat_s)
        if decision is ModeDecision.ENTER_GUIDED:
            self._mode_task = asyncio.create_task(self._claim_guided(profile.guided_mode), name="enter-guided")
        elif decision is ModeDecision.PAUSE:
            reason = f"mode changed to {link.state.mode} outside the companion: mission paused (resume to continue)"
            with contextlib.suppress(MissionError):
                ex.pause(now)
            self._event("mission-paused", level=logging.WARNING, reason=reason)
            self._gcs_text(reason, "warning")

    async def _claim_guided(self, guided_mode: str) -> None:
        failure = await enter_guided(self.mode_owner, self._enter_guided, self.clock.now)
        if failure is None:
            self._event("mode", mode=guided_mode, reason="motion starts or resumes")
            return
        from companion.mission import State

        reason = f"cannot switch the autopilot to {guided_mode}: {failure}; mission paused"
        self._event("mission-paused", level=logging.WARNING, reason=reason)
        self._gcs_text(reason, "warning")
        ex = self.executor
        if ex is not None and ex.state is State.RUNNING:
            with contextlib.suppress(MissionError):
                ex.pause(self.clock.now())

    def _turn_first(self, goal: Any, T_ned_body: FloatArray) -> FloatArray:
        """The pose to servo to now: for a large heading change, first turn in place, then go.

        The SE(3)-log law couples rotation and translation: a 180 deg turn combined with a move
        follows a screw arc that can swing the vehicle a metre off the straight line (off the rack,
        where the tracker loses it). Above `turn_first_rad` of heading error the goal becomes the
        goal's heading at the position where the turn started; below it, the goal itself.
        """
        T_goal = np.asarray(goal.T_ned_body_goal, dtype=np.float64)
        yaw_err = float(frames.wrap_angle(frames.yaw_from_rotation(T_goal[:3, :3])
                                          - frames.yaw_from_rotation(T_ned_body[:3, :3])))
        key = (goal.action_index, goal.action_id)
        threshold = self.turn_first_rad
        if threshold <= 0.0:
            return T_goal
        if self._turn_key != key:
            self._turn_key = key
            self._turn_pivot = T_ned_body[:3, 3].copy() if abs(yaw_err) > threshold else None
        if self._turn_pivot is not None:
            if abs(yaw_err) > 0.5 * threshold:
                T = T_goal.copy()
                T[:3, 3] = self._turn_pivot
                return T
            self._turn_pivot = None
        return T_goal

    def _mission_event(self, ev: Any) -> None:
        self._event("mission", kind=str(ev.kind), message=ev.message, severity=ev.severity,
                    action=ev.action_id)
        if self.link is not None and str(ev.kind) != "request":
            with contextlib.suppress(Exception):
                self.link.statustext(ev.message[:200], ev.severity if ev.severity in ("info", "warning", "error")
                                     else "info")

    def _start_request(self, request: Any) -> None:
        if self._request_task is not None and not self._request_task.done():
            self._request_task.cancel()
        self._request_task = asyncio.create_task(self._do_request(request), name=f"request-{request.kind}")

    async def _do_request(self, request: Any) -> None:
        from companion.mission import RequestKind

        link = self.link
        ex = self.executor
        if link is None or ex is None:
            return
        ok = True
        message = ""
        try:
            if request.kind in (RequestKind.ARM, RequestKind.TAKEOFF):
                refusal = self.takeoff_refusal()
                if refusal is not None:
                    self._refuse_mission(self.mission_id, f"{request.kind}: {refusal}")
                    if request.kind is RequestKind.TAKEOFF and link.state.armed and self._landed():
                        with contextlib.suppress(CompanionError):
                            await link.disarm()
                    raise MissionError(f"{request.kind} refused: {refusal}")
            if request.kind is RequestKind.ARM:
                profile = link.profile
                if profile is None:
                    raise LinkError("autopilot type unknown: cannot arm")
                if profile.name == "ardupilot":  # arm in GUIDED and take off inside it
                    await link.set_mode(profile.guided_mode)
                waited = await arm_when_ready(link, self.clock.sleep, self.clock.now,
                                              timeout_s=float(self.config.mission.arm_ready_timeout_s),
                                              say=lambda text: self._gcs_text(text, "info"))
                self._event("armed", waited_s=round(waited, 2))
            elif request.kind is RequestKind.TAKEOFF:
                await link.takeoff(float(request.height_m))
                await self._wait_height(float(request.height_m))
                await self._enter_guided()
                self.mode_owner.accepted(self.clock.now())
            elif request.kind is RequestKind.LAND:
                await link.land()
            elif request.kind is RequestKind.HOLD:
                # the daemon only takes the vehicle out of the mode it drives (guided): a pilot's LOITER or an
                # autopilot failsafe's LAND is left alone
                ours = link.profile is not None and link.state.mode in (link.profile.guided_mode,
                                                                         link.profile.takeoff_mode)
                if link.state.armed and ours and self._safety_view.last_action in ("none", ""):
                    with contextlib.suppress(CompanionError):
                        await self._hold()
                return
            elif request.kind is RequestKind.PHOTO:
                fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
                self._pending_photo = (request.id, fut)
                await fut
                return
        except CompanionError as exc:
            ok = False
            message = str(exc)
        except asyncio.CancelledError:
            raise
        ex.notify(request.id, ok, self.clock.now(), message)

    async def _enter_guided(self) -> None:
        """Switch to the profile's velocity-setpoint mode; PX4 needs the setpoint stream before OFFBOARD."""
        from companion.control.types import VelocityCommand

        link = self.link
        assert link is not None
        profile = link.profile
        if profile is None:
            raise LinkError("autopilot type unknown")
        if link.state.mode == profile.guided_mode:
            return
        link.set_velocity_command(VelocityCommand.zero())
        await self.clock.sleep(0.5)
        await link.set_mode(profile.guided_mode)

    async def _wait_height(self, height_m: float, tolerance_m: float = 0.25, timeout_s: float = 30.0) -> None:
        """Wait until the autopilot reports a height within `tolerance_m` of `height_m` above home."""
        link = self.link
        assert link is not None
        home_z = 0.0 if self._home_T_ned_body is None else float(self._home_T_ned_body[2, 3])
        deadline = self.clock.now() + timeout_s
        while self.clock.now() < deadline:
            nav = self.last_nav
            z = None
            if nav is not None and bool(nav.ok):
                z = float(nav.position_ned_m[2])
            elif link.state.position_ned_m is not None:
                z = float(link.state.position_ned_m[2])
            if z is not None and home_z - z >= height_m - tolerance_m:
                return
            await self.clock.sleep(0.1)
        raise LinkError(f"take-off did not reach {height_m:g} m within {timeout_s:g} s")

    def _take_photo_now(self, frame: Any, nav: Any) -> None:
        assert self._pending_photo is not None
        request_id, fut = self._pending_photo
        self._pending_photo = None
        ex = self.executor
        try:
            assert self.flight is not None
            self._photo_index += 1
            sidecar = {
                "time_s": float(frame.stamp_s),
                "wall_time": time.time(),
                "seq": int(frame.seq),
                "pose": {
                    "T_ned_body": np.asarray(nav.T_ned_body),
                    "covariance_xyz_rpy": np.asarray(nav.pose_covariance),
                    "ok": bool(nav.ok),
                    "source": str(nav.source),
                },
                "mission": None if ex is None else ex.mission.name,
                "mission_id": self.mission_id,
                "action_id": None if ex is None or ex.pending_request is None else ex.pending_request.action_id,
                "camera_calibration": self.config.camera.calibration or None,
            }
            path = self.flight.save_photo(frame.image, sidecar)
            if self.link is not None:
                R_ned_cam = np.asarray(nav.T_ned_body)[:3, :3] @ self.T_body_cam[:3, :3]
                self.link.camera_image_captured(self._photo_index, file_url=path.name, R_ned_cam=R_ned_cam)
            self._event("photo", file=path.name)
            if ex is not None:
                ex.notify(request_id, True, self.clock.now(), path.name)
        except (OSError, CompanionError) as exc:
            if ex is not None:
                ex.notify(request_id, False, self.clock.now(), str(exc))
        if not fut.done():
            fut.set_result(None)

    # ================================================================ safety
    def _on_message(self, msg: Any) -> None:
        """Feeds new downward rangefinder readings to the filter; the link has decoded them into its state."""
        if msg.get_type() != "DISTANCE_SENSOR" or self.link is None or self.nav_filter is None:
            return
        state = self.link.state
        stamp = state.rangefinder_stamp_s
        if state.rangefinder_m is None or stamp is None or stamp == self._range_stamp_s:
            return  # another orientation, out of range, or already fed
        self._range_stamp_s = stamp
        try:
            self.nav_filter.add_range(float(state.rangefinder_m), float(stamp))
        except CompanionError as exc:
            self._event("range-rejected", level=logging.DEBUG, error=str(exc))

    def _ceiling_clearance(self) -> float | None:
        """Upward rangefinder distance (m) from the link's state; None when unknown or older than 1 s."""
        state = self.link.state if self.link is not None else None
        if state is None or state.rangefinder_up_m is None or state.rangefinder_up_stamp_s is None:
            return None
        if self.clock.now() - float(state.rangefinder_up_stamp_s) > 1.0:
            return None
        return float(state.rangefinder_up_m)

    def _landed(self) -> bool:
        """Disarmed, or armed with EXTENDED_SYS_STATE saying on the ground (unknown landed state: airborne)."""
        state = self.link.state if self.link is not None else None
        if state is None or not state.armed:
            return True
        return bool(state.landed_state == "on_ground")

    def _safety_inputs(self) -> Any:
        from companion.safety import SafetyInputs

        state = self.link.state if self.link is not None else None
        nav = self.last_nav
        pos: tuple[float, float, float] | None = None
        altitude = None
        if nav is not None and bool(nav.ok):
            p = np.asarray(nav.position_ned_m, dtype=np.float64)
            pos = (float(p[0]), float(p[1]), float(p[2]))
        elif state is not None and state.position_ned_m is not None:
            p = np.asarray(state.position_ned_m, dtype=np.float64)
            pos = (float(p[0]), float(p[1]), float(p[2]))
        if pos is not None:
            home_z = 0.0 if self._home_T_ned_body is None else float(self._home_T_ned_body[2, 3])
            altitude = home_z - pos[2]
        return SafetyInputs(
            battery_v=None if state is None else state.battery_voltage_v,
            battery_pct=None if state is None else state.battery_remaining_pct,
            altitude_m=altitude,
            ceiling_clearance_m=self._ceiling_clearance(),
            last_gcs_heartbeat_s=None if state is None else state.last_gcs_heartbeat_s,
            last_pose_s=self.last_fresh_pose_s,
            last_autopilot_heartbeat_s=None if state is None else state.last_autopilot_heartbeat_s,
            position_ned_m=pos,
            armed=bool(state.armed) if state is not None else False,
            landed=self._landed(),
        )

    async def _watchdog_loop(self) -> None:
        from companion.safety import SafetyAction

        period = self.options.watchdog_period_s
        while True:
            await self.clock.sleep(period)
            self.counters.watchdog_steps += 1
            if self.safety is None:
                continue
            now = self.clock.now()
            out = self.safety.step(self._safety_inputs(), now)
            self.safety_output = out
            for ev in out.events:
                record = {"time_s": ev.time_s, "kind": ev.kind, "action": str(ev.action), "message": ev.message,
                          "severity": ev.severity}
                self._safety_view.events.append(record)
                self._event("safety", level=logging.WARNING, **record)
                if self.link is not None:
                    sev = ev.severity if ev.severity in ("info", "warning", "error", "critical") else "warning"
                    with contextlib.suppress(Exception):
                        self.link.statustext(f"SAFETY {ev.message}"[:200], sev)
            self._safety_view.send_poses = bool(out.send_poses)
            self._safety_view.allow_mission = bool(out.allow_commands)
            changed = out.action != self._safety_view.last_action
            if self._safety_view.last_action == "retry" and now < self._safety_retry_s:
                continue
            self._safety_view.last_action = str(out.action)
            if changed and out.action is not SafetyAction.NONE:
                await self._apply_safety_action(out.action)
            elif changed and self._safety_paused:
                self._resume_after_safety()

    def _resume_after_safety(self) -> None:
        """The fault that paused the mission has cleared: resume it (the guided mode is claimed again)."""
        from companion.mission import State

        self._safety_paused = False
        ex = self.executor
        if ex is None or ex.state is not State.PAUSED:
            return
        with contextlib.suppress(MissionError):
            ex.resume(self.clock.now())
            self.mode_owner.claim()
            self._event("mission-resumed", reason="safety hold cleared")
            self._gcs_text("safety hold cleared: mission resumed", "info")

    async def _apply_safety_action(self, action: Any) -> None:
        from companion.safety import SafetyAction

        link = self.link
        if link is None:
            return
        if self._mission_active():
            from companion.mission import State

            assert self.executor is not None
            # a hold (vision, GCS or autopilot link briefly lost) pauses the mission so that it can resume
            # when the fault clears; a landing ends it
            pause = action in (SafetyAction.HOVER, SafetyAction.STOP_COMMANDS) and \
                (self.executor.state is State.RUNNING or self._safety_paused)
            with contextlib.suppress(CompanionError):
                if pause:
                    if self.executor.state is State.RUNNING:
                        self.executor.pause(self.clock.now())
                    self._safety_paused = True
                else:
                    self.executor.abort(self.clock.now(), f"safety: {action}")
                    self._safety_paused = False
            if self._request_task is not None and not self._request_task.done():
                self._request_task.cancel()
        link.set_velocity_command(None)
        self._last_command = None
        self._event("safety-action", level=logging.WARNING, action=str(action))
        if action is SafetyAction.STOP_COMMANDS or not link.state.armed:
            return
        try:
            if action is SafetyAction.HOVER:
                await self._hold()
            elif action in (SafetyAction.LAND, SafetyAction.LAND_NOW):
                await link.land()
        except CompanionError as exc:
            self._event("safety-action-failed", level=logging.ERROR, action=str(action), error=str(exc))
            self._safety_view.last_action = "retry"  # try again in a second
            self._safety_retry_s = self.clock.now() + 1.0

    # ================================================================ health, status
    async def _health_loop(self) -> None:
        period = float(self.config.logging.health_period_s)
        while True:
            await self.clock.sleep(period)
            self.counters.health_reports += 1
            status = self.status()
            self._event("health", **status)
            if self.link is not None:
                with contextlib.suppress(Exception):
                    # the GCS gets the summary when it changes (a line every period floods QGC's messages);
                    # the tracker health goes as NAMED_VALUE_FLOAT every period
                    line = self._health_line(status)
                    if line != self._last_health_line:
                        self._last_health_line = line
                        self.link.statustext(line[:200], "info")
                    self._tracker_health()
            if self.flight is not None:
                self.flight.flush()

    def _tracker_health(self) -> None:
        """NAMED_VALUE_FLOAT tracker health for the GCS: rack/ground ok fractions and pose rate since last time."""
        assert self.link is not None
        p = self.pipeline
        if p is None:
            return
        frames_now, rack_now, ground_now = p.frames, p.rack_ok_frames, p.ground_ok_frames
        f0, r0, g0, s0, t0 = self._health_prev
        now = self.clock.now()
        df = max(frames_now - f0, 1)
        self.link.named_value_float("rack_ok", (rack_now - r0) / df)
        self.link.named_value_float("ground_ok", (ground_now - g0) / df)
        self.link.named_value_float("pose_hz", (self.counters.poses_sent - s0) / max(now - t0, 1e-3))
        self._health_prev = (frames_now, rack_now, ground_now, self.counters.poses_sent, now)

    @staticmethod
    def _health_line(status: dict[str, Any]) -> str:
        est = status["estimator"]
        return (f"companion: cam {status['camera']['state']} vis {est['source']} ok={est['ok']} "
                f"mission {status['mission']['state']} safety {status['safety']['action']}")

    def status(self) -> dict[str, Any]:
        """A JSON-serializable status: daemon, link, camera, estimator, mission, safety."""
        now = self.clock.now()
        link = self.link
        state = link.state if link is not None else None
        nav = self.last_nav
        cam = self.camera
        stats = getattr(cam, "stats", None)
        mission: dict[str, Any] = {"state": "none"}
        if self.executor is not None:
            ex = self.executor
            mission = {
                "id": self.mission_id,
                "name": ex.mission.name,
                "state": str(ex.state),
                "actions": len(ex.mission.actions),
                "done": len(ex.results),
            }
        if self.mission_refused is not None:
            if self.executor is None:
                mission = {"state": "refused", "id": self.mission_refused["id"]}
            mission["refused"] = self.mission_refused["reason"]
        pos = None if nav is None else [round(float(v), 3) for v in nav.position_ned_m]
        return {
            "daemon": {
                "uptime_s": round(now - self._start_s, 1),
                "flight_folder": str(self.flight.path) if self.flight is not None else None,
                **dataclasses.asdict(self.counters),
            },
            "link": {
                "url": self.config.mavlink.url,
                "health": _health_name(link),
                "last_heartbeat_age_s": None if state is None or state.last_autopilot_heartbeat_s is None
                else round(now - state.last_autopilot_heartbeat_s, 1),
                "autopilot": None if state is None else state.autopilot,
                "mode": None if state is None else state.mode,
                "armed": None if state is None else bool(state.armed),
                "battery_v": None if state is None else state.battery_voltage_v,
                "battery_pct": None if state is None else state.battery_remaining_pct,
            },
            "camera": {
                "kind": self.config.camera.kind,
                "state": str(getattr(cam, "state", "closed")).split(".")[-1].lower() if cam is not None else "closed",
                "ok": self.camera_ok,
                "captured": None if stats is None else stats.captured,
                "dropped_stale": None if stats is None else stats.dropped_stale,
            },
            "estimator": {
                "ok": None if nav is None else bool(nav.ok),
                "source": "none" if nav is None else str(nav.source),
                "position_ned_m": pos,
                "reset_counter": None if nav is None else int(nav.reset_counter),
                "last_pose_age_s": None if self.last_pose_sent_s is None else round(now - self.last_pose_sent_s, 3),
                # capture -> pose on the socket, median of the last 100 poses: what VISO_DELAY_MS is set from
                "capture_to_send_ms_p50": (None if not self._latency_ms
                                           else round(float(np.median(self._latency_ms)), 1)),
            },
            "mission": mission,
            "safety": {
                "action": self._safety_view.last_action,
                "send_poses": self._safety_view.send_poses,
                "events": len(self._safety_view.events),
            },
        }


def _health_name(link: Any) -> str:
    """The link's state for people: "autopilot-ok", "no-autopilot-heard", "autopilot-lost", "disconnected"."""
    if link is None:
        return "closed"
    health = getattr(link, "health", None)
    value = str(getattr(health, "value", health))
    return {"connected": "no-autopilot-heard"}.get(value, value).replace("_", "-")


class _Controller:
    """The control API's MissionController: start/pause/resume/abort on the daemon."""

    def __init__(self, daemon: Daemon) -> None:
        self._d = daemon

    async def start(self, mission_id: str) -> None:
        from companion.mission import load_mission

        server = self._d.api_server
        if server is None:
            raise MissionError("control API not running")
        path = server.store.path(mission_id)
        mission = load_mission(path, limits=self._d.mission_limits)
        await self._d.start_mission(mission, mission_id)

    async def pause(self, mission_id: str | None) -> None:
        self._d.pause_mission(mission_id)

    async def resume(self, mission_id: str | None) -> None:
        self._d.resume_mission(mission_id)

    async def abort(self, mission_id: str | None) -> None:
        self._d.abort_mission(mission_id)


async def run_daemon(config: Any, config_path: Path | None = None, clock: Clock | None = None,
                     record_frames: bool | None = None) -> int:
    """`companion run`: start the daemon, wait for SIGTERM/SIGINT, stop gracefully; returns the exit code.

    record_frames: None keeps ``logging.record_frames`` of the config; True/False overrides it."""
    daemon = Daemon(config, clock=clock or SystemClock(), options=DaemonOptions(record_frames=record_frames))
    try:
        await daemon.start()
    except CompanionError as exc:
        print(f"companion: error: cannot start: {' '.join(str(exc).split())}", file=sys.stderr, flush=True)
        return 2 if isinstance(exc, ConfigError | InputError) else 1
    daemon.install_signal_handlers()
    if config_path is not None and daemon.flight is not None:
        with contextlib.suppress(OSError):
            (daemon.flight.path / "config.toml").write_bytes(Path(config_path).read_bytes())
    try:
        reason = await daemon.wait_shutdown_requested()
        await daemon.wait_stopped()
    finally:
        daemon.remove_signal_handlers()
        await daemon.stop("exit")
    _log.info("stopped: %s", reason)
    return 0
