"""A folder of images played as a camera (sorted by name, optional `timestamps.txt`).

Image files (png, jpg, jpeg, bmp, tif, tiff, pgm, ppm) are sorted in natural
order (`frame2.png` before `frame10.png`). If the folder has `timestamps.txt`,
its lines give each frame's recorded time in seconds, either one number per
line (in sorted file order) or `FILENAME STAMP` per line; `#` starts a comment.
Realtime pacing replays those intervals on the injected clock (or 1/fps
without a timestamps file); `pacing="consumer"` delivers every frame as fast as
it is taken (replay). `Frame.source_stamp_s` is the recorded time.
"""

from __future__ import annotations

import itertools
import os
import re
from pathlib import Path

import cv2

from companion.clock import Clock
from companion.errors import CameraError
from drivers.camera.base import CameraSource, Capture, EndOfStream

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"})
TIMESTAMPS_FILE = "timestamps.txt"


def natural_key(name: str) -> list[int | str]:
    """Sort key that orders embedded numbers numerically."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    """The image files of `folder`, natural-sorted by name."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_timestamps(path: Path, files: list[Path]) -> list[float]:
    """Recorded stamps (s) for `files` from a timestamps file; `CameraError` names the bad line."""
    by_name: dict[str, float] = {}
    in_order: list[float] = []
    for number, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        try:
            if len(parts) == 1:
                in_order.append(float(parts[0]))
            elif len(parts) == 2:
                by_name[parts[0]] = float(parts[1])
            else:
                raise ValueError
        except ValueError:
            raise CameraError(f"{path}:{number}: expected STAMP or FILENAME STAMP, got {raw!r}") from None
    if by_name and in_order:
        raise CameraError(f"{path}: mixes STAMP and FILENAME STAMP lines")
    if by_name:
        missing = [f.name for f in files if f.name not in by_name]
        if missing:
            raise CameraError(f"{path}: no stamp for {missing[0]}")
        stamps = [by_name[f.name] for f in files]
    else:
        if len(in_order) != len(files):
            raise CameraError(f"{path}: {len(in_order)} stamps for {len(files)} images")
        stamps = in_order
    if any(b < a for a, b in itertools.pairwise(stamps)):
        raise CameraError(f"{path}: stamps must not decrease in file order")
    return stamps


class ImageFolderCamera(CameraSource):
    """Images of a folder as a camera source (see the module docstring)."""

    def __init__(
        self,
        clock: Clock,
        folder: str | os.PathLike[str],
        *,
        fps: float = 30.0,
        pacing: str = "realtime",
        loop: bool = False,
        color: str = "gray",
        lost_after_s: float = 0.5,
        reopen_backoff_s: float = 0.2,
        reopen_backoff_max_s: float = 5.0,
    ) -> None:
        if pacing not in ("realtime", "consumer"):
            raise CameraError(f'pacing: must be "realtime" or "consumer", got {pacing!r}')
        if fps <= 0:
            raise CameraError(f"fps: must be > 0, got {fps}")
        super().__init__(
            clock,
            name=f"folder:{Path(folder).name}",
            color=color,
            lost_after_s=lost_after_s,
            reopen_backoff_s=reopen_backoff_s,
            reopen_backoff_max_s=reopen_backoff_max_s,
            drop_stale=pacing == "realtime",
        )
        self._folder = Path(folder)
        self._fps = float(fps)
        self._realtime = pacing == "realtime"
        self._loop_files = loop
        self._imread_flag = cv2.IMREAD_GRAYSCALE if color == "gray" else cv2.IMREAD_COLOR
        self._files: list[Path] = []
        self._stamps: list[float] | None = None
        self._index = 0  # next file
        self._played = 0  # frames played (over loops)
        self._cycle_offset_s = 0.0
        self._origin_s: float | None = None

    @property
    def files(self) -> list[Path]:
        """The image files in play order (after entering)."""
        return list(self._files)

    async def _check_available(self) -> None:
        if not self._folder.is_dir():
            raise CameraError(f"{self._folder}: no such image folder")
        files = list_images(self._folder)
        if not files:
            raise CameraError(f"{self._folder}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        stamps_path = self._folder / TIMESTAMPS_FILE
        self._stamps = read_timestamps(stamps_path, files) if stamps_path.is_file() else None
        self._files = files

    def _open(self) -> None:
        if not self._folder.is_dir():
            raise CameraError(f"{self._folder}: folder vanished")

    def _offset_s(self, index: int) -> float:
        """Play time of file `index` in the current cycle, relative to the first file (s)."""
        if self._stamps is not None:
            return self._stamps[index] - self._stamps[0]
        return index / self._fps

    def _read(self) -> Capture | None:
        if self._index >= len(self._files):
            if not self._loop_files:
                raise EndOfStream
            self._cycle_offset_s += self._offset_s(len(self._files) - 1) + 1.0 / self._fps
            self._index = 0
        index = self._index
        self._index += 1  # a bad file is skipped after the reopen
        if self._realtime:
            if self._origin_s is None:
                self._origin_s = self._clock.now()
            self._pace(self._origin_s + self._cycle_offset_s + self._offset_s(index))
        path = self._files[index]
        image = cv2.imread(str(path), self._imread_flag)
        if image is None:
            raise CameraError(f"{path}: cannot read image")
        self._played += 1
        source_stamp_s = self._stamps[index] if self._stamps is not None else None
        return Capture(image, source_stamp_s=source_stamp_s)
