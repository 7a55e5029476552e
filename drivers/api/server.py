"""The control API: a small authenticated HTTP server (aiohttp) in front of the daemon.

Routes (JSON in and out; errors are `{"error": "..."}`):

    GET    /api/v1/status                         status_provider()            200
    GET    /api/v1/missions                       stored missions              200
    POST   /api/v1/missions?name=FILE.xml         upload (raw body or multipart field "file")
                                                  201 stored, 413 too large, 422 invalid (not stored)
    GET    /api/v1/missions/{id}                  metadata                     200 / 404
    GET    /api/v1/missions/{id}/xml              the file                     200 / 404
    DELETE /api/v1/missions/{id}                  remove                       200 / 404
    POST   /api/v1/missions/{id}/start|pause|resume|abort   controller(id)     200 / 404 / 409
    POST   /api/v1/mission/pause|resume|abort     controller(None): the active mission

With a `StatusPage` (`drivers.api.page`): the web status page under /page/ (public static files) and its
data routes /api/v1/page/state, /api/v1/video.mjpeg, /api/v1/video.jpg (token rules as above).

Binds 127.0.0.1 by default. With a token file every request needs
`Authorization: Bearer <token>` (401 otherwise); binding any non-loopback
address without a token file is refused at start (`ConfigError`).
"""

from __future__ import annotations

import asyncio
import hmac
import inspect
import json
import logging
import os
from collections.abc import Awaitable, Callable, Mapping
from types import TracebackType
from typing import Any, Protocol

from aiohttp import BodyPartReader, web

from companion.config import ApiConfig
from companion.config_checks import api_token
from companion.config_checks import read_token_file as read_token_file  # re-exported by drivers.api
from companion.errors import CompanionError, ConfigError, MissionError
from drivers.api.page import StatusPage
from drivers.api.store import MissionStore, is_valid_id, mission_id_from_name

_log = logging.getLogger(__name__)

API_PREFIX = "/api/v1"
_CHUNK_BYTES = 65536
_MAX_PARTS = 8  # multipart parts looked at before the "file" field


class MissionController(Protocol):
    """What the daemon provides to act on missions. Raise `CompanionError` to refuse (HTTP 409).

    `mission_id` is a stored mission's id; None for pause/resume/abort means the active mission.
    A method may return a JSON-serializable dict, sent back as `result`.
    """

    async def start(self, mission_id: str) -> Any: ...

    async def pause(self, mission_id: str | None) -> Any: ...

    async def resume(self, mission_id: str | None) -> Any: ...

    async def abort(self, mission_id: str | None) -> Any: ...


Validator = Callable[[bytes, str], Any]
StatusProvider = Callable[[], "Mapping[str, Any] | Awaitable[Mapping[str, Any]]"]


def default_validator(limits: Any | None = None) -> Validator:
    """`companion.mission.parse_mission` as an upload validator (raises `MissionError`).

    `limits`: the vehicle's `companion.mission.MissionLimits` (ceiling, speed, geofence: the
    daemon passes `companion.config.mission_limits(config)`, as `companion mission validate
    --config` does, so an upload is refused with the line the offline check prints); None uses
    the parser's defaults, which need not match the configured safety limits.
    """
    from companion.mission import parse_mission

    def validate(data: bytes, name: str) -> Any:
        return parse_mission(data, source_name=name, limits=limits)

    return validate



def _json_error(status: int, message: str, **headers: str) -> web.Response:
    return web.json_response({"error": message}, status=status, headers=headers or None)


class _TooLarge(Exception):
    pass


def _summary(mission: Any) -> dict[str, Any]:
    """Display metadata of a validated mission object (any shape)."""
    out: dict[str, Any] = {"name": str(getattr(mission, "name", "") or "")}
    actions = getattr(mission, "actions", None)
    out["actions"] = len(actions) if actions is not None else None
    summary = getattr(mission, "summary", None)
    if callable(summary):
        try:
            out["summary"] = str(summary())
        except Exception:  # display only
            _log.debug("mission summary failed", exc_info=True)
    return out


class ApiServer:
    """The control API server; an async context manager (see the module docstring)."""

    def __init__(
        self,
        config: ApiConfig,
        *,
        store_dir: str | os.PathLike[str],
        validate: Validator,
        controller: MissionController,
        status_provider: StatusProvider,
        token: str | None = None,
        page: StatusPage | None = None,
    ) -> None:
        self.config = config
        self.store = MissionStore(store_dir)
        self._validate = validate
        self._controller = controller
        self._status_provider = status_provider
        self._token_override = token
        self._token: str | None = None
        self._runner: web.AppRunner | None = None
        self._port: int | None = None
        self._upload_lock = asyncio.Lock()
        self.page = page  # the web status page (drivers.api.page), None: API only

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> int:
        """The bound TCP port (the ephemeral one when `config.port` is 0)."""
        if self._port is None:
            raise RuntimeError("ApiServer is not running")
        return self._port

    @property
    def url(self) -> str:
        """Base URL a local client uses ("http://127.0.0.1:PORT")."""
        host = self.config.bind
        if host in ("0.0.0.0", "", "::"):
            host = "127.0.0.1"
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}"

    @property
    def token_required(self) -> bool:
        return self._token is not None

    def _load_token(self) -> str | None:
        if self._token_override is not None:
            return self._token_override
        return api_token(self.config)  # the rule `companion check-config` applies too

    async def start(self) -> None:
        self._token = self._load_token()
        self.store.ensure()
        app = web.Application(
            middlewares=[self._errors_middleware, self._auth_middleware],
            client_max_size=self.config.max_upload_bytes + _CHUNK_BYTES,
        )
        p = API_PREFIX
        app.router.add_get(f"{p}/status", self._status)
        app.router.add_get(f"{p}/missions", self._list)
        app.router.add_post(f"{p}/missions", self._upload)
        app.router.add_get(f"{p}/missions/{{mission_id}}", self._info)
        app.router.add_get(f"{p}/missions/{{mission_id}}/xml", self._xml)
        app.router.add_delete(f"{p}/missions/{{mission_id}}", self._delete)
        app.router.add_post(f"{p}/missions/{{mission_id}}/{{action}}", self._act)
        app.router.add_post(f"{p}/mission/{{action}}", self._act_active)
        if self.page is not None:
            self.page.add_routes(app, p)
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        site = web.TCPSite(runner, self.config.bind, self.config.port)
        try:
            await site.start()
        except OSError as exc:
            await runner.cleanup()
            raise ConfigError(f"api.port: cannot bind {self.config.bind}:{self.config.port}: {exc}") from exc
        self._runner = runner
        self._port = int(runner.addresses[0][1])
        _log.info("control API on %s (token %s)", self.url, "required" if self._token else "off, loopback only")

    async def stop(self) -> None:
        runner, self._runner = self._runner, None
        if self.page is not None:
            self.page.close()
        if runner is not None:
            await runner.cleanup()
        self._port = None

    async def __aenter__(self) -> ApiServer:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    # ------------------------------------------------------------------ middlewares
    @web.middleware
    async def _errors_middleware(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        try:
            return await handler(request)
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            return _json_error(exc.status, exc.reason)

    @web.middleware
    async def _auth_middleware(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if self._token is not None and not (self.page is not None and self.page.is_public(request.path)):
            header = request.headers.get("Authorization", "")
            scheme, _, presented = header.partition(" ")
            if scheme.lower() != "bearer" or not hmac.compare_digest(presented.strip().encode(), self._token.encode()):
                return _json_error(401, "missing or wrong bearer token", **{"WWW-Authenticate": "Bearer"})
        return await handler(request)

    # ------------------------------------------------------------------ handlers
    async def _status(self, request: web.Request) -> web.Response:
        try:
            result = self._status_provider()
            if inspect.isawaitable(result):
                result = await result
            body = dict(result)
        except Exception as exc:  # the status of a sick daemon must not take the API down
            _log.exception("status provider failed")
            return _json_error(500, f"status unavailable: {type(exc).__name__}: {exc}")
        return web.json_response(body, dumps=lambda obj: json.dumps(obj, default=str))

    async def _list(self, request: web.Request) -> web.Response:
        missions = await asyncio.to_thread(self.store.list)
        return web.json_response({"missions": missions})

    async def _read_part(self, part: BodyPartReader) -> bytes:
        limit = self.config.max_upload_bytes
        chunks: list[bytes] = []
        total = 0
        while True:
            chunk = await part.read_chunk(_CHUNK_BYTES)
            if not chunk:
                break
            total += len(chunk)
            if total > limit:
                raise _TooLarge
            chunks.append(chunk)
        return b"".join(chunks)

    async def _read_upload(self, request: web.Request) -> tuple[bytes, str]:
        name = request.query.get("name", "")
        limit = self.config.max_upload_bytes
        multipart = request.content_type.startswith("multipart/")
        # A declared length above the limit (plus the multipart envelope) is refused before reading.
        if request.content_length is not None and request.content_length > limit + (_CHUNK_BYTES if multipart else 0):
            raise _TooLarge
        if multipart:
            reader = await request.multipart()
            for _ in range(_MAX_PARTS):
                part = await reader.next()
                if part is None:
                    break
                if isinstance(part, BodyPartReader) and part.name == "file":
                    name = name or (part.filename or "")
                    return await self._read_part(part), name
            raise web.HTTPBadRequest(reason='multipart upload needs a "file" field')
        chunks: list[bytes] = []
        total = 0
        async for chunk in request.content.iter_chunked(_CHUNK_BYTES):
            total += len(chunk)
            if total > limit:
                raise _TooLarge
            chunks.append(chunk)
        return b"".join(chunks), name

    async def _upload(self, request: web.Request) -> web.Response:
        limit = self.config.max_upload_bytes
        try:
            data, name = await self._read_upload(request)
        except _TooLarge:
            return _json_error(413, f"upload larger than api.max_upload_bytes = {limit} bytes", Connection="close")
        if not name:
            return _json_error(400, "missing file name (?name=FILE.xml or a multipart filename)")
        if not data:
            return _json_error(422, f"{name}: empty file")
        mission_id = mission_id_from_name(name)
        try:
            mission = await asyncio.to_thread(self._validate, data, name)
        except (CompanionError, ValueError) as exc:
            return _json_error(422, str(exc) or type(exc).__name__)
        async with self._upload_lock:
            replaced = mission_id in self.store
            info = await asyncio.to_thread(self.store.put, mission_id, data, {**_summary(mission), "file": name})
        info["replaced"] = replaced
        _log.info("mission %s uploaded (%d bytes)", mission_id, len(data))
        return web.json_response(info, status=201)

    def _stored_id(self, request: web.Request) -> str:
        mission_id = request.match_info["mission_id"]
        if not is_valid_id(mission_id) or mission_id not in self.store:
            raise web.HTTPNotFound(reason=f"no mission {mission_id!r}")
        return mission_id

    async def _info(self, request: web.Request) -> web.Response:
        mission_id = self._stored_id(request)
        return web.json_response(await asyncio.to_thread(self.store.info, mission_id))

    async def _xml(self, request: web.Request) -> web.Response:
        mission_id = self._stored_id(request)
        data = await asyncio.to_thread(self.store.path(mission_id).read_bytes)
        return web.Response(body=data, content_type="application/xml")

    async def _delete(self, request: web.Request) -> web.Response:
        mission_id = self._stored_id(request)
        await asyncio.to_thread(self.store.delete, mission_id)
        return web.json_response({"id": mission_id, "deleted": True})

    async def _call_controller(self, action: str, mission_id: str | None) -> web.Response:
        if action not in ("start", "pause", "resume", "abort"):
            raise web.HTTPNotFound(reason=f"unknown action {action!r}")
        if action == "start" and mission_id is None:
            raise web.HTTPNotFound(reason="start needs a mission id")
        method = getattr(self._controller, action)
        try:
            result = await method(mission_id)
        except (MissionError, CompanionError) as exc:
            return _json_error(409, str(exc) or type(exc).__name__)
        body: dict[str, Any] = {"action": action, "id": mission_id, "ok": True}
        if result is not None:
            body["result"] = result
        return web.json_response(body, dumps=lambda obj: json.dumps(obj, default=str))

    async def _act(self, request: web.Request) -> web.Response:
        action = request.match_info["action"]
        if action not in ("start", "pause", "resume", "abort"):
            raise web.HTTPNotFound(reason=f"unknown action {action!r}")
        return await self._call_controller(action, self._stored_id(request))

    async def _act_active(self, request: web.Request) -> web.Response:
        action = request.match_info["action"]
        if action == "start":
            raise web.HTTPNotFound(reason="start needs a mission id: POST /api/v1/missions/{id}/start")
        return await self._call_controller(action, None)
