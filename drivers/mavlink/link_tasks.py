"""`TasksMixin`: the bodies of `MavLink`'s background tasks: connection (re-opened with backoff), the
autopilot-silence watchdog, the single writer, and the periodic senders (heartbeat, TIMESYNC requests,
EKF origin, velocity setpoints)."""

from __future__ import annotations

from companion.errors import LinkError
from drivers.mavlink.link_core import log
from drivers.mavlink.link_reader import ReaderMixin
from drivers.mavlink.sendqueue import Priority

__all__ = ["TasksMixin"]


class TasksMixin(ReaderMixin):
    """Task bodies of `MavLink`; on `ReaderMixin` because an opened transport feeds the reader."""

    # ---------------------------------------------------------------- connection
    async def _open_transport(self) -> None:
        self._lost.clear()
        await self._transport.open(self._receive, self._on_lost)

    def _on_lost(self, exc: BaseException | None) -> None:
        if exc is not None:
            log.warning("mavlink transport %s lost: %s", self.config.url, exc)
        self._lost.set()

    async def _connection_loop(self) -> None:
        backoff = self.config.reconnect_initial_s
        while True:
            if not self._transport.is_open:
                try:
                    await self._open_transport()
                    backoff = self.config.reconnect_initial_s
                except (LinkError, OSError) as exc:
                    self._counts["connect_failures"] += 1
                    log.debug("mavlink connect %s failed: %s", self.config.url, exc)
                    await self._clock.sleep(backoff)
                    backoff = min(2.0 * backoff, self.config.reconnect_max_s)
                    continue
            await self._lost.wait()
            self._lost.clear()
            await self._transport.close()
            self._counts["reconnects"] += 1
            self._last_reconnect_s = self._clock.now()
            self._queue.clear(Priority.POSE)
            self._queue.clear(Priority.SETPOINT)
            await self._clock.sleep(backoff)
            backoff = min(2.0 * backoff, self.config.reconnect_max_s)

    async def _watchdog_loop(self) -> None:
        period = min(0.25, self.config.autopilot_timeout_s / 4.0)
        while True:
            await self._clock.sleep(period)
            last = self._last_autopilot_rx_s  # any message counts: a lost heartbeat or two is not silence
            if last is None:
                continue
            now = self._clock.now()
            if self._autopilot_present and now - last > self.config.autopilot_timeout_s:
                self._autopilot_present = False
                self._counts["autopilot_lost"] += 1
                log.warning("autopilot silent for %.2f s on %s: reconnecting", now - last, self.config.url)
                self._silent_reconnects = 0
                self._lost.set()
            elif not self._autopilot_present:
                factor = 2.0 ** min(self._silent_reconnects + 1, 3)
                if now - max(last, self._last_reconnect_s) > factor * self.config.autopilot_timeout_s:
                    self._silent_reconnects += 1
                    self._lost.set()

    # ---------------------------------------------------------------- writer
    async def _writer_loop(self) -> None:
        queue = self._queue
        while True:
            await queue.wait()
            while (item := queue.pop()) is not None:
                if item.expires_s is not None and self._clock.now() > item.expires_s:
                    self._counts["frames_expired"] += 1
                    continue
                try:
                    self._write_now(item.data, item.to_gcs)
                except Exception:  # the only writer: one bad write must not silence the link for good
                    self._counts["write_failures"] += 1
                    log.exception("mavlink writer: writing a frame failed")

    def _write_now(self, data: bytes, to_gcs: bool) -> None:
        if self._transport.write(data):
            self._counts["frames_out"] += 1
        else:
            self._counts["write_failures"] += 1
        if to_gcs:
            for t, _ in self._forwards:
                t.write(data)
        if self._tlog is not None:
            self._tlog.write(data)

    # ---------------------------------------------------------------- periodic senders
    async def _heartbeat_loop(self) -> None:
        while True:
            self._enqueue(self._encoder.heartbeat(), Priority.CONTROL, to_gcs=True)
            await self._clock.sleep(self.config.heartbeat_period_s)

    async def _timesync_loop(self) -> None:
        if self.config.timesync_period_s <= 0.0:
            return
        while True:
            if self._autopilot_present:
                ts1 = self._timesync.request_ns(self._clock.now())
                self._enqueue(self._encoder.timesync(0, ts1), Priority.CONTROL)
            # Fast requests until converged, so poses can start in the autopilot's time base quickly.
            fast = not self._timesync.converged
            await self._clock.sleep(min(0.1, self.config.timesync_period_s) if fast else self.config.timesync_period_s)

    async def _origin_loop(self) -> None:
        origin = self.config.origin
        if origin is None:
            return
        while True:
            address = self._tracker.autopilot_address
            if self._autopilot_present and address is not None and not self.state.ekf_origin_set:
                self._enqueue(self._encoder.set_gps_global_origin(address[0], *origin), Priority.CONTROL)
                self._counts["origin_requests_sent"] += 1
            await self._clock.sleep(self.config.origin_period_s)

    async def _setpoint_loop(self) -> None:
        period = 1.0 / self.config.setpoint_rate_hz
        while True:
            cmd = self._velocity_cmd
            target = self._tracker.autopilot_address
            if cmd is None or target is None or not self._autopilot_present:
                # Nothing to fly, or the autopilot went silent: never stream blind (resumes on its heartbeat).
                self._setpoint_wake.clear()
                await self._setpoint_wake.wait()
                continue
            frame = self._encoder.velocity_setpoint(
                target,
                self._boot_ms(),
                cmd.vx_m_s,
                cmd.vy_m_s,
                cmd.vz_m_s,
                cmd.yaw_rate_rad_s,
                body_frame=getattr(cmd, "frame", "ned") == "body",
            )
            self._enqueue(frame, Priority.SETPOINT, self._clock.now() + period)
            self._counts["setpoints_sent"] += 1
            await self._clock.sleep(period)
