"""Uploaded missions on disk: one `<id>.xml` per mission plus a `<id>.json` metadata sidecar.

Files are written atomically (temporary file + rename), so a reader never sees
half a mission. Mission ids are derived from the uploaded file name: its stem,
with every character outside `[A-Za-z0-9._-]` replaced by `-`, at most 64
characters, never starting with a dot.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

_ID_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]{0,63}$")
MAX_ID_CHARS = 64


def mission_id_from_name(name: str) -> str:
    """The mission id for an uploaded file name ("Rack survey #2.xml" -> "Rack-survey--2")."""
    stem = Path(name.replace("\\", "/")).name
    if stem.lower().endswith(".xml"):
        stem = stem[:-4]
    cleaned = re.sub(r"[^A-Za-z0-9._-]", "-", stem).lstrip(".")[:MAX_ID_CHARS]
    return cleaned or "mission"


def is_valid_id(mission_id: str) -> bool:
    """True for ids `mission_id_from_name` can produce (safe as file names)."""
    return bool(_ID_RE.match(mission_id))


class MissionStore:
    """A folder of validated mission files."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)

    def ensure(self) -> None:
        """Create the folder (mode 0750) if needed."""
        self.folder.mkdir(parents=True, exist_ok=True, mode=0o750)

    def path(self, mission_id: str) -> Path:
        """The XML file of a stored mission; `KeyError` if there is none."""
        if not is_valid_id(mission_id):
            raise KeyError(mission_id)
        path = self.folder / f"{mission_id}.xml"
        if not path.is_file():
            raise KeyError(mission_id)
        return path

    def __contains__(self, mission_id: object) -> bool:
        if not isinstance(mission_id, str):
            return False
        try:
            self.path(mission_id)
        except KeyError:
            return False
        return True

    def _write_atomic(self, path: Path, data: bytes) -> None:
        fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".upload-", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    def put(self, mission_id: str, data: bytes, metadata: dict[str, Any]) -> dict[str, Any]:
        """Store `data` under `mission_id` (replacing one with the same id); returns the full metadata."""
        if not is_valid_id(mission_id):
            raise KeyError(mission_id)
        self.ensure()
        info = dict(metadata)
        info.update(
            id=mission_id,
            size_bytes=len(data),
            sha256=hashlib.sha256(data).hexdigest(),
            uploaded_utc=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        )
        self._write_atomic(self.folder / f"{mission_id}.xml", data)
        self._write_atomic(self.folder / f"{mission_id}.json", json.dumps(info, indent=1).encode())
        return info

    def info(self, mission_id: str) -> dict[str, Any]:
        """Metadata of a stored mission (from its sidecar, or the file alone); `KeyError` if missing."""
        path = self.path(mission_id)
        sidecar = path.with_suffix(".json")
        info: dict[str, Any] = {}
        with contextlib.suppress(OSError, ValueError):
            loaded = json.loads(sidecar.read_text(encoding="utf-8"))
            if isinstance(loaded, dict):
                info = loaded
        stat = path.stat()
        info.setdefault("name", "")
        info.setdefault("actions", None)
        info.setdefault("size_bytes", stat.st_size)
        info.setdefault(
            "uploaded_utc",
            datetime.datetime.fromtimestamp(stat.st_mtime, datetime.UTC).isoformat(timespec="seconds"),
        )
        info["id"] = mission_id
        return info

    def list(self) -> list[dict[str, Any]]:
        """Metadata of every stored mission, sorted by id."""
        if not self.folder.is_dir():
            return []
        ids = sorted(p.stem for p in self.folder.glob("*.xml") if is_valid_id(p.stem))
        out = []
        for mission_id in ids:
            with contextlib.suppress(KeyError, OSError):
                out.append(self.info(mission_id))
        return out

    def delete(self, mission_id: str) -> None:
        """Remove a stored mission; `KeyError` if missing."""
        path = self.path(mission_id)
        path.unlink()
        with contextlib.suppress(OSError):
            path.with_suffix(".json").unlink()
