"""Camera sources: newest-frame handover, stamping at capture, loss and recovery, pacing, factory."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.clock import ManualClock
from companion.config import CameraConfig
from companion.errors import CameraError
from drivers.camera import (
    CameraState,
    ImageFolderCamera,
    SyntheticCamera,
    V4L2Camera,
    VideoFileCamera,
    load_camera_model,
    open_camera,
)
from tests.drivers.fakes import FakeDevice, RecordingClock, image, wait_event, write_video


def v4l2(clock: Any, device: FakeDevice, **kw: Any) -> V4L2Camera:
    params: dict[str, Any] = {"width": 64, "height": 48, "lost_after_s": 0.5, "reopen_backoff_s": 0.2}
    params.update(kw)
    return V4L2Camera(clock, "/dev/video9", capture_factory=device.factory, **params)


async def test_newest_frame_wins_and_stale_frames_are_counted() -> None:
    clock = ManualClock(start_s=100.0)
    device = FakeDevice()
    async with v4l2(clock, device) as cam:
        await asyncio.to_thread(device.wait_reads, 1)
        device.feed(image(1))
        await asyncio.to_thread(device.wait_reads, 2)
        await clock.advance(0.01)
        device.feed(image(2), image(3))
        await asyncio.to_thread(device.wait_reads, 4)
        frame = await cam.next_frame(timeout_s=1.0)
        assert frame is not None
        assert frame.seq == 2 and frame.dropped_before == 2
        assert frame.image.shape == (48, 64) and frame.image.dtype == np.uint8  # gray by default
        assert int(frame.image[0, 0]) == 3
        assert frame.stamp_s == pytest.approx(100.01)  # stamped at capture, not at delivery
        stats = cam.stats
        assert (stats.captured, stats.delivered, stats.dropped_stale) == (3, 1, 2)
        await clock.advance(0.02)
        device.feed(image(4))
        frame = await cam.next_frame(timeout_s=1.0)
        assert frame is not None and frame.seq == 3 and frame.dropped_before == 0
        assert frame.stamp_s == pytest.approx(100.03)
        assert cam.healthy and cam.state is CameraState.STREAMING
    assert cam.stats.state is CameraState.CLOSED
    assert device.current.released


async def test_next_frame_times_out_on_the_injected_clock() -> None:
    clock = ManualClock()
    device = FakeDevice()
    async with v4l2(clock, device, lost_after_s=10.0) as cam:
        waiter = asyncio.create_task(cam.next_frame(timeout_s=0.1))
        await clock.advance(0.05)
        assert not waiter.done()
        await clock.advance(0.06)
        assert await asyncio.wait_for(waiter, 5.0) is None


async def test_device_vanishes_then_lost_reopen_with_backoff_and_recovered() -> None:
    clock = RecordingClock()
    device = FakeDevice()
    lost = asyncio.Event()
    recovered = asyncio.Event()
    reasons: list[str] = []
    cam = v4l2(clock, device)

    def on_lost(reason: str) -> None:
        reasons.append(reason)
        lost.set()

    cam.on_lost(on_lost)
    cam.on_recovered(recovered.set)
    async with cam:
        await asyncio.to_thread(device.wait_reads, 1)
        device.feed(image(7))
        assert await cam.next_frame(timeout_s=1.0) is not None
        assert cam.healthy

        device.unplug()  # read fails -> lost, backoff 0.2 s (registered before on_lost returns)
        await wait_event(lost)
        assert cam.stats.lost and not cam.healthy and "read failed" in reasons[0]
        second_backoff = clock.expect_sleep(0.4)
        await clock.advance(0.2)  # reopen attempt fails: still unplugged -> backoff doubles
        await asyncio.wait_for(second_backoff, 5.0)
        assert len(device.opens) == 2 and cam.stats.lost

        device.plugged = True
        await clock.advance(0.4)  # reopen succeeds
        await asyncio.to_thread(device.wait_reads, 3)
        device.feed(image(9))
        await wait_event(recovered)
        frame = await cam.next_frame(timeout_s=1.0)
        assert frame is not None and int(frame.image[0, 0]) == 9
        stats = cam.stats
        assert stats.reopen_count == 1 and stats.lost_count == 1 and stats.read_failures == 2
        assert cam.healthy and len(reasons) == 1


async def test_missing_device_at_start_is_lost_not_an_exception() -> None:
    clock = RecordingClock()
    device = FakeDevice(plugged=False)
    lost = asyncio.Event()
    recovered = asyncio.Event()
    cam = v4l2(clock, device)
    cam.on_lost(lambda reason: lost.set())
    cam.on_recovered(recovered.set)
    async with cam:
        await wait_event(lost)
        assert cam.state is CameraState.LOST and "cannot open" in (cam.stats.last_error or "")
        device.plugged = True
        await clock.advance(0.2)
        await asyncio.to_thread(device.wait_reads, 1)
        device.feed(image(5))
        await wait_event(recovered)
        assert cam.stats.reopen_count == 1


async def test_stalled_stream_is_reported_lost_and_recovers_with_frames() -> None:
    clock = ManualClock()
    device = FakeDevice()
    lost = asyncio.Event()
    recovered = asyncio.Event()
    cam = v4l2(clock, device, lost_after_s=0.4)
    cam.on_lost(lambda reason: lost.set())
    cam.on_recovered(recovered.set)
    async with cam:
        await asyncio.to_thread(device.wait_reads, 1)
        device.feed(image(1))
        assert await cam.next_frame(timeout_s=1.0) is not None
        await clock.advance(0.3)
        assert not lost.is_set()
        await clock.advance(0.3)  # 0.6 s without a frame > 0.4 s
        assert lost.is_set() and cam.stats.lost and "no frame" in (cam.stats.last_error or "")
        device.feed(image(2))
        await wait_event(recovered)
        assert cam.healthy and cam.stats.reopen_count == 0


async def test_v4l2_configures_format_resolution_fps_and_exposure() -> None:
    clock = ManualClock()
    device = FakeDevice()
    config = CameraConfig(kind="v4l2", device="2", width=64, height=48, fps=60.0, pixel_format="YUYV", exposure=50.0)
    async with open_camera(config, clock, capture_factory=device.factory):
        await asyncio.to_thread(device.wait_reads, 1)
        props = device.current.props
    assert device.opens[0] == (2, cv2.CAP_V4L2)
    assert props[cv2.CAP_PROP_FOURCC] == float(cv2.VideoWriter.fourcc(*"YUYV"))
    assert props[cv2.CAP_PROP_FRAME_WIDTH] == 64 and props[cv2.CAP_PROP_FRAME_HEIGHT] == 48
    assert props[cv2.CAP_PROP_FPS] == 60.0
    assert props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1.0 and props[cv2.CAP_PROP_EXPOSURE] == 50.0


async def test_v4l2_wrong_resolution_is_a_failed_open() -> None:
    clock = ManualClock()
    device = FakeDevice()
    device.reported = {cv2.CAP_PROP_FRAME_WIDTH: 640.0, cv2.CAP_PROP_FRAME_HEIGHT: 480.0}
    lost = asyncio.Event()
    cam = v4l2(clock, device)
    cam.on_lost(lambda reason: lost.set())
    async with cam:
        await wait_event(lost)
        assert "640x480" in (cam.stats.last_error or "")
    assert device.opens and device.captures[-1].released


async def test_bgr_output_keeps_color() -> None:
    clock = ManualClock()
    device = FakeDevice()
    async with v4l2(clock, device, color="bgr") as cam:
        await asyncio.to_thread(device.wait_reads, 1)
        device.feed(image(4))
        frame = await cam.next_frame(timeout_s=1.0)
    assert frame is not None and frame.image.shape == (48, 64, 3)


async def test_video_file_consumer_pacing_delivers_every_frame_then_ends(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    write_video(str(path), frames=6)
    clock = ManualClock()
    cam = VideoFileCamera(clock, path, pacing="consumer")
    async with cam:
        frames = [f async for f in cam.frames(timeout_s=5.0)]
        assert cam.ended and cam.state is CameraState.ENDED
    assert [f.seq for f in frames] == list(range(6))
    assert all(f.dropped_before == 0 for f in frames)
    levels = [int(f.image.mean()) for f in frames]
    assert all(abs(level - (20 * k + 10)) <= 3 for k, level in enumerate(levels))
    assert frames[-1].source_stamp_s is not None
    assert cam.stats.dropped_stale == 0


async def test_video_file_realtime_pacing_follows_the_clock(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    write_video(str(path), frames=4, fps=10.0)
    clock = ManualClock(start_s=50.0)
    async with VideoFileCamera(clock, path, pacing="realtime", lost_after_s=5.0) as cam:
        first = await cam.next_frame(timeout_s=1.0)
        assert first is not None and first.stamp_s == pytest.approx(50.0)
        waiter = asyncio.create_task(cam.next_frame())
        await clock.advance(0.05)
        assert not waiter.done()
        await clock.advance_to(50.1 + 1e-9)  # frame 1 is due at 1/fps = 0.1 s
        second = await asyncio.wait_for(waiter, 5.0)
        assert second is not None and second.seq == 1 and second.stamp_s == pytest.approx(50.1)


async def test_missing_video_file_raises() -> None:
    with pytest.raises(CameraError, match="no such video"):
        async with VideoFileCamera(ManualClock(), "/nonexistent/clip.avi"):
            pass


def write_folder(folder: Path, names: list[str], stamps: list[str] | None = None) -> None:
    folder.mkdir()
    for k, name in enumerate(names):
        cv2.imwrite(str(folder / name), np.full((8, 10), 10 * k, dtype=np.uint8))
    (folder / "notes.md").write_text("not an image")
    if stamps is not None:
        (folder / "timestamps.txt").write_text("\n".join(stamps) + "\n")


async def test_image_folder_natural_order_and_timestamps(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    write_folder(folder, ["f10.png", "f2.png", "f1.png"], ["# name stamp", "f1.png 5.0", "f2.png 5.5", "f10.png 6.25"])
    clock = ManualClock()
    async with ImageFolderCamera(clock, folder, pacing="consumer") as cam:
        frames = [f async for f in cam.frames(timeout_s=5.0)]
    assert [p.name for p in cam.files] == ["f1.png", "f2.png", "f10.png"]
    assert [f.source_stamp_s for f in frames] == [5.0, 5.5, 6.25]
    assert [int(f.image[0, 0]) for f in frames] == [20, 10, 0]  # written in the listed order


async def test_image_folder_realtime_replays_recorded_intervals(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    write_folder(folder, ["a.png", "b.png"], ["1.0", "1.5"])
    clock = ManualClock(start_s=0.0)
    async with ImageFolderCamera(clock, folder, lost_after_s=5.0) as cam:
        first = await cam.next_frame(timeout_s=1.0)
        waiter = asyncio.create_task(cam.next_frame())
        await clock.advance(0.4)
        assert not waiter.done()
        await clock.advance_to(0.5 + 1e-9)
        second = await asyncio.wait_for(waiter, 5.0)
        assert first is not None and second is not None
        assert second.stamp_s - first.stamp_s == pytest.approx(0.5)
        assert await cam.next_frame(timeout_s=1.0) is None and cam.ended


async def test_image_folder_rejects_bad_timestamps(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    write_folder(folder, ["a.png", "b.png"], ["1.0"])
    with pytest.raises(CameraError, match="1 stamps for 2 images"):
        async with ImageFolderCamera(ManualClock(), folder):
            pass


def pose_x_render(T_ned_body: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    return np.full((12, 16), round(float(T_ned_body[0, 3]) * 10), dtype=np.uint8)


async def test_synthetic_renders_truth_pose_at_fps_and_goes_lost_without_poses() -> None:
    clock = ManualClock(start_s=10.0)
    truth: dict[str, Any] = {"x_m": 1.0, "available": True}

    def pose_source() -> tuple[float, np.ndarray[Any, Any]] | None:
        if not truth["available"]:
            return None
        T = np.eye(4)
        T[0, 3] = truth["x_m"]
        return clock.now(), T

    lost = asyncio.Event()
    recovered = asyncio.Event()
    cam = SyntheticCamera(clock, pose_x_render, pose_source, fps=20.0, lost_after_s=0.3)
    cam.on_lost(lambda reason: lost.set())
    cam.on_recovered(recovered.set)
    async with cam:
        first = await cam.next_frame(timeout_s=1.0)
        assert first is not None and int(first.image[0, 0]) == 10 and first.stamp_s == pytest.approx(10.0)
        truth["x_m"] = 2.0
        waiter = asyncio.create_task(cam.next_frame())
        await clock.advance(0.05)
        second = await asyncio.wait_for(waiter, 5.0)
        assert second is not None and int(second.image[0, 0]) == 20 and second.stamp_s == pytest.approx(10.05)
        assert second.source_stamp_s == pytest.approx(10.05)

        truth["available"] = False
        await clock.advance(0.5, step_s=0.05)
        assert lost.is_set() and cam.stats.lost
        truth["available"] = True
        await clock.advance(0.05)
        await wait_event(recovered)
        assert cam.healthy


async def test_synthetic_unplug_via_render_error_reopens() -> None:
    clock = RecordingClock(start_s=0.0)
    plugged = {"on": True}

    def render(T_ned_body: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        if not plugged["on"]:
            raise CameraError("unplugged")
        return pose_x_render(T_ned_body)

    lost = asyncio.Event()
    recovered = asyncio.Event()
    cam = SyntheticCamera(clock, render, lambda: (clock.now(), np.eye(4)), fps=10.0, reopen_backoff_s=0.2)
    cam.on_lost(lambda reason: lost.set())
    cam.on_recovered(recovered.set)
    async with cam:
        assert await cam.next_frame(timeout_s=1.0) is not None
        plugged["on"] = False
        await clock.advance(0.1)
        await wait_event(lost)
        assert "unplugged" in (cam.stats.last_error or "")
        plugged["on"] = True
        await clock.advance(0.2)
        await wait_event(recovered)
        assert cam.stats.reopen_count == 1


async def test_synthetic_unexpected_render_error_surfaces_from_next_frame() -> None:
    clock = ManualClock()

    def render(T_ned_body: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        raise ZeroDivisionError("bug")

    async with SyntheticCamera(clock, render, lambda: (clock.now(), np.eye(4))) as cam:
        with pytest.raises(CameraError, match="ZeroDivisionError"):
            await cam.next_frame(timeout_s=1.0)


def test_open_camera_synthetic_requires_render_and_pose_source() -> None:
    with pytest.raises(CameraError, match="render"):
        open_camera(CameraConfig(kind="synthetic"), ManualClock())


def test_load_camera_model_from_yaml_scaled_intrinsics_and_defaults(tmp_path: Path) -> None:
    calibrated = PinholeCamera(
        width=1440, height=960, fx=1260.0, fy=1262.0, cx=720.0, cy=480.0, dist=(0.1, -0.02, 0.0, 0.0)
    )
    calibrated.to_yaml(tmp_path / "cam.yaml")
    same = load_camera_model(CameraConfig(calibration=str(tmp_path / "cam.yaml"), width=1440, height=960))
    assert same.fx == pytest.approx(1260.0) and same.dist is not None
    half = load_camera_model(CameraConfig(calibration=str(tmp_path / "cam.yaml"), width=720, height=480))
    assert half.width == 720 and half.fx == pytest.approx(630.0)
    with pytest.raises(CameraError, match="aspect"):
        load_camera_model(CameraConfig(calibration=str(tmp_path / "cam.yaml"), width=640, height=480))
    inline = load_camera_model(CameraConfig(intrinsics=(500.0, 501.0, 320.0, 240.0), width=640, height=480))
    assert (inline.fx, inline.fy, inline.cx, inline.cy) == (500.0, 501.0, 320.0, 240.0)
    synthetic = load_camera_model(CameraConfig(kind="synthetic"))
    assert (synthetic.width, synthetic.fx, synthetic.cx, synthetic.cy) == (720, 630.0, 360.0, 240.0)
    with pytest.raises(CameraError, match=r"camera\.calibration"):
        load_camera_model(CameraConfig(kind="v4l2"))
    with pytest.raises(CameraError, match=r"camera\.calibration"):
        load_camera_model(CameraConfig(calibration=str(tmp_path / "missing.yaml")))
