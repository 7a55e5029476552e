"""The synthetic camera's renderer for the daemon: the rack scene seen from a body pose in NED.

`SceneRenderer(T_ned_rack, T_body_cam, camera, model)` is a callable
``render(T_ned_body) -> (H, W) uint8`` for `drivers.camera.SyntheticCamera`:
it converts the body pose to the camera pose in the rack frame and renders
`companion.sim.rack_scene.RackScene` (the rack over textured ground) with a
little sensor noise. Fault injection for the simulator wraps it (`FaultyRender`):
``camera-unplug`` raises `CameraError` (the driver treats it as a vanished
device), ``vision-loss`` returns a featureless frame (the camera works, the
trackers see nothing).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import CameraError, InputError
from companion.geometry import frames

__all__ = ["APPEARANCES", "FaultyRender", "SceneRenderer", "paper_rack_model"]

APPEARANCES = ("default", "field")  # RackScene, FieldRackScene


def paper_rack_model() -> Any:
    """The packaged 5-pipe rack (``racks/sweep_5pipe.toml``, the rack declared in the example sweep mission)."""
    from companion.data import data_path
    from companion.vision.rack import RackModel

    return RackModel.load(data_path("racks/sweep_5pipe.toml"))


class SceneRenderer:
    """``render(T_ned_body) -> image``: the rack scene from the camera mounted on the body."""

    def __init__(
        self,
        T_ned_rack: Any,
        T_body_cam: Any,
        camera: PinholeCamera,
        model: Any | None = None,
        seed: int = 0,
        noise_std: float = 2.0,
        appearance: str = "default",
    ) -> None:
        from companion.sim.rack_scene import RackScene
        from companion.sim.rack_scene_field import FieldRackScene

        if appearance not in APPEARANCES:
            raise InputError(f"appearance: expected one of {APPEARANCES}, got {appearance!r}")
        self.T_ned_rack = check_transform(T_ned_rack, "T_ned_rack")
        self.T_body_cam = check_transform(T_body_cam, "T_body_cam")
        self.camera = camera
        self.model = model if model is not None else paper_rack_model()
        # "field": the harsher appearance of issue #14 (sparse spots, high-contrast ground, shadows, JPEG).
        self.scene: Any = (FieldRackScene(self.model, seed=seed) if appearance == "field"
                           else RackScene(self.model, seed=seed))
        self.noise_std = float(noise_std)
        self._rng = np.random.default_rng(seed + 1)
        self._lock = threading.Lock()

    @classmethod
    def from_config(
        cls, config: Any, camera: PinholeCamera, seed: int = 0, appearance: str = "default"
    ) -> SceneRenderer:
        """From a `CompanionConfig`: rack model file (or the packaged one), `T_ned_rack`, `T_body_cam`."""
        model = None
        if config.rack.model:
            from companion.vision.rack import RackModel

            model = RackModel.load(config.rack.model)
        return cls(config.rack.T_ned_rack, config.mount.T_body_cam, camera, model=model, seed=seed,
                   appearance=appearance)

    def T_rack_cam(self, T_ned_body: Any) -> FloatArray:
        return frames.T_rack_cam_from_T_ned_body(T_ned_body, self.T_ned_rack, self.T_body_cam)

    def __call__(self, T_ned_body: Any) -> Any:
        with self._lock:
            return self.scene.render(self.T_rack_cam(T_ned_body), self.camera, noise_std=self.noise_std,
                                     rng=self._rng)


class FaultyRender:
    """Wraps a renderer with time-windowed faults and records when each frame finished rendering.

    `windows`: list of (kind, start_s, end_s) on `now()`'s time base; kind "camera-unplug" raises
    `CameraError`, "vision-loss" returns a flat grey image. `done_perf_s[k]` is the
    `time.perf_counter()` at which the k-th successful render finished (the frame with ``seq == k``).
    """

    def __init__(self, render: Callable[[Any], Any], now: Callable[[], float],
                 windows: list[tuple[str, float, float]] | None = None) -> None:
        self.render = render
        self.now = now
        self.windows = list(windows or [])
        self.done_perf_s: list[float] = []
        self.done_clock_s: list[float] = []
        self.failed = 0

    def active(self, kind: str, t: float | None = None) -> bool:
        t = self.now() if t is None else t
        return any(k == kind and start <= t < end for k, start, end in self.windows)

    def __call__(self, T_ned_body: Any) -> Any:
        t = self.now()
        if self.active("camera-unplug", t):
            self.failed += 1
            raise CameraError("simulated camera unplugged")
        image = self.render(T_ned_body)
        if self.active("vision-loss", t):
            image = np.full_like(np.asarray(image), 128)
        self.done_perf_s.append(time.perf_counter())
        self.done_clock_s.append(self.now())
        return image
