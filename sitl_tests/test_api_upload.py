"""Control API end to end: mission upload with and without token, oversize and malformed files rejected.

The server runs on a real 127.0.0.1 socket (ephemeral port) with the real mission validator
(`companion.mission.parse_mission`), the shipped example missions, and the CLI client.
"""

from __future__ import annotations

import argparse
import asyncio
import io
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from companion.config import ApiConfig
from companion.mission import parse_mission
from drivers.api import ApiClient, ApiError, ApiServer, default_validator, mission_cli

EXAMPLES = Path(__file__).resolve().parents[1] / "missions" / "examples"
TOKEN = "0123456789abcdef-sitl-token"


class RecordingController:
    def __init__(self, store_dir: Path) -> None:
        self.store_dir = store_dir
        self.started: list[str] = []

    async def start(self, mission_id: str) -> dict[str, Any]:
        # what the daemon does: load the stored file and check it parses
        mission = parse_mission((self.store_dir / f"{mission_id}.xml").read_bytes(), source_name=mission_id)
        self.started.append(mission_id)
        return {"actions": len(mission.actions)}

    async def pause(self, mission_id: str | None) -> None:
        return None

    async def resume(self, mission_id: str | None) -> None:
        return None

    async def abort(self, mission_id: str | None) -> None:
        return None


def server_for(tmp_path: Path, token_file: Path | None = None, max_upload_bytes: int = 65536) -> ApiServer:
    store = tmp_path / "missions"
    config = ApiConfig(port=0, token_file=str(token_file) if token_file else "", max_upload_bytes=max_upload_bytes)
    return ApiServer(
        config,
        store_dir=store,
        validate=default_validator(),
        controller=RecordingController(store),
        status_provider=lambda: {"mission": {"state": "idle"}},
    )


def stored(tmp_path: Path) -> list[str]:
    return sorted(p.name for p in (tmp_path / "missions").glob("*.xml"))


async def test_upload_without_token_on_loopback_then_start(tmp_path: Path) -> None:
    async with server_for(tmp_path) as server, ApiClient(server.url) as client:
        info = await client.upload_file(EXAMPLES / "rack_sweep.xml")
        assert info["id"] == "rack_sweep" and info["name"] == "rack-sweep" and info["actions"] > 5
        result = await client.start("rack_sweep")
        assert result["result"]["actions"] == info["actions"]
    assert stored(tmp_path) == ["rack_sweep.xml"]
    assert (tmp_path / "missions" / "rack_sweep.xml").read_bytes() == (EXAMPLES / "rack_sweep.xml").read_bytes()


async def test_upload_requires_the_token_when_one_is_configured(tmp_path: Path) -> None:
    token_file = tmp_path / "api-token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    async with server_for(tmp_path, token_file) as server:
        async with ApiClient(server.url) as anonymous:
            with pytest.raises(ApiError) as denied:
                await anonymous.upload_file(EXAMPLES / "fig6.xml")
        assert denied.value.status == 401
        assert stored(tmp_path) == []
        async with ApiClient(server.url, token=TOKEN) as client:
            assert (await client.upload_file(EXAMPLES / "fig6.xml"))["id"] == "fig6"
        # the CLI reads the token file named on the command line
        args = argparse.Namespace(
            mission_command="list", url=server.url, token_file=str(token_file), config=None, json=False
        )
        out = io.StringIO()
        assert await asyncio.to_thread(mission_cli, args, out) == 0
        assert "fig6" in out.getvalue()
        no_token = argparse.Namespace(mission_command="list", url=server.url, token_file=None, config=None, json=False)
        assert await asyncio.to_thread(mission_cli, no_token, io.StringIO()) == 1
    assert stored(tmp_path) == ["fig6.xml"]


async def test_non_loopback_bind_needs_a_token_file(tmp_path: Path) -> None:
    from companion.errors import ConfigError

    config = ApiConfig(bind="0.0.0.0", port=0)
    server = ApiServer(
        config,
        store_dir=tmp_path / "m",
        validate=default_validator(),
        controller=RecordingController(tmp_path / "m"),
        status_provider=dict,
    )
    with pytest.raises(ConfigError, match=r"api\.token_file"):
        await server.start()


async def test_oversize_upload_is_rejected_with_413_and_not_stored(tmp_path: Path) -> None:
    big = (EXAMPLES / "rack_sweep.xml").read_bytes().replace(b"<!--", b"<!--" + b" " * 4096, 1)
    assert len(big) > 4096
    async with server_for(tmp_path, max_upload_bytes=4096) as server:
        async with ApiClient(server.url) as client:
            with pytest.raises(ApiError) as rejected:
                await client.upload(big, "big.xml")
            assert rejected.value.status == 413
            assert (await client.upload_file(EXAMPLES / "fig6.xml"))["id"] == "fig6"  # small files still fine
        async with (
            aiohttp.ClientSession() as session,
            session.post(f"{server.url}/api/v1/missions?name=chunked.xml", data=_chunks(big)) as response,
        ):
            assert response.status == 413  # no Content-Length: cut off while streaming
    assert stored(tmp_path) == ["fig6.xml"]


async def _chunks(data: bytes) -> Any:
    for start in range(0, len(data), 1000):
        yield data[start : start + 1000]


MALFORMED = {
    "not_xml.xml": b"this is not xml",
    "truncated.xml": (EXAMPLES / "fig6.xml").read_bytes()[:-40],
    "wrong_root.xml": b'<?xml version="1.0"?><plan name="x"/>',
    "entities.xml": b'<?xml version="1.0"?><!DOCTYPE m [<!ENTITY x "boom">]><mission version="1" name="&x;"/>',
    "bad_field.xml": (EXAMPLES / "fig6.xml").read_bytes().replace(b'timeout="', b'timeout="-', 1),
}


@pytest.mark.parametrize("name", sorted(MALFORMED))
async def test_malformed_missions_are_rejected_with_422_and_not_stored(tmp_path: Path, name: str) -> None:
    async with server_for(tmp_path) as server, ApiClient(server.url) as client:
        with pytest.raises(ApiError) as rejected:
            await client.upload(MALFORMED[name], name)
        assert rejected.value.status == 422
        assert name in rejected.value.message  # the validator's message names the file (and line/field)
        assert await client.list_missions() == []
    assert stored(tmp_path) == []


async def test_vehicle_limits_given_to_the_validator_are_enforced_on_upload(tmp_path: Path) -> None:
    from companion.mission import MissionLimits

    store = tmp_path / "missions"
    server = ApiServer(
        ApiConfig(port=0),
        store_dir=store,
        validate=default_validator(MissionLimits(ceiling_m=2.0)),
        controller=RecordingController(store),
        status_provider=dict,
    )
    async with server, ApiClient(server.url) as client:
        with pytest.raises(ApiError) as rejected:
            await client.upload_file(EXAMPLES / "rack_sweep.xml")  # climbs to 2.5 m
        assert rejected.value.status == 422 and "above the ceiling 2 m" in rejected.value.message
        assert (await client.upload_file(EXAMPLES / "fig6.xml"))["id"] == "fig6"  # 1 m: fine
    assert stored(tmp_path) == ["fig6.xml"]
