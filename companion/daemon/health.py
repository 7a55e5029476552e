"""Health and status: the periodic health report (log, GCS), `status()`, `status_line()` and the
systemd notifier (READY once the autopilot is heard, WATCHDOG pings, STATUS lines, STOPPING)."""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any

import numpy as np

from companion.daemon.state import DaemonState

__all__ = ["HealthTask"]


class HealthTask(DaemonState):
    """The health loop, the notifier loop and the status views."""

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
            search = self._along_pipe_search
            if search is not None:  # the rack-end search leg (along_pipe_task): its state and distance flown
                mission["along_pipe_search"] = {"state": str(search.state), "flown_m": round(float(search.flown_m), 3)}
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
                # the position along the pipes is still the configured start's (acquired on the deck, no rack end seen)
                "along_pipe_from_start": bool(self.along_pipe_from_start_hint),
                # how the rack lock was established: verified / re-acquired / acquired / unverified / unchecked
                "rack_lock": self.rack_lock,
                "last_pose_age_s": None if self.last_pose_sent_s is None else round(now - self.last_pose_sent_s, 3),
                # capture -> pose on the socket, median of the last 100 poses: what VISO_DELAY_MS is set from
                "capture_to_send_ms_p50": (None if not self._latency_ms
                                           else round(float(np.median(self._latency_ms)), 1)),
                # the vision worker's own time per frame (trackers, acquisition), last 100 frames: what the
                # companion computer's CPU spends; above the frame period the camera's frames queue up
                "vision_ms_p50": None if not self._vision_ms else round(float(np.median(self._vision_ms)), 1),
                "vision_ms_max": None if not self._vision_ms else round(float(np.max(self._vision_ms)), 1),
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
