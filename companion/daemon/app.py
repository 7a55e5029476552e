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

One module per task, each a mixin of `companion.daemon.state.DaemonState` that `Daemon` combines:
`wiring` (build and open), `vision_task`, `imu_task`, `control_task` (with `along_pipe_task`, the rack-end
search leg), `missions`, `watchdog`, `health`
(health, status and the systemd notifier) and `api_controller`; this module keeps the lifecycle
(start, stop, shutdown) and `run_daemon`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import logging
import signal
import sys
from pathlib import Path
from typing import Any

from companion.clock import Clock, SystemClock
from companion.daemon.along_pipe_task import AlongPipeTask
from companion.daemon.api_controller import ApiController
from companion.daemon.control_task import ControlTask
from companion.daemon.flight import FlightFolder
from companion.daemon.health import HealthTask
from companion.daemon.imu_task import ImuTask
from companion.daemon.missions import Missions
from companion.daemon.options import DaemonOptions
from companion.daemon.page_state import PageState
from companion.daemon.state import FrameRecord
from companion.daemon.video_task import VideoTask
from companion.daemon.vision_task import VisionTask
from companion.daemon.watchdog import SafetyWatchdog
from companion.daemon.wiring import Wiring
from companion.errors import CompanionError, ConfigError, InputError, LinkError
from companion.jit import compile_in_background

__all__ = ["Daemon", "DaemonOptions", "FrameRecord", "run_daemon"]

_log = logging.getLogger("companion.daemon")


class Daemon(Wiring, VisionTask, ImuTask, ControlTask, AlongPipeTask, Missions, SafetyWatchdog, HealthTask, VideoTask,
             PageState):
    """The companion daemon (an async context manager; see the module docstring)."""

    # ================================================================ lifecycle
    async def __aenter__(self) -> Daemon:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop("context exit")

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
            # The trackers' compiled kernels (companion/jit.py): compiled or loaded in a thread, numpy meanwhile,
            # so that the first install's compilation never stalls the vision loop.
            compile_in_background()
            self._open_page_state()
            await self._open_video()  # video.enabled: overlay stream to the GCS (video_task)
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

    async def _close_resources(self) -> None:
        for unsub in self._unsubscribe:
            with contextlib.suppress(Exception):
                unsub()
        self._unsubscribe.clear()
        if self.api_server is not None:
            with contextlib.suppress(Exception):
                await self.api_server.__aexit__(None, None, None)
            self.api_server = None
        self._close_video()
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
        if self._notifier is not None:
            with contextlib.suppress(Exception):
                self._notifier.close()
            self._notifier = None
        if self.flight is not None:
            self._event("daemon-stopped", reason=self._shutdown_reason, **dataclasses.asdict(self.counters))
            self.flight.close()

    async def _open_api(self) -> None:
        from drivers.api import ApiServer, default_validator

        cfg = self.config
        server = ApiServer(cfg.api, store_dir=cfg.mission.upload_folder,
                           validate=default_validator(self.mission_limits), controller=ApiController(self),
                           status_provider=self.status, page=self._status_page())
        await server.__aenter__()
        self.api_server = server
        self._event("api-listening", url=server.url)


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
