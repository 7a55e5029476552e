"""Async client of the control API, and the `companion mission ...` / `companion status` commands.

`ApiClient` wraps the HTTP routes of `drivers.api.server`; every failure is an
`ApiError` (status 0 when the daemon cannot be reached). The CLI functions take
an `argparse.Namespace` already parsed by `companion/cli.py`; the helpers
`add_client_arguments` and `add_mission_subcommands` add the arguments they
read (see `docs/drivers.md`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any, TextIO

import aiohttp

from companion.config import DEFAULT_CONFIG_PATH, load_config
from companion.errors import CompanionError, ConfigError
from drivers.api.server import API_PREFIX

DEFAULT_URL = "http://127.0.0.1:8765"
MISSION_COMMANDS = ("upload", "list", "start", "pause", "resume", "abort", "status")

EXIT_OK = 0
EXIT_FAILED = 1  # daemon unreachable, refused, unauthorized, unknown mission
EXIT_INVALID = 2  # usage error, invalid or oversize mission file


class ApiError(CompanionError):
    """A control API request failed: `status` is the HTTP status (0: daemon unreachable)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


class ApiClient:
    """Talks to a running daemon's control API (async context manager)."""

    def __init__(self, base_url: str = DEFAULT_URL, *, token: str | None = None, timeout_s: float = 10.0) -> None:
        self.base_url = base_url.rstrip("/")
        self._token = token
        self._timeout = aiohttp.ClientTimeout(total=timeout_s)
        self._session: aiohttp.ClientSession | None = None

    async def __aenter__(self) -> ApiClient:
        headers = {"Authorization": f"Bearer {self._token}"} if self._token else {}
        self._session = aiohttp.ClientSession(timeout=self._timeout, headers=headers)
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        session, self._session = self._session, None
        if session is not None:
            await session.close()

    async def _request(self, method: str, path: str, **kwargs: Any) -> Any:
        if self._session is None:
            raise RuntimeError("use ApiClient as an async context manager")
        url = f"{self.base_url}{API_PREFIX}{path}"
        try:
            async with self._session.request(method, url, **kwargs) as response:
                text = await response.text()
                try:
                    body = json.loads(text) if text else {}
                except ValueError:
                    body = {"error": text.strip()[:200]}
                if response.status >= 400:
                    message = body.get("error") if isinstance(body, dict) else None
                    raise ApiError(response.status, str(message or response.reason or response.status))
                return body
        except aiohttp.ClientError as exc:
            raise ApiError(0, f"cannot reach the daemon at {self.base_url}: {exc}") from exc
        except TimeoutError as exc:
            raise ApiError(0, f"no answer from the daemon at {self.base_url}") from exc

    async def status(self) -> dict[str, Any]:
        """The daemon's status dict."""
        result: dict[str, Any] = await self._request("GET", "/status")
        return result

    async def list_missions(self) -> list[dict[str, Any]]:
        """Metadata of the stored missions."""
        body = await self._request("GET", "/missions")
        missions: list[dict[str, Any]] = body.get("missions", [])
        return missions

    async def upload(self, data: bytes, name: str) -> dict[str, Any]:
        """Upload a mission file's bytes under the file name `name`; returns its stored metadata."""
        result: dict[str, Any] = await self._request(
            "POST", "/missions", params={"name": name}, data=data, headers={"Content-Type": "application/xml"}
        )
        return result

    async def upload_file(self, path: str | os.PathLike[str], name: str | None = None) -> dict[str, Any]:
        """Upload the mission file at `path` (named `name` or its file name)."""
        p = Path(path)
        data = await asyncio.to_thread(p.read_bytes)
        return await self.upload(data, name or p.name)

    async def mission(self, mission_id: str) -> dict[str, Any]:
        """Metadata of one stored mission."""
        result: dict[str, Any] = await self._request("GET", f"/missions/{mission_id}")
        return result

    async def delete(self, mission_id: str) -> dict[str, Any]:
        result: dict[str, Any] = await self._request("DELETE", f"/missions/{mission_id}")
        return result

    async def act(self, action: str, mission_id: str | None = None) -> dict[str, Any]:
        """start/pause/resume/abort a stored mission, or (mission_id None) the active one."""
        if action not in ("start", "pause", "resume", "abort"):
            raise ValueError(f"unknown action {action!r}")
        path = f"/missions/{mission_id}/{action}" if mission_id else f"/mission/{action}"
        result: dict[str, Any] = await self._request("POST", path)
        return result

    async def start(self, mission_id: str) -> dict[str, Any]:
        return await self.act("start", mission_id)

    async def pause(self, mission_id: str | None = None) -> dict[str, Any]:
        return await self.act("pause", mission_id)

    async def resume(self, mission_id: str | None = None) -> dict[str, Any]:
        return await self.act("resume", mission_id)

    async def abort(self, mission_id: str | None = None) -> dict[str, Any]:
        return await self.act("abort", mission_id)


# --------------------------------------------------------------------------- argparse helpers
def add_client_arguments(parser: argparse.ArgumentParser) -> None:
    """--url, --token-file, --config, --json (how to reach the daemon)."""
    parser.add_argument(
        "--url", default=None, help=f"control API base URL (default: from --config, else {DEFAULT_URL})"
    )
    parser.add_argument("--token-file", default=None, help="bearer token file (default: api.token_file of --config)")
    parser.add_argument(
        "--config",
        default=None,
        help=f"daemon config to read api.bind/port/token_file from (default {DEFAULT_CONFIG_PATH})",
    )
    parser.add_argument("--json", action="store_true", help="print the raw JSON answer")


def add_mission_subcommands(subparsers: Any) -> None:
    """Add upload/list/start/pause/resume/abort/status under an existing `mission` subparsers object.

    Each sets `mission_command` and `func=mission_cli`. (`validate` stays with the caller.)
    """
    helps = {
        "upload": "upload a mission file (validated by the daemon, stored if valid)",
        "list": "list stored missions",
        "start": "start a stored mission",
        "pause": "pause the active mission (or ID)",
        "resume": "resume the paused mission (or ID)",
        "abort": "abort the active mission (or ID): the vehicle hovers",
        "status": "mission progress",
    }
    for command in MISSION_COMMANDS:
        sub = subparsers.add_parser(command, help=helps[command])
        if command == "upload":
            sub.add_argument("file", help="mission XML file")
            sub.add_argument("--name", default=None, help="name to store it under (default: the file name)")
        elif command == "start":
            sub.add_argument("mission_id", help="stored mission id (see `companion mission list`)")
        elif command in ("pause", "resume", "abort"):
            sub.add_argument("mission_id", nargs="?", default=None, help="mission id (default: the active one)")
        add_client_arguments(sub)
        sub.set_defaults(mission_command=command, func=mission_cli)


def resolve_endpoint(args: argparse.Namespace) -> tuple[str, str | None]:
    """(base URL, token or None) from --url/--token-file, else the daemon's config file."""
    url: str | None = getattr(args, "url", None)
    token_file: str | None = getattr(args, "token_file", None)
    config_path = getattr(args, "config", None)
    config = None
    if config_path is not None:
        config = load_config(config_path)  # ConfigError: the user named a bad file
    elif url is None or token_file is None:
        with contextlib.suppress(ConfigError):
            if DEFAULT_CONFIG_PATH.is_file():
                config = load_config(DEFAULT_CONFIG_PATH)
    if url is None:
        if config is not None:
            host = config.api.bind
            if host in ("0.0.0.0", "::", ""):
                host = "127.0.0.1"
            host = f"[{host}]" if ":" in host else host
            url = f"http://{host}:{config.api.port}"
        else:
            url = DEFAULT_URL
    if token_file is None and config is not None and config.api.token_file:
        token_file = config.api.token_file
    token = None
    if token_file:
        try:
            token = Path(token_file).read_text(encoding="utf-8").strip() or None
        except OSError as exc:
            if getattr(args, "token_file", None) is not None:
                raise ConfigError(f"--token-file: cannot read {token_file}: {exc.strerror or exc}") from exc
            token = None  # the config's file may be root-only; the server will answer 401 if it needs it
    return url, token


# --------------------------------------------------------------------------- output
def _fmt(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3f}".rstrip("0").rstrip(".") if abs(value) < 1e6 else f"{value:.4g}"
    if value is None:
        return "-"
    if isinstance(value, list | tuple):
        return ", ".join(_fmt(v) for v in value) if value else "[]"
    return str(value)


def _flatten(data: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.extend(_flatten(value, f"{name}."))
        else:
            out.append((name, value))
    return out


def format_status(status: Mapping[str, Any]) -> str:
    """A readable multi-line rendering of a status dict: one block per top-level section."""
    lines: list[str] = []
    scalars = [(k, v) for k, v in status.items() if not isinstance(v, Mapping)]
    for key, value in scalars:
        lines.append(f"{key}: {_fmt(value)}")
    for key, value in status.items():
        if isinstance(value, Mapping):
            lines.append(f"{key}:")
            rows = _flatten(value)
            width = max((len(k) for k, _ in rows), default=0)
            lines.extend(f"  {k.ljust(width)}  {_fmt(v)}" for k, v in rows)
            if not rows:
                lines.append("  -")
    return "\n".join(lines)


def format_missions(missions: list[dict[str, Any]]) -> str:
    """A table of stored missions."""
    if not missions:
        return "no missions stored"
    header = ("ID", "NAME", "ACTIONS", "BYTES", "UPLOADED (UTC)")
    rows = [
        (
            str(m.get("id", "")),
            str(m.get("name", "") or "-"),
            _fmt(m.get("actions")),
            _fmt(m.get("size_bytes")),
            str(m.get("uploaded_utc", "-")),
        )
        for m in missions
    ]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)).rstrip() for r in [header, *rows]]
    return "\n".join(lines)


# --------------------------------------------------------------------------- commands
async def _mission_command(args: argparse.Namespace, out: TextIO) -> int:
    command = getattr(args, "mission_command", None)
    as_json = bool(getattr(args, "json", False))
    if command not in MISSION_COMMANDS:
        print(f"companion mission: unknown command {command!r} (one of {', '.join(MISSION_COMMANDS)})", file=sys.stderr)
        return EXIT_INVALID
    url, token = resolve_endpoint(args)
    async with ApiClient(url, token=token) as client:
        if command == "upload":
            path = Path(args.file)
            if not path.is_file():
                print(f"companion mission upload: {path}: no such file", file=sys.stderr)
                return EXIT_INVALID
            info = await client.upload_file(path, getattr(args, "name", None))
            if as_json:
                print(json.dumps(info, indent=1), file=out)
            else:
                verb = "replaced" if info.get("replaced") else "uploaded"
                print(
                    f"{verb} {info.get('id')}: {info.get('name') or '(unnamed)'}, "
                    f"{_fmt(info.get('actions'))} actions, {info.get('size_bytes')} bytes",
                    file=out,
                )
        elif command == "list":
            missions = await client.list_missions()
            print(json.dumps(missions, indent=1) if as_json else format_missions(missions), file=out)
        elif command == "status":
            status = await client.status()
            mission = status.get("mission", status)
            if as_json:
                print(json.dumps(mission, indent=1), file=out)
            else:
                print(format_status({"mission": mission} if isinstance(mission, Mapping) else status), file=out)
        else:
            mission_id = getattr(args, "mission_id", None) or getattr(args, "name", None)
            if command == "start" and not mission_id:
                print("companion mission start: a mission id is required", file=sys.stderr)
                return EXIT_INVALID
            result = await client.act(command, mission_id)
            if as_json:
                print(json.dumps(result, indent=1), file=out)
            else:
                print(f"{command} {mission_id or 'active mission'}: ok", file=out)
    return EXIT_OK


def _report_error(prefix: str, exc: Exception) -> int:
    if isinstance(exc, ApiError):
        if exc.status == 0:
            print(f"{prefix}: {exc.message} (is `companion run` active?)", file=sys.stderr)
            return EXIT_FAILED
        hint = " (use --token-file)" if exc.status == 401 else ""
        print(f"{prefix}: HTTP {exc.status}: {exc.message}{hint}", file=sys.stderr)
        return EXIT_INVALID if exc.status in (413, 422) else EXIT_FAILED
    print(f"{prefix}: {exc}", file=sys.stderr)
    return EXIT_INVALID


def mission_cli(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """`companion mission upload|list|start|pause|resume|abort|status`; returns the exit code."""
    try:
        return asyncio.run(_mission_command(args, out or sys.stdout))
    except (ApiError, ConfigError, OSError) as exc:
        return _report_error(f"companion mission {getattr(args, 'mission_command', '')}".rstrip(), exc)


async def _status_command(args: argparse.Namespace, out: TextIO) -> int:
    url, token = resolve_endpoint(args)
    async with ApiClient(url, token=token) as client:
        status = await client.status()
    print(json.dumps(status, indent=1) if getattr(args, "json", False) else format_status(status), file=out)
    return EXIT_OK


def status_cli(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """`companion status`: daemon, link, camera, estimator, mission, safety; returns the exit code."""
    try:
        return asyncio.run(_status_command(args, out or sys.stdout))
    except (ApiError, ConfigError, OSError) as exc:
        return _report_error("companion status", exc)
