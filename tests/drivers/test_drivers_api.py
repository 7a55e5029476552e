"""Control API server and client over real 127.0.0.1 sockets (port 0), with an injected validator."""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import os
from pathlib import Path
from typing import Any

import pytest

from companion.config import ApiConfig
from companion.errors import ConfigError, MissionError
from drivers.api import (
    ApiClient,
    ApiError,
    ApiServer,
    MissionStore,
    add_mission_subcommands,
    format_status,
    mission_cli,
    mission_id_from_name,
    status_cli,
)

TOKEN = "s3cret-token-0123456789"


class Parsed:
    """What the fake validator returns (shaped like companion.mission.Mission for display)."""

    def __init__(self, name: str, actions: int) -> None:
        self.name = name
        self.actions = tuple(range(actions))


def validate(data: bytes, name: str) -> Parsed:
    """Accepts `<mission name="N" actions="K"/>` documents; anything else is a MissionError."""
    text = data.decode("utf-8", "replace")
    if not text.startswith("<mission") or 'actions="' not in text:
        raise MissionError(f"{name}:1: mission: not a mission document")
    mission_name = text.split('name="', 1)[1].split('"', 1)[0] if 'name="' in text else ""
    return Parsed(mission_name, int(text.split('actions="', 1)[1].split('"', 1)[0]))


class Controller:
    def __init__(self) -> None:
        self.calls: list[tuple[str, str | None]] = []
        self.refuse: str | None = None

    async def _record(self, action: str, mission_id: str | None) -> dict[str, Any]:
        if self.refuse == action:
            raise MissionError(f"cannot {action}: vehicle not armed")
        self.calls.append((action, mission_id))
        return {"state": action}

    async def start(self, mission_id: str) -> dict[str, Any]:
        return await self._record("start", mission_id)

    async def pause(self, mission_id: str | None) -> dict[str, Any]:
        return await self._record("pause", mission_id)

    async def resume(self, mission_id: str | None) -> dict[str, Any]:
        return await self._record("resume", mission_id)

    async def abort(self, mission_id: str | None) -> dict[str, Any]:
        return await self._record("abort", mission_id)


def status() -> dict[str, Any]:
    return {
        "daemon": {"uptime_s": 12.5, "version": "0.1.0"},
        "link": {"connected": True, "autopilot": "ardupilot", "mode": "GUIDED"},
        "camera": {"state": "streaming", "fps": 29.97, "dropped_stale": 3},
        "estimator": {"ok": True, "source": "rack"},
        "mission": {"id": "survey", "state": "running", "action": 3, "of": 8},
        "safety": {"state": "nominal", "events": []},
    }


def make_server(tmp_path: Path, controller: Controller, **api: Any) -> ApiServer:
    config = ApiConfig(port=0, max_upload_bytes=api.pop("max_upload_bytes", 2048), **api)
    return ApiServer(
        config, store_dir=tmp_path / "missions", validate=validate, controller=controller, status_provider=status
    )


GOOD = b'<mission name="Rack sweep" actions="4"/>'


async def test_upload_list_start_pause_resume_abort_status(tmp_path: Path) -> None:
    controller = Controller()
    async with make_server(tmp_path, controller) as server, ApiClient(server.url) as client:
        assert server.url.startswith("http://127.0.0.1:") and server.port > 0
        info = await client.upload(GOOD, "rack sweep.xml")
        assert info["id"] == "rack-sweep" and info["name"] == "Rack sweep" and info["actions"] == 4
        assert info["replaced"] is False and info["size_bytes"] == len(GOOD)
        assert (tmp_path / "missions" / "rack-sweep.xml").read_bytes() == GOOD
        again = await client.upload(GOOD, "rack sweep.xml")
        assert again["replaced"] is True
        missions = await client.list_missions()
        assert [m["id"] for m in missions] == ["rack-sweep"] and missions[0]["actions"] == 4

        assert (await client.start("rack-sweep"))["result"] == {"state": "start"}
        await client.pause()
        await client.resume("rack-sweep")
        await client.abort()
        assert controller.calls == [
            ("start", "rack-sweep"),
            ("pause", None),
            ("resume", "rack-sweep"),
            ("abort", None),
        ]
        with pytest.raises(ApiError) as unknown:
            await client.start("nope")
        assert unknown.value.status == 404
        controller.refuse = "start"
        with pytest.raises(ApiError) as refused:
            await client.start("rack-sweep")
        assert refused.value.status == 409 and "not armed" in refused.value.message
        assert await client.status() == status()
        await client.delete("rack-sweep")
        assert await client.list_missions() == []


async def test_invalid_and_oversize_uploads_are_rejected_and_not_stored(tmp_path: Path) -> None:
    async with make_server(tmp_path, Controller(), max_upload_bytes=1024) as server, ApiClient(server.url) as client:
        with pytest.raises(ApiError) as invalid:
            await client.upload(b"<html>not a mission</html>", "bad.xml")
        assert invalid.value.status == 422 and "bad.xml:1" in invalid.value.message
        with pytest.raises(ApiError) as oversize:
            await client.upload(b'<mission actions="1"/>' + b" " * 2000, "big.xml")
        assert oversize.value.status == 413
        with pytest.raises(ApiError) as empty:
            await client.upload(b"", "empty.xml")
        assert empty.value.status == 422
        assert await client.list_missions() == []
    assert sorted(os.listdir(tmp_path / "missions")) == []


async def test_oversize_upload_without_content_length_is_rejected(tmp_path: Path) -> None:
    async def body() -> Any:
        for _ in range(10):
            yield b" " * 512

    async with make_server(tmp_path, Controller(), max_upload_bytes=1024) as server:
        import aiohttp

        async with (
            aiohttp.ClientSession() as session,
            session.post(f"{server.url}/api/v1/missions", params={"name": "chunked.xml"}, data=body()) as response,
        ):
            assert response.status == 413
    assert os.listdir(tmp_path / "missions") == []


async def test_upload_limit_is_enforced_while_streaming(tmp_path: Path) -> None:
    """The server answers 413 after limit bytes, while the client still has an endless body to send."""
    import aiohttp

    sent: list[int] = []
    never = asyncio.Event()

    async def endless() -> Any:
        for k in range(4):
            sent.append(k)
            yield b" " * 512
        await never.wait()  # the rest of an "infinite" body: only reached if the server keeps reading
        yield b""

    async with make_server(tmp_path, Controller(), max_upload_bytes=1024) as server:
        # The timeout only turns a server that waits for the whole body (a hang) into a failure.
        async with (
            asyncio.timeout(30.0),
            aiohttp.ClientSession() as session,
            session.post(f"{server.url}/api/v1/missions", params={"name": "endless.xml"}, data=endless()) as response,
        ):
            assert response.status == 413
        assert len(sent) <= 4 and not never.is_set()
    assert os.listdir(tmp_path / "missions") == []


async def test_multipart_upload(tmp_path: Path) -> None:
    import aiohttp

    async with make_server(tmp_path, Controller()) as server, aiohttp.ClientSession() as session:
        form = aiohttp.FormData()
        form.add_field("file", GOOD, filename="multi.xml", content_type="application/xml")
        async with session.post(f"{server.url}/api/v1/missions", data=form) as response:
            assert response.status == 201
            assert (await response.json())["id"] == "multi"


async def test_token_required_when_configured(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    async with make_server(tmp_path, Controller(), token_file=str(token_file)) as server:
        assert server.token_required
        async with ApiClient(server.url) as anonymous:
            with pytest.raises(ApiError) as denied:
                await anonymous.upload(GOOD, "m.xml")
            assert denied.value.status == 401
            with pytest.raises(ApiError):
                await anonymous.status()
        async with ApiClient(server.url, token="wrong-token-0123456789") as wrong:
            with pytest.raises(ApiError) as denied:
                await wrong.list_missions()
            assert denied.value.status == 401
        async with ApiClient(server.url, token=TOKEN) as client:
            assert (await client.upload(GOOD, "m.xml"))["id"] == "m"
    assert [p.name for p in (tmp_path / "missions").glob("*.xml")] == ["m.xml"]


async def test_non_loopback_bind_without_token_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"api\.token_file"):
        async with make_server(tmp_path, Controller(), bind="0.0.0.0"):
            pass


async def test_world_readable_or_short_token_file_is_refused(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN)
    token_file.chmod(0o644)
    with pytest.raises(ConfigError, match="readable by other users"):
        async with make_server(tmp_path, Controller(), token_file=str(token_file)):
            pass
    token_file.chmod(0o602)  # anyone could replace the token
    with pytest.raises(ConfigError, match="writable by other users"):
        async with make_server(tmp_path, Controller(), token_file=str(token_file)):
            pass
    token_file.write_text("short")
    token_file.chmod(0o600)
    with pytest.raises(ConfigError, match="at least 16"):
        async with make_server(tmp_path, Controller(), token_file=str(token_file)):
            pass


async def test_unreachable_daemon_is_api_error_status_0(tmp_path: Path) -> None:
    async with make_server(tmp_path, Controller()) as server:
        url = server.url
    async with ApiClient(url, timeout_s=2.0) as client:
        with pytest.raises(ApiError) as err:
            await client.status()
    assert err.value.status == 0


async def test_failing_status_provider_is_a_json_500(tmp_path: Path) -> None:
    def broken() -> dict[str, Any]:
        raise RuntimeError("estimator exploded")

    config = ApiConfig(port=0)
    server = ApiServer(config, store_dir=tmp_path, validate=validate, controller=Controller(), status_provider=broken)
    async with server, ApiClient(server.url) as client:
        with pytest.raises(ApiError) as err:
            await client.status()
        assert err.value.status == 500 and "estimator exploded" in err.value.message
        assert await client.list_missions() == []  # the rest of the API keeps working


def test_mission_ids_are_safe_file_names() -> None:
    assert mission_id_from_name("Rack survey #2.xml") == "Rack-survey--2"
    assert mission_id_from_name("../../etc/passwd") == "passwd"
    assert mission_id_from_name("..hidden.xml") == "hidden"
    assert mission_id_from_name("") == "mission"
    assert len(mission_id_from_name("x" * 200 + ".xml")) == 64


def test_store_ignores_path_traversal_ids(tmp_path: Path) -> None:
    store = MissionStore(tmp_path)
    with pytest.raises(KeyError):
        store.path("../secret")
    assert "../secret" not in store


def parse_cli(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="companion")
    commands = parser.add_subparsers(dest="command")
    mission = commands.add_parser("mission")
    add_mission_subcommands(mission.add_subparsers(dest="mission_command"))
    return parser.parse_args(argv)


async def run_cli(argv: list[str]) -> tuple[int, str]:
    args = parse_cli(argv)
    out = io.StringIO()
    code = await asyncio.to_thread(args.func, args, out)
    return code, out.getvalue()


async def test_cli_commands_against_a_running_server(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    controller = Controller()
    mission_file = tmp_path / "sweep.xml"
    mission_file.write_bytes(GOOD)
    bad_file = tmp_path / "bad.xml"
    bad_file.write_bytes(b"<nope/>")
    async with make_server(tmp_path, controller) as server:
        url = ["--url", server.url]
        code, out = await run_cli(["mission", "upload", str(mission_file), *url])
        assert code == 0 and out.startswith("uploaded sweep: Rack sweep, 4 actions")
        code, out = await run_cli(["mission", "upload", str(bad_file), *url])
        assert code == 2 and out == ""
        assert "HTTP 422" in capsys.readouterr().err
        code, out = await run_cli(["mission", "list", *url])
        assert code == 0 and out.splitlines()[0].split() == ["ID", "NAME", "ACTIONS", "BYTES", "UPLOADED", "(UTC)"]
        assert out.splitlines()[1].startswith("sweep")
        code, out = await run_cli(["mission", "start", "sweep", *url])
        assert code == 0 and out.strip() == "start sweep: ok"
        code, out = await run_cli(["mission", "abort", *url])
        assert code == 0 and out.strip() == "abort active mission: ok"
        code, out = await run_cli(["mission", "start", "ghost", *url])
        assert code == 1
        code, out = await run_cli(["mission", "status", "--json", *url])
        assert code == 0 and json.loads(out) == status()["mission"]
        args = argparse.Namespace(url=server.url, json=False)
        text = io.StringIO()
        assert await asyncio.to_thread(status_cli, args, text) == 0
        assert "camera:\n" in text.getvalue() and "dropped_stale  3" in text.getvalue()
    assert controller.calls == [("start", "sweep"), ("abort", None)]
    gone = argparse.Namespace(mission_command="list", url=url[1])
    assert await asyncio.to_thread(mission_cli, gone) == 1  # server gone
    assert "is `companion run` active?" in capsys.readouterr().err


def test_format_status_is_readable() -> None:
    text = format_status({"state": "ok", "link": {"connected": True, "rtt_ms": 12.3456, "gcs": {"count": 2}}})
    assert text.splitlines() == ["state: ok", "link:", "  connected  yes", "  rtt_ms     12.346", "  gcs.count  2"]
