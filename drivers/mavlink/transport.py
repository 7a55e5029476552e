"""Byte transports for the link: UDP (in/out), TCP client, serial -- all non-blocking on asyncio.

A transport delivers received bytes through ``on_bytes`` (called from the event loop) and
reports a dead connection through ``on_lost``; ``write`` never blocks (it returns False when
there is nobody to send to). Reconnecting is the link's job: it closes and re-opens.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable
from typing import Any

from companion.errors import LinkError
from drivers.mavlink.url import Endpoint

__all__ = ["SerialTransport", "TcpTransport", "Transport", "UdpTransport", "make_transport"]

OnBytes = Callable[[bytes], None]
OnLost = Callable[[BaseException | None], None]


class Transport:
    """Base class: one endpoint, opened and closed by the link. ``datagram``: reads are whole datagrams."""

    datagram = False

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.bytes_out = 0
        self.write_errors = 0
        self._on_bytes: OnBytes = lambda data: None
        self._on_lost: OnLost = lambda exc: None

    @property
    def is_open(self) -> bool:
        raise NotImplementedError

    @property
    def local_address(self) -> tuple[str, int] | None:
        return None

    async def open(self, on_bytes: OnBytes, on_lost: OnLost) -> None:
        raise NotImplementedError

    def write(self, data: bytes) -> bool:
        raise NotImplementedError

    def accept_last_source(self) -> None:
        """The bytes just delivered held a valid frame (only udpin cares: it replies to that sender)."""

    async def close(self) -> None:
        raise NotImplementedError


class _UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpTransport) -> None:
        self._owner = owner

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self._owner._received(data, addr)

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable on udpout while the peer is down: not fatal, keep sending.
        self._owner.write_errors += 1

    def connection_lost(self, exc: Exception | None) -> None:
        self._owner._lost(exc)


class UdpTransport(Transport):
    """``udpout`` sends to host:port; ``udpin`` binds host:port and answers the last sender."""

    datagram = True

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._transport: asyncio.DatagramTransport | None = None
        self._peer: Any = None
        self._last_source: Any = None
        self._bound_port: int | None = None
        self._closing = False

    @property
    def is_open(self) -> bool:
        return self._transport is not None and not self._transport.is_closing()

    @property
    def local_address(self) -> tuple[str, int] | None:
        if self._transport is None:
            return None
        sockname = self._transport.get_extra_info("sockname")
        return None if sockname is None else (str(sockname[0]), int(sockname[1]))

    @property
    def peer(self) -> Any:
        """Where udpin replies go (the last sender), None before anyone spoke."""
        return self._peer

    async def open(self, on_bytes: OnBytes, on_lost: OnLost) -> None:
        self._on_bytes, self._on_lost = on_bytes, on_lost
        self._closing = False
        loop = asyncio.get_running_loop()
        ep = self.endpoint
        if ep.kind == "udpout":
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _UdpProtocol(self), remote_addr=(ep.host, ep.port)
            )
            self._peer = (ep.host, ep.port)
        else:
            port = self._bound_port if self._bound_port is not None else ep.port
            transport, _ = await loop.create_datagram_endpoint(lambda: _UdpProtocol(self), local_addr=(ep.host, port))
            self._peer = None
        self._transport = transport
        if ep.kind == "udpin":
            addr = self.local_address
            self._bound_port = None if addr is None else addr[1]

    def _received(self, data: bytes, addr: Any) -> None:
        self._last_source = addr
        self._on_bytes(data)

    def accept_last_source(self) -> None:
        """udpin: reply to the sender of the datagram just delivered (call it once that held a valid frame,
        so a source of noise cannot steal the link)."""
        if self.endpoint.kind == "udpin" and self._last_source is not None:
            self._peer = self._last_source

    def _lost(self, exc: BaseException | None) -> None:
        if not self._closing:
            self._on_lost(exc)

    def write(self, data: bytes) -> bool:
        t = self._transport
        if t is None or t.is_closing():
            return False
        try:
            if self.endpoint.kind == "udpout":
                t.sendto(data)
            elif self._peer is None:
                return False
            else:
                t.sendto(data, self._peer)
        except OSError:
            self.write_errors += 1
            return False
        self.bytes_out += len(data)
        return True

    async def close(self) -> None:
        self._closing = True
        if self._transport is not None:
            self._transport.close()
            self._transport = None


class TcpTransport(Transport):
    """TCP client; a closed or reset connection is reported through ``on_lost``."""

    MAX_BUFFERED_BYTES = 1 << 20

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._writer: asyncio.StreamWriter | None = None
        self._reader_task: asyncio.Task[None] | None = None

    @property
    def is_open(self) -> bool:
        return self._writer is not None and not self._writer.is_closing()

    @property
    def local_address(self) -> tuple[str, int] | None:
        if self._writer is None:
            return None
        sockname = self._writer.get_extra_info("sockname")
        return None if sockname is None else (str(sockname[0]), int(sockname[1]))

    async def open(self, on_bytes: OnBytes, on_lost: OnLost) -> None:
        self._on_bytes, self._on_lost = on_bytes, on_lost
        try:
            reader, writer = await asyncio.open_connection(self.endpoint.host, self.endpoint.port)
        except OSError as exc:
            raise LinkError(f"tcp {self.endpoint.host}:{self.endpoint.port}: {exc}") from exc
        self._writer = writer
        self._reader_task = asyncio.create_task(self._read(reader), name="mavlink-tcp-reader")

    async def _read(self, reader: asyncio.StreamReader) -> None:
        exc: BaseException | None = None
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                self._on_bytes(data)
        except asyncio.CancelledError:
            raise
        except OSError as e:
            exc = e
        self._on_lost(exc)

    def write(self, data: bytes) -> bool:
        w = self._writer
        if w is None or w.is_closing():
            return False
        if w.transport.get_write_buffer_size() > self.MAX_BUFFERED_BYTES:
            self.write_errors += 1
            return False
        w.write(data)
        self.bytes_out += len(data)
        return True

    async def close(self) -> None:
        task, self._reader_task = self._reader_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()


class SerialTransport(Transport):
    """Serial port through pyserial (opened in a thread), read and written with the loop's fd watchers."""

    MAX_PENDING_BYTES = 1 << 16

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._serial: Any = None
        self._fd: int | None = None
        self._pending = bytearray()

    @property
    def is_open(self) -> bool:
        return self._fd is not None

    async def open(self, on_bytes: OnBytes, on_lost: OnLost) -> None:
        import serial  # local: only serial links need pyserial

        self._on_bytes, self._on_lost = on_bytes, on_lost
        try:
            ser = await asyncio.to_thread(
                serial.Serial, self.endpoint.device, self.endpoint.baud, timeout=0, write_timeout=0
            )
        except (OSError, serial.SerialException) as exc:
            raise LinkError(f"serial {self.endpoint.device}: {exc}") from exc
        self._serial = ser
        fd = int(ser.fileno())
        os.set_blocking(fd, False)
        self._fd = fd
        asyncio.get_running_loop().add_reader(fd, self._readable)

    def _readable(self) -> None:
        fd = self._fd
        if fd is None:
            return
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(exc)
            return
        if not data:
            self._fail(None)
            return
        self._on_bytes(data)

    def _fail(self, exc: BaseException | None) -> None:
        self._detach()
        self._on_lost(exc)

    def _detach(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            loop = asyncio.get_running_loop()
            loop.remove_reader(fd)
            loop.remove_writer(fd)
        self._pending.clear()

    def _flush(self) -> None:
        fd = self._fd
        if fd is None:
            return
        try:
            n = os.write(fd, self._pending)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(exc)
            return
        del self._pending[:n]
        if not self._pending:
            asyncio.get_running_loop().remove_writer(fd)

    def write(self, data: bytes) -> bool:
        fd = self._fd
        if fd is None:
            return False
        if self._pending:
            if len(self._pending) + len(data) > self.MAX_PENDING_BYTES:
                self.write_errors += 1
                return False
            self._pending += data
            self.bytes_out += len(data)
            return True
        try:
            n = os.write(fd, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self._fail(exc)
            return False
        if n < len(data):
            self._pending += data[n:]
            asyncio.get_running_loop().add_writer(fd, self._flush)
        self.bytes_out += len(data)
        return True

    async def close(self) -> None:
        self._detach()
        ser, self._serial = self._serial, None
        if ser is not None:
            await asyncio.to_thread(ser.close)


def make_transport(endpoint: Endpoint) -> Transport:
    """The transport class for an endpoint kind."""
    if endpoint.kind in ("udpin", "udpout"):
        return UdpTransport(endpoint)
    if endpoint.kind == "tcp":
        return TcpTransport(endpoint)
    return SerialTransport(endpoint)
