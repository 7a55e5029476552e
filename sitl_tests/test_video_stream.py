"""Issue #15: the overlay video the ground station decodes, in real time against the fake autopilot.

The daemon streams H.264 over RTP to a UDP port on loopback; PyAV decodes it from the SDP file the
daemon wrote (as VLC or ffplay would). Checked on the decoded frames: they keep coming, the stamp block
reads back as a recent capture time (CLOCK_MONOTONIC), and the drawn limbs lie on the true camera
pose's projection (the frame rate and the latency are timing: `bench/video_stream.py` measures them).
Then the camera vanishes and comes back, and receivers and page clients leave mid-stream: the stream and
the page keep going.
"""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from companion.geometry import frames
from companion.vision.rack.limbs import sample_limbs
from sitl_tests.video_harness import RtpReceiver, live_rig

pytest.importorskip("av")

# the synthetic camera renders 320x240 at 20 frames/s (cheap enough for a loaded 2-core CI machine);
# the stream is 640x480 (the size), capped at 20 frames/s
CAMERA = {"width": 320, "height": 240, "fps": 20.0}
VIDEO = {"width": 640, "height": 480, "fps": 20.0}


def _green_mask(img: np.ndarray) -> np.ndarray:
    b, g, r = (img[..., k].astype(np.int16) for k in range(3))
    return (g > 150) & (g - r > 80) & (g - b > 80)


def _limb_hits(img: np.ndarray, uv: np.ndarray, radius_px: int = 3) -> float:
    """Fraction of the pixels `uv` (N, 2) with overlay green within `radius_px`."""
    import cv2

    green = cv2.dilate(_green_mask(img).astype(np.uint8), np.ones((2 * radius_px + 1,) * 2, np.uint8)) > 0
    px = np.round(uv).astype(int)
    return float(np.mean(green[px[:, 1], px[:, 0]]))


async def test_rtp_stream_stamps_and_overlay(tmp_path: Path) -> None:
    async with live_rig(tmp_path, width=CAMERA["width"], height=CAMERA["height"], fps=CAMERA["fps"],
                        overrides={"video": VIDEO}) as rig:
        sdp = rig.daemon.video_sdp_path
        assert sdp is not None and "H264/90000" in sdp.read_text()
        rx = RtpReceiver(sdp, keep_images=40)
        await asyncio.to_thread(rx.start)
        t_measure = time.monotonic() + 2.0  # after the receiver's probing and the first key frame
        await asyncio.sleep(8.0)
        rx.stop()
        assert rx.error is None, rx.error
        T_ned_body = rig.ap.truth.T_ned_body  # resting on the deck the whole time
        T_rack_cam = frames.T_rack_cam_from_T_ned_body(T_ned_body, rig.config.rack.T_ned_rack,
                                                       rig.config.mount.T_body_cam)
        stats = rig.daemon.video_streamer.stats()
        frames_done = rig.daemon.counters.frames

    window = [f for f in rx.frames if f.recv_mono_s >= t_measure]
    assert len(window) > 20, f"only {len(window)} frames decoded after the warm-up ({len(rx.frames)} in all)"
    rate = rx.decoded_per_s(t_measure)
    lat = rx.latencies_ms(t_measure)
    print(f"decoded {rate:.1f} frames/s at 640x480, latency median {np.median(lat):.0f} ms "
          f"p90 {np.percentile(lat, 90):.0f} ms; vision frames {frames_done}; {stats}")
    assert lat.size >= 0.9 * len(window), "stamp block unreadable on too many frames"
    # a stamp misread gives an arbitrary time; a correct one is a capture of the last moments (the bound
    # is not a latency target, that figure is the benchmark's)
    assert np.all(lat > 0.0) and np.all(lat < 3000.0), lat

    # the limbs of the model drawn at the estimated pose lie where the true pose projects them
    pipes = rig.daemon.pipeline.rack_tracker.model.pipe_arrays()
    truth = sample_limbs(T_rack_cam, rig.camera_model, pipes, 40, margin_px=6.0)
    uv = truth.uv * np.array([640 / CAMERA["width"], 480 / CAMERA["height"]])
    keep = (uv[:, 1] > 16) & (uv[:, 1] < 480 - 80)  # off the stamp row and the text band
    assert keep.sum() > 50
    imgs = [f.image for f in rx.frames if f.image is not None][-10:]
    assert imgs, "no decoded images kept"
    hits = [_limb_hits(img, uv[keep]) for img in imgs]
    green_share = float(np.mean([_green_mask(img).mean() for img in imgs]))
    print(f"limb samples on overlay green: {np.round(hits, 2)}; green share of the image {green_share:.3f}")
    assert min(hits) >= 0.8
    assert green_share < 0.08  # the hits are not just an image full of green


def _read_mjpeg_parts(sock: socket.socket, parts: int, timeout_s: float = 5.0) -> int:
    """Read the HTTP response on `sock` until `parts` JPEGs arrived; returns how many did."""
    sock.settimeout(timeout_s)
    data = b""
    t_end = time.monotonic() + timeout_s
    while data.count(b"Content-Type: image/jpeg") < parts and time.monotonic() < t_end:
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
    return data.count(b"Content-Type: image/jpeg")


def _mjpeg_socket(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
    sock.sendall(b"GET /api/v1/video.mjpeg HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    return sock


async def test_stream_and_page_survive_camera_loss_and_leaving_clients(tmp_path: Path) -> None:
    async with live_rig(tmp_path, width=CAMERA["width"], height=CAMERA["height"], fps=15.0, api=True,
                        overrides={"video": {"width": 320, "height": 240}}) as rig:
        api = rig.daemon.api_server
        assert api is not None
        rx = RtpReceiver(rig.daemon.video_sdp_path)
        await asyncio.to_thread(rx.start)
        # a page client reads two images and drops the connection mid-stream (RST, no goodbye)
        sock = _mjpeg_socket(api.port)
        assert await asyncio.to_thread(_read_mjpeg_parts, sock, 2) >= 2
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        sock.close()
        # the camera vanishes for 2 s and comes back
        await asyncio.sleep(1.0)
        t_unplug = time.monotonic()
        rig.unplug(2.0)
        await asyncio.sleep(1.5)
        idle_during = rig.daemon.video_streamer.stats().idle_frames
        camera_during = rig.daemon.status()["camera"]["state"]
        alert_during = rig.daemon.video_streamer.idle_alert
        await asyncio.sleep(3.5)
        t_back = t_unplug + 2.0
        # the RTP receiver leaves and a new one joins mid-stream
        rx.stop()
        rx2 = RtpReceiver(rig.daemon.video_sdp_path)
        await asyncio.to_thread(rx2.start)
        sock2 = _mjpeg_socket(api.port)
        parts_after = await asyncio.to_thread(_read_mjpeg_parts, sock2, 3)
        sock2.close()
        await asyncio.sleep(2.5)
        rx2.stop()
        status = rig.daemon.status()
        page = rig.daemon.page_state()
    assert rx.error is None and rx2.error is None, (rx.error, rx2.error)
    assert camera_during == "lost"
    assert alert_during == "CAMERA LOST"
    assert idle_during >= 1, "no 'no camera' frames while the camera was gone"
    # live frames again after the camera came back: fresh capture stamps, decoded by the first receiver
    fresh = [f for f in rx.frames if f.stamp_ms is not None and f.stamp_ms / 1000.0 > t_back + 0.3]
    assert len(fresh) >= 10, f"{len(fresh)} live frames after the camera came back"
    assert len(rx2.frames) >= 10, "a receiver joining mid-stream decodes nothing"
    assert parts_after >= 3
    assert status["camera"]["state"] == "streaming"
    assert any("camera-lost" in line for line in page["log"]) and any("camera-recovered" in line
                                                                       for line in page["log"])
