"""A tiny sd_notify: tells systemd the daemon is ready, alive (watchdog), busy with what, stopping.

Messages go as one datagram to the unix socket named by `$NOTIFY_SOCKET`
(a path, or an abstract name starting with "@"). Without that variable (not
started by systemd with Type=notify) every call is a no-op. `WATCHDOG_USEC`
(and `WATCHDOG_PID`, if set, must be this process) gives the watchdog period;
ping at half of it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections.abc import Mapping

_log = logging.getLogger(__name__)


class SdNotifier:
    """Sends sd_notify messages; a no-op outside systemd."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        environ = os.environ if env is None else env
        address = environ.get("NOTIFY_SOCKET", "")
        self._address: str | bytes | None = None
        if address.startswith("@"):
            self._address = b"\0" + address[1:].encode()
        elif address.startswith("/"):
            self._address = address
        self._socket: socket.socket | None = None
        self.watchdog_interval_s: float | None = None
        usec = environ.get("WATCHDOG_USEC", "")
        pid = environ.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_interval_s = int(usec) / 1e6

    @property
    def enabled(self) -> bool:
        """True when started by systemd with a notify socket."""
        return self._address is not None

    def notify(self, message: str) -> bool:
        """Send `message` ("KEY=VALUE" lines); returns whether it was sent. Never raises."""
        if self._address is None:
            return False
        try:
            if self._socket is None:
                # non-blocking: a full notify queue (systemd busy) drops a message instead of stalling the
                # daemon's event loop, which runs the flight
                self._socket = socket.socket(socket.AF_UNIX,
                                             socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
            self._socket.sendto(message.encode("utf-8"), self._address)
        except BlockingIOError:
            _log.debug("sd_notify queue full: %s dropped", message.split("\n", 1)[0])
            return False
        except OSError as exc:
            _log.warning("sd_notify failed: %s", exc)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        """READY=1 (start-up finished), with an optional STATUS line."""
        return self.notify("READY=1" if status is None else f"READY=1\nSTATUS={status}")

    def watchdog(self) -> bool:
        """WATCHDOG=1: the service is alive (send every watchdog_interval_s / 2)."""
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        """STATUS=...: one line shown by `systemctl status`."""
        return self.notify("STATUS=" + text.replace("\n", " "))

    def stopping(self) -> bool:
        """STOPPING=1: shutdown started."""
        return self.notify("STOPPING=1")

    def close(self) -> None:
        sock, self._socket = self._socket, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()
