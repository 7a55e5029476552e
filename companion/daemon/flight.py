"""The flight folder: one directory per daemon run.

Contents::

    log.jsonl        structured log, one JSON object per line (``t_s`` = daemon clock, ``event``, fields)
    flight.tlog      MAVLink traffic (written by the link when it supports it)
    trajectory.tum   fused estimate in TUM format: ``stamp x y z qx qy qz qw`` (NED, body FRD), what evo reads
    photos/          ``<name>.png`` + ``<name>.json`` sidecar per photo

All writers here are small, synchronous and called from the daemon's event
loop; they flush on `flush()` (health summary) and on `close()`.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from companion.checks import FloatArray, check_transform
from companion.geometry import frames

__all__ = ["FlightFolder", "JsonlLog", "TumWriter", "read_tum", "to_jsonable"]

_logger = logging.getLogger("companion.daemon")


def to_jsonable(value: Any) -> Any:
    """Recursively convert numpy arrays/scalars, paths and dataclass-like objects into JSON types."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, Path):
        return str(value)
    return str(value)


class JsonlLog:
    """Structured log: one JSON object per line, mirrored to Python `logging`."""

    def __init__(self, path: Path | None, clock_now: Any) -> None:
        self._now = clock_now
        self._fh: TextIO | None = path.open("a", encoding="utf-8") if path is not None else None
        self.path = path

    def event(self, event: str, level: int = logging.INFO, **fields: Any) -> None:
        """Append one record ``{"t_s", "wall", "event", **fields}`` and mirror it to the Python logger."""
        record = {
            "t_s": round(float(self._now()), 6),
            "wall": _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds"),
            "event": event,
            **to_jsonable(fields),
        }
        if self._fh is not None:
            self._fh.write(json.dumps(record, separators=(",", ":")) + "\n")
        if _logger.isEnabledFor(level):
            text = " ".join(f"{k}={v}" for k, v in fields.items())
            _logger.log(level, "%s %s", event, text)

    def flush(self) -> None:
        if self._fh is not None:
            self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.flush()
            self._fh.close()
            self._fh = None


class TumWriter:
    """Trajectory in TUM format: ``stamp_s x y z qx qy qz qw`` per line (T_ned_body)."""

    def __init__(self, path: Path | None) -> None:
        self._fh: TextIO | None = path.open("a", encoding="utf-8") if path is not None else None
        self.path = path
        self.count = 0

    def write(self, stamp_s: float, T_ned_body: Any) -> None:
        T = check_transform(T_ned_body, "T_ned_body")
        q_wxyz = frames.quaternion_wxyz_from_rotation(T[:3, :3])
        x, y, z = (float(v) for v in T[:3, 3])
        w, qx, qy, qz = (float(v) for v in q_wxyz)
        if self._fh is not None:
            self._fh.write(f"{stamp_s:.6f} {x:.6f} {y:.6f} {z:.6f} {qx:.8f} {qy:.8f} {qz:.8f} {w:.8f}\n")
        self.count += 1

    def flush(self) -> None:
        if self._fh is not None:
            self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.flush()
            self._fh.close()
            self._fh = None


def read_tum(path: Path) -> tuple[FloatArray, FloatArray]:
    """Read a TUM file: returns ``stamps_s (N,)`` and ``T_ned_body (N, 4, 4)``."""
    rows = [line.split() for line in path.read_text(encoding="utf-8").splitlines() if line and line[0] != "#"]
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)
    q_wxyz = np.concatenate([data[:, 7:8], data[:, 4:7]], axis=1)
    T = np.tile(np.eye(4), (data.shape[0], 1, 1))
    if data.shape[0]:
        T[:, :3, :3] = frames.rotation_from_quaternion_wxyz(q_wxyz)
        T[:, :3, 3] = data[:, 1:4]
    return data[:, 0], T


class FlightFolder:
    """Creates and owns the files of one run's flight folder."""

    def __init__(self, path: Path, clock_now: Any, photo_root: Path | None = None) -> None:
        self.path = path
        self.path.mkdir(parents=True, exist_ok=True)
        # photos go to ``photo_root/<flight name>/`` (the config's mission.photo_folder) when given, else into
        # the flight folder; created at the first photo
        self.photos = (photo_root / path.name) if photo_root is not None else self.path / "photos"
        self.log = JsonlLog(self.path / "log.jsonl", clock_now)
        self.tum = TumWriter(self.path / "trajectory.tum")
        self.tlog_path = self.path / "flight.tlog"
        self._photo_count = 0
        self._frames_fh: TextIO | None = None

    @classmethod
    def create(cls, root: Path, clock_now: Any, name: str | None = None,
               photo_root: Path | None = None) -> FlightFolder:
        """A new folder under `root` named by UTC wall time (``flight-YYYYmmdd-HHMMSS[-n]``) or `name`."""
        root.mkdir(parents=True, exist_ok=True)
        base = name or "flight-" + _dt.datetime.now(_dt.UTC).strftime("%Y%m%d-%H%M%S")
        path = root / base
        n = 1
        while path.exists():
            n += 1
            path = root / f"{base}-{n}"
        return cls(path, clock_now, photo_root)

    def save_photo(self, image: Any, sidecar: dict[str, Any]) -> Path:
        """Write ``photo-NNNN.png`` (gray or BGR as the camera delivers it, full resolution) and its JSON
        sidecar into the photo folder; returns the image path."""
        import cv2  # local: keeps the module importable for tools that never save photos

        self.photos.mkdir(parents=True, exist_ok=True)
        self._photo_count += 1
        stem = f"photo-{self._photo_count:04d}"
        img_path = self.photos / f"{stem}.png"
        if not cv2.imwrite(str(img_path), np.ascontiguousarray(image)):
            raise OSError(f"could not write {img_path}")
        (self.photos / f"{stem}.json").write_text(
            json.dumps(to_jsonable({"image": img_path.name, **sidecar}), indent=2), encoding="utf-8"
        )
        return img_path

    def save_frame(self, image: Any, seq: int, stamp_s: float) -> Path:
        """Record one camera frame as ``frames/NNNNNNNN.png`` and its stamp in ``frames/timestamps.txt``."""
        import cv2

        folder = self.path / "frames"
        if self._frames_fh is None:
            folder.mkdir(exist_ok=True)
            self._frames_fh = (folder / "timestamps.txt").open("a", encoding="utf-8")
        name = f"{seq:08d}.png"
        if not cv2.imwrite(str(folder / name), np.ascontiguousarray(image)):
            raise OSError(f"could not write {folder / name}")
        self._frames_fh.write(f"{name} {stamp_s:.6f}\n")
        return folder / name

    def flush(self) -> None:
        self.log.flush()
        self.tum.flush()
        if self._frames_fh is not None:
            self._frames_fh.flush()

    def close(self) -> None:
        self.log.close()
        self.tum.close()
        if self._frames_fh is not None:
            self._frames_fh.close()
            self._frames_fh = None
