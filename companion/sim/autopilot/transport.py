"""Byte transports of the fake autopilot: a UDP server, a UDP client and a TCP server (asyncio).

Only bytes cross this boundary; framing and MAVLink live in `autopilot.py`.

- ``udpin:HOST:PORT`` binds the port and replies to the peers it heard from (the
  most recent `max_peers`), like ArduPilot SITL's UDP server; clients use ``udpout:HOST:PORT``.
- ``udpout:HOST:PORT`` sends to a fixed peer (a client listening with ``udpin``) from an ephemeral port.
- ``tcpin:HOST:PORT`` listens and serves any number of clients; clients use ``tcp:HOST:PORT``.

Port 0 binds an ephemeral port; `url_for_client` names the address a client should use.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
from collections.abc import Callable
from dataclasses import dataclass

from companion.errors import ConfigError, LinkError

__all__ = [
    "ListenUrl",
    "ServerTransport",
    "TcpServerTransport",
    "UdpClientTransport",
    "UdpServerTransport",
    "open_transport",
    "parse_listen_url",
]

PeerKey = tuple[str, int] | int
OnBytes = Callable[[bytes, PeerKey], None]

_MAX_TCP_BUFFER_BYTES = 1 << 20


@dataclass(frozen=True)
class ListenUrl:
    """A parsed endpoint: scheme ("udpin" | "udpout" | "tcpin"), host, port."""

    scheme: str
    host: str
    port: int


def parse_listen_url(url: str) -> ListenUrl:
    """Parse ``udpin:HOST:PORT``, ``udpout:HOST:PORT`` or ``tcpin:HOST:PORT`` (``scheme://`` also accepted)."""
    text = url.strip().replace("://", ":")
    scheme, _, rest = text.partition(":")
    host, _, port_text = rest.rpartition(":")
    if scheme not in ("udpin", "udpout", "tcpin") or not host or not port_text:
        raise ConfigError(f"listen URL {url!r} must be udpin:HOST:PORT, udpout:HOST:PORT or tcpin:HOST:PORT")
    try:
        port = int(port_text)
    except ValueError as exc:
        raise ConfigError(f"listen URL {url!r}: port {port_text!r} is not an integer") from exc
    if not 0 <= port <= 65535 or (scheme == "udpout" and port == 0):
        raise ConfigError(f"listen URL {url!r}: bad port {port}")
    return ListenUrl(scheme, host, port)


class ServerTransport:
    """Common surface: `start()`, `send(data)` to every peer, `close()`, `url_for_client`, `peer_count`."""

    def __init__(self, on_bytes: OnBytes) -> None:
        self._on_bytes = on_bytes
        self.bytes_sent = 0
        self.bytes_received = 0

    async def start(self) -> None:
        raise NotImplementedError

    def send(self, data: bytes) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    @property
    def url_for_client(self) -> str:
        raise NotImplementedError

    @property
    def peer_count(self) -> int:
        raise NotImplementedError


class _UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpServerTransport | UdpClientTransport) -> None:
        self._owner = owner

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self._owner._datagram(data, (addr[0], addr[1]))

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable when a peer went away: harmless for a datagram server.
        pass


class UdpServerTransport(ServerTransport):
    """UDP server: binds (host, port), replies to the `max_peers` most recent senders."""

    def __init__(self, host: str, port: int, on_bytes: OnBytes, max_peers: int = 4) -> None:
        super().__init__(on_bytes)
        self._host, self._port = host, port
        self._peers: collections.OrderedDict[tuple[str, int], None] = collections.OrderedDict()
        self._max_peers = max_peers
        self._transport: asyncio.DatagramTransport | None = None

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _UdpProtocol(self), local_addr=(self._host, self._port)
            )
        except OSError as exc:
            raise LinkError(f"cannot bind udp {self._host}:{self._port}: {exc}") from exc
        self._transport = transport
        sockname = transport.get_extra_info("sockname")
        self._port = int(sockname[1])

    def _datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        self._peers[addr] = None
        self._peers.move_to_end(addr)
        while len(self._peers) > self._max_peers:
            self._peers.popitem(last=False)
        self.bytes_received += len(data)
        self._on_bytes(data, addr)

    def send(self, data: bytes) -> None:
        if self._transport is None:
            return
        for addr in self._peers:
            self._transport.sendto(data, addr)
            self.bytes_sent += len(data)

    async def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    @property
    def port(self) -> int:
        return self._port

    @property
    def url_for_client(self) -> str:
        return f"udpout:{_reachable_host(self._host)}:{self._port}"

    @property
    def peer_count(self) -> int:
        return len(self._peers)


class UdpClientTransport(ServerTransport):
    """UDP towards a fixed peer (the client listens with udpin)."""

    def __init__(self, host: str, port: int, on_bytes: OnBytes) -> None:
        super().__init__(on_bytes)
        self._peer = (host, port)
        self._transport: asyncio.DatagramTransport | None = None

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(lambda: _UdpProtocol(self), remote_addr=self._peer)
        self._transport = transport

    def _datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        self.bytes_received += len(data)
        self._on_bytes(data, addr)

    def send(self, data: bytes) -> None:
        if self._transport is not None:
            self._transport.sendto(data)
            self.bytes_sent += len(data)

    async def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    @property
    def url_for_client(self) -> str:
        return f"udpin:{self._peer[0]}:{self._peer[1]}"

    @property
    def peer_count(self) -> int:
        return 1


class TcpServerTransport(ServerTransport):
    """TCP server: every connected client gets everything sent; each client's bytes carry its own key."""

    def __init__(self, host: str, port: int, on_bytes: OnBytes) -> None:
        super().__init__(on_bytes)
        self._host, self._port = host, port
        self._server: asyncio.Server | None = None
        self._writers: dict[int, asyncio.StreamWriter] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._next_id = 0

    async def start(self) -> None:
        try:
            self._server = await asyncio.start_server(self._client, self._host, self._port)
        except OSError as exc:
            raise LinkError(f"cannot listen on tcp {self._host}:{self._port}: {exc}") from exc
        self._port = int(self._server.sockets[0].getsockname()[1])

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        key = self._next_id
        self._next_id += 1
        self._writers[key] = writer
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)  # type: ignore[arg-type]
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                self.bytes_received += len(data)
                self._on_bytes(data, key)
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            # close() cancels and awaits this handler; ending it quietly keeps Python 3.11's
            # start_server from logging the cancelled handler as an "Exception in callback".
            pass
        finally:
            self._writers.pop(key, None)
            if task is not None:
                self._tasks.discard(task)  # type: ignore[arg-type]
            writer.close()
            with contextlib.suppress(ConnectionError, OSError):
                await writer.wait_closed()

    def send(self, data: bytes) -> None:
        for writer in list(self._writers.values()):
            if writer.is_closing() or writer.transport.get_write_buffer_size() > _MAX_TCP_BUFFER_BYTES:
                continue  # a client that does not read loses data rather than growing our memory
            writer.write(data)
            self.bytes_sent += len(data)

    def drop_clients(self) -> None:
        """Close every client connection (they may reconnect)."""
        for writer in list(self._writers.values()):
            writer.close()

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self.drop_clients()
            for task in list(self._tasks):
                task.cancel()
            for task in list(self._tasks):
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            await self._server.wait_closed()
            self._server = None

    @property
    def port(self) -> int:
        return self._port

    @property
    def url_for_client(self) -> str:
        return f"tcp:{_reachable_host(self._host)}:{self._port}"

    @property
    def peer_count(self) -> int:
        return len(self._writers)


def _reachable_host(bind_host: str) -> str:
    """The address a local client dials for a server bound to `bind_host` (wildcard -> loopback)."""
    return "127.0.0.1" if bind_host in ("0.0.0.0", "") else bind_host


def open_transport(url: str, on_bytes: OnBytes) -> ServerTransport:
    """The transport for a listen URL (not started yet)."""
    parsed = parse_listen_url(url)
    if parsed.scheme == "udpin":
        return UdpServerTransport(parsed.host, parsed.port, on_bytes)
    if parsed.scheme == "udpout":
        return UdpClientTransport(parsed.host, parsed.port, on_bytes)
    return TcpServerTransport(parsed.host, parsed.port, on_bytes)
