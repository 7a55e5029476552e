"""The web status page on the control API: static files, the page's state, the live image (MJPEG).

Routes (added to `drivers.api.server.ApiServer` when it is given a `StatusPage`):

    GET /                          302 to /page/
    GET /page/ , /page/{file}      the page (HTML, JS, CSS shipped in drivers/api/static; no token:
                                   they hold no data, every request the page makes carries the token)
    GET /api/v1/page/state         state_provider() as JSON                        (token rules apply)
    GET /api/v1/video.mjpeg        multipart/x-mixed-replace JPEG stream            (token rules apply)
    GET /api/v1/video.jpg          the newest JPEG (204 before the first)          (token rules apply)

The MJPEG handler waits for the streamer's next JPEG (a listener on the streamer thread wakes it through
the event loop), writes it, and returns when the client goes away or the server stops; a slow client
gets the newest picture each time, never a backlog.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import json
import logging
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any

from aiohttp import web

_log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).with_name("static")
PUBLIC_PREFIXES = ("/page/",)
PUBLIC_PATHS = ("/", "/page", "/favicon.ico")
_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}
_BOUNDARY = "companionframe"

PageStateProvider = Callable[[], "Mapping[str, Any] | Awaitable[Mapping[str, Any]]"]


class StatusPage:
    """The page's routes; `streamer` is a `drivers.video.VideoStreamer` (None: no live image)."""

    def __init__(self, state_provider: PageStateProvider, streamer: Any | None = None) -> None:
        self._state_provider = state_provider
        self._streamer = streamer
        self._waiters: set[asyncio.Event] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._remove_listener: Callable[[], Any] | None = None
        self._closing = False
        self.clients = 0  # MJPEG clients connected now

    @staticmethod
    def is_public(path: str) -> bool:
        return path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)

    def add_routes(self, app: web.Application, prefix: str) -> None:
        self._loop = asyncio.get_running_loop()
        if self._streamer is not None and self._remove_listener is None:
            self._remove_listener = self._streamer.add_jpeg_listener(self._on_jpeg)
        app.router.add_get("/", self._root)
        app.router.add_get("/page", self._root)
        app.router.add_get("/page/", self._static)
        app.router.add_get("/page/{name}", self._static)
        app.router.add_get(f"{prefix}/page/state", self._state)
        app.router.add_get(f"{prefix}/video.mjpeg", self._mjpeg)
        app.router.add_get(f"{prefix}/video.jpg", self._jpeg)

    def close(self) -> None:
        """Release the streaming handlers (before the server stops: they would hold its shutdown)."""
        self._closing = True
        if self._remove_listener is not None:
            self._remove_listener()
            self._remove_listener = None
        for ev in list(self._waiters):
            ev.set()

    # ------------------------------------------------------------------ streamer thread -> loop
    def _on_jpeg(self, seq: int, jpeg: bytes) -> None:
        loop = self._loop
        if loop is None or not self._waiters:
            return
        with contextlib.suppress(RuntimeError):  # loop closed during shutdown
            loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        for ev in list(self._waiters):
            ev.set()

    # ------------------------------------------------------------------ handlers
    async def _root(self, request: web.Request) -> web.StreamResponse:
        raise web.HTTPFound("/page/")

    async def _static(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info.get("name", "") or "index.html"
        path = STATIC_DIR / name
        if "/" in name or name.startswith(".") or path.suffix not in _TYPES or not path.is_file():
            raise web.HTTPNotFound(reason=f"no page file {name!r}")
        body = await asyncio.to_thread(path.read_bytes)
        return web.Response(body=body, content_type=_TYPES[path.suffix], charset="utf-8",
                            headers={"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"})

    async def _state(self, request: web.Request) -> web.Response:
        try:
            result = self._state_provider()
            if inspect.isawaitable(result):
                result = await result
            body = dict(result)
        except Exception as exc:  # a sick daemon's page must still load
            _log.exception("page state provider failed")
            return web.json_response({"error": f"state unavailable: {type(exc).__name__}: {exc}"}, status=500)
        return web.json_response(body, dumps=lambda obj: json.dumps(obj, default=str))

    def _need_streamer(self) -> Any:
        if self._streamer is None:
            raise web.HTTPNotFound(reason="no video (video.enabled = false)")
        return self._streamer

    async def _jpeg(self, request: web.Request) -> web.Response:
        streamer = self._need_streamer()
        streamer.want_jpeg()
        seq, jpeg = streamer.latest_jpeg()
        if not jpeg:
            return web.Response(status=204, headers={"Cache-Control": "no-store"})
        return web.Response(body=jpeg, content_type="image/jpeg", headers={"Cache-Control": "no-store",
                                                                            "X-Frame-Seq": str(seq)})

    async def _mjpeg(self, request: web.Request) -> web.StreamResponse:
        streamer = self._need_streamer()
        resp = web.StreamResponse(headers={"Content-Type": f"multipart/x-mixed-replace; boundary={_BOUNDARY}",
                                           "Cache-Control": "no-store"})
        await resp.prepare(request)
        ev = asyncio.Event()
        self._waiters.add(ev)
        self.clients += 1
        last = -1
        try:
            while not self._closing:
                streamer.want_jpeg()
                seq, jpeg = streamer.latest_jpeg()
                if seq != last and jpeg:
                    last = seq
                    head = (f"--{_BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
                            f"X-Frame-Seq: {seq}\r\n\r\n").encode()
                    await resp.write(head + jpeg + b"\r\n")
                ev.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(ev.wait(), timeout=1.0)  # wakes on a new JPEG; 1 s keeps interest up
        except (ConnectionError, asyncio.CancelledError):  # the client went away mid-stream
            _log.debug("MJPEG client left")
        finally:
            self._waiters.discard(ev)
            self.clients -= 1
        return resp
