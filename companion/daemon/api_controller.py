"""The control API's `MissionController`: start / pause / resume / abort on the daemon."""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.errors import MissionError

if TYPE_CHECKING:
    from companion.daemon.app import Daemon

__all__ = ["ApiController"]


class ApiController:
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
