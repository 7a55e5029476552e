"""Connection URLs of the MAVLink link.

Accepted forms (an optional ``//`` after the scheme is ignored):

- ``serial:/dev/ttyAMA0:921600`` -- a serial port and its baud rate
- ``udpin:HOST:PORT``  -- bind HOST:PORT and answer whoever sent the last datagram
- ``udpout:HOST:PORT`` -- send to HOST:PORT (from an ephemeral local port)
- ``tcp:HOST:PORT``    -- TCP client (``tcpout:`` is accepted as an alias)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from companion.errors import ConfigError

__all__ = ["Endpoint", "EndpointKind", "parse_url"]

EndpointKind = Literal["serial", "udpin", "udpout", "tcp"]

_ALIASES: dict[str, EndpointKind] = {
    "serial": "serial",
    "udpin": "udpin",
    "udpout": "udpout",
    "tcp": "tcp",
    "tcpout": "tcp",
}


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection URL: network endpoints use host/port, serial ones device/baud."""

    kind: EndpointKind
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    @property
    def url(self) -> str:
        """The canonical URL of this endpoint."""
        if self.kind == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind}:{self.host}:{self.port}"


def _parse_int(text: str, what: str, url: str, low: int, high: int) -> int:
    try:
        value = int(text, 10)
    except ValueError:
        raise ConfigError(f"link url {url!r}: {what} {text!r} is not an integer") from None
    if not low <= value <= high:
        raise ConfigError(f"link url {url!r}: {what} {value} outside [{low}, {high}]")
    return value


def parse_url(url: str) -> Endpoint:
    """Parse a link URL; raises `ConfigError` naming the problem."""
    if not isinstance(url, str) or ":" not in url:
        raise ConfigError(f"link url {url!r}: expected SCHEME:..., e.g. udpin:0.0.0.0:14550")
    scheme, rest = url.split(":", 1)
    kind = _ALIASES.get(scheme.strip().lower())
    if kind is None:
        raise ConfigError(f"link url {url!r}: unknown scheme {scheme!r} (serial, udpin, udpout, tcp)")
    if rest.startswith("//"):
        rest = rest[2:]
    if ":" not in rest:
        raise ConfigError(f"link url {url!r}: missing ':' before the {'baud rate' if kind == 'serial' else 'port'}")
    head, tail = rest.rsplit(":", 1)
    if kind == "serial":
        if not head:
            raise ConfigError(f"link url {url!r}: empty serial device")
        return Endpoint(kind=kind, device=head, baud=_parse_int(tail, "baud rate", url, 50, 20_000_000))
    host = head[1:-1] if head.startswith("[") and head.endswith("]") else head
    if not host:
        raise ConfigError(f"link url {url!r}: empty host")
    low_port = 0 if kind == "udpin" else 1
    return Endpoint(kind=kind, host=host, port=_parse_int(tail, "port", url, low_port, 65535))
