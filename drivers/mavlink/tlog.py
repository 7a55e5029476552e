"""``.tlog`` writer: each record is an 8-byte big-endian unix time in microseconds followed by
one raw MAVLink frame, exactly as MAVProxy writes them (MAVExplorer and mavlogdump read it)."""

from __future__ import annotations

import contextlib
import logging
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

__all__ = ["TlogWriter", "read_tlog"]

_STAMP = struct.Struct(">Q")
log = logging.getLogger(__name__)


class TlogWriter:
    """Appends frames to a tlog file. ``wall_time_s`` gives the unix time (default `time.time`).

    The log is a by-product of the flight: a write error (disk full, card pulled) is logged once,
    stops the log (``failed`` is set, ``error`` names it) and is never raised into the link.
    """

    def __init__(self, path: str | Path, wall_time_s: Callable[[], float] = time.time) -> None:
        self.path = Path(path)
        self._wall_time_s = wall_time_s
        self._file: BinaryIO | None = open(self.path, "ab")  # noqa: SIM115 -- closed in close()
        self.records = 0
        self.error: OSError | None = None

    @property
    def failed(self) -> bool:
        """True once a write failed (the log stopped there)."""
        return self.error is not None

    def write(self, frame: bytes) -> None:
        """Record one complete frame stamped with the current wall time (no-op after a failure)."""
        if self._file is None:
            return
        try:
            self._file.write(_STAMP.pack(max(0, int(self._wall_time_s() * 1e6))) + frame)
        except OSError as exc:
            self._fail(exc)
            return
        self.records += 1

    def _fail(self, exc: OSError) -> None:
        self.error = exc
        log.error("tlog %s: write failed, logging stopped: %s", self.path, exc)
        file, self._file = self._file, None
        if file is not None:
            with contextlib.suppress(OSError):
                file.close()

    def flush(self) -> None:
        if self._file is not None:
            try:
                self._file.flush()
            except OSError as exc:
                self._fail(exc)

    def close(self) -> None:
        file, self._file = self._file, None
        if file is not None:
            try:
                file.close()
            except OSError as exc:  # the buffered tail could not be written
                self.error = self.error or exc
                log.error("tlog %s: closing failed: %s", self.path, exc)


def read_tlog(path: str | Path) -> list[tuple[int, bytes]]:
    """(usec, frame) records of a tlog written with MAVLink 2 / 1 frames (for tests and tools)."""
    data = Path(path).read_bytes()
    out: list[tuple[int, bytes]] = []
    i = 0
    while i + 8 + 3 <= len(data):
        (usec,) = _STAMP.unpack_from(data, i)
        j = i + 8
        marker, payload_len = data[j], data[j + 1]
        if marker == 0xFD:
            signed = data[j + 2] & 0x01
            n = 10 + payload_len + 2 + (13 if signed else 0)
        elif marker == 0xFE:
            n = 6 + payload_len + 2
        else:
            raise ValueError(f"tlog {path}: no MAVLink frame at byte {j}")
        out.append((usec, data[j : j + n]))
        i = j + n
    return out
