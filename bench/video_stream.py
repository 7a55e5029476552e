"""The ground-station video's cost: the encoder's CPU share, and the vision pipeline with and without the stream.

Part 1 (encoder): a `VideoStreamer` fed rendered rack frames (the simulator's scene, 640x480 camera) with
the full overlay (limbs, texture points, text, stamp block) at 15 frames/s for ``--encode-s`` seconds;
the streamer thread measures its own CPU time (time.thread_time) in encoding + RTP sending and in
drawing. Reported as a share of one core: CPU seconds / wall seconds.

Part 2 (vision with / without the stream): the daemon in real time against the fake autopilot with the
synthetic camera (320x240 at 15 frames/s, resting on the deck over the rack), the stream 640x480 at
15 frames/s to a UDP port nobody reads (what is sent is what costs). Alternating runs with the video
off and on (``--runs`` each, ``--run-s`` seconds after a warm-up): pose rate (poses sent / s) and
capture-to-send latency (median of the frames); the medians over the runs are compared.

Part 3 (what the ground station sees): the same rig with the camera at 320x240, 20 frames/s and the stream
scaled to 640x480 at 20 frames/s, decoded by PyAV from the SDP file the daemon wrote (as VLC or ffplay
would), ``--runs`` runs of ``--run-s`` seconds after a 2 s warm-up: the decoded frame rate and the
glass-to-decoded latency (the capture time on CLOCK_MONOTONIC read back from the stamp block against
time.monotonic at decode), median and p90 per run, medians over the runs.

    python bench/video_stream.py [--runs 3] [--run-s 8] [--encode-s 10]

Prints ONE JSON object on stdout; progress on stderr.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.geometry import frames
from companion.sim.run import sim_config
from drivers.camera import load_camera_model
from drivers.video import Overlay
from drivers.video.streamer import FrameJob, VideoStreamer
from sitl_tests.video_harness import RtpReceiver, free_udp_port, live_rig


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def encoder_cost(seconds: float, fps: float = 15.0) -> dict[str, Any]:
    from companion.sim.render import SceneRenderer
    from companion.vision.rack import RackModel

    with tempfile.TemporaryDirectory() as tmp:
        config = sim_config(Path(tmp), {"camera": {"width": 640, "height": 480}})
    cam = load_camera_model(config.camera)
    render = SceneRenderer.from_config(config, cam, seed=2)
    model = RackModel.load(config.rack.model)
    pipes = model.pipe_arrays()
    rng = np.random.default_rng(4)
    jobs = []
    for k in range(8):  # a short drift along the pipes: the encoder sees motion, not a still
        T_ned_body = np.eye(4)
        T_ned_body[:3, 3] = (0.05 * k, 0.01 * k, -1.2)
        T_rack_cam = frames.T_rack_cam_from_T_ned_body(T_ned_body, config.rack.T_ned_rack, config.mount.T_body_cam)
        image = render(T_ned_body)
        texture = np.column_stack([rng.uniform(0.0, 2.0, 60), rng.uniform(0.0, 3.0, 60), np.full(60, 0.3)])
        jobs.append((image, Overlay(T_rack_cam=T_rack_cam, pipes=pipes, rack_ok=True, texture_rack=texture,
                                    lines=("pose N +0.00 E +0.00 D -1.20 m yaw +0 deg (rack)",
                                           "rack ok edges 230 tex 50 res 0.25px vision 9 ms",
                                           "mission bench running 1/3 takeoff:up", "safety none GUIDED ARMED"))))
    streamer = VideoStreamer(size=(640, 480), fps=fps, bitrate_kbps=1500, host="127.0.0.1", port=free_udp_port(),
                             camera=cam, stamp=True)
    streamer.start()
    t0 = time.monotonic()
    k = 0
    while (now := time.monotonic()) - t0 < seconds:
        image, overlay = jobs[k % len(jobs)]
        streamer.submit(FrameJob(image, now, overlay))
        k += 1
        time.sleep(max(0.0, t0 + k / fps - time.monotonic()))
    wall = time.monotonic() - t0
    time.sleep(0.2)
    streamer.stop()
    st = streamer.stats()
    return {
        "size": [640, 480], "fps_in": fps, "wall_s": round(wall, 2), "frames_encoded": st.encoded,
        "frames_per_s": round(st.encoded / wall, 2),
        "encode_cpu_share_of_core": round(st.encode_cpu_s / wall, 4),
        "overlay_cpu_share_of_core": round(st.overlay_cpu_s / wall, 4),
        "streamer_thread_cpu_share_of_core": round(st.thread_cpu_s / wall, 4),
        "encode_ms_per_frame": round(1000.0 * st.encode_cpu_s / max(st.encoded, 1), 2),
        "kbit_per_s": round(8.0 * st.bytes_sent / wall / 1000.0, 1),
    }


async def vision_run(video: bool, seconds: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        async with live_rig(Path(tmp), width=320, height=240, fps=15.0, video=video,
                            overrides={"video": {"width": 640, "height": 480, "fps": 15.0, "stamp": True}}) as rig:
            records: list[Any] = []
            await asyncio.sleep(2.0)  # warm-up: tracker settled, encoder running
            rig.daemon.frame_observers.append(records.append)
            await asyncio.sleep(seconds)
            rig.daemon.frame_observers.remove(records.append)
            streamer = rig.daemon.video_streamer
            encoded = None if streamer is None else streamer.stats().encoded
    sent = [r for r in records if r.sent]
    lat = [1000.0 * (r.sent_s - r.capture_s) for r in sent]
    return {"video": video, "poses_per_s": round(len(sent) / seconds, 2), "frames": len(records),
            "latency_ms_p50": round(float(np.median(lat)), 2) if lat else None,
            "latency_ms_p90": round(float(np.percentile(lat, 90)), 2) if lat else None,
            "frames_encoded": encoded}


async def vision_compare(runs: int, seconds: float) -> dict[str, Any]:
    out: dict[str, list[dict[str, Any]]] = {"off": [], "on": []}
    for k in range(runs):
        for video in (False, True):
            r = await vision_run(video, seconds)
            log(f"run {k + 1}/{runs} video {'on ' if video else 'off'}: {r}")
            out["on" if video else "off"].append(r)

    def med(key: str, side: str) -> float:
        return round(float(np.median([r[key] for r in out[side] if r[key] is not None])), 2)

    summary = {side: {"poses_per_s_median": med("poses_per_s", side),
                      "latency_ms_p50_median": med("latency_ms_p50", side)} for side in ("off", "on")}
    return {"runs": out, "summary": summary}


async def decoded_run(seconds: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        async with live_rig(Path(tmp), width=320, height=240, fps=20.0,
                            overrides={"video": {"width": 640, "height": 480, "fps": 20.0}}) as rig:
            sdp = rig.daemon.video_sdp_path
            assert sdp is not None
            rx = RtpReceiver(sdp)
            await asyncio.to_thread(rx.start)
            t_measure = time.monotonic() + 2.0  # after the receiver's probing and the first key frame
            await asyncio.sleep(2.0 + seconds)
            rx.stop()
    if rx.error is not None:
        raise RuntimeError(f"decoding failed: {rx.error}")
    lat = rx.latencies_ms(t_measure)
    return {"frames_decoded": sum(f.recv_mono_s >= t_measure for f in rx.frames),
            "decoded_per_s": round(rx.decoded_per_s(t_measure), 2), "stamps_read": int(lat.size),
            "latency_ms_p50": round(float(np.median(lat)), 1) if lat.size else None,
            "latency_ms_p90": round(float(np.percentile(lat, 90)), 1) if lat.size else None}


async def decoded_compare(runs: int, seconds: float) -> dict[str, Any]:
    out = []
    for k in range(runs):
        r = await decoded_run(seconds)
        log(f"decoded run {k + 1}/{runs}: {r}")
        out.append(r)

    def med(key: str) -> float | None:
        vals = [r[key] for r in out if r[key] is not None]
        return round(float(np.median(vals)), 1) if vals else None

    return {"runs": out, "summary": {"decoded_per_s_median": med("decoded_per_s"),
                                     "latency_ms_p50_median": med("latency_ms_p50"),
                                     "latency_ms_p90_median": med("latency_ms_p90")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--run-s", type=float, default=8.0)
    ap.add_argument("--encode-s", type=float, default=10.0)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    log("encoder cost at 640x480, 15 frames/s ...")
    enc = encoder_cost(args.encode_s)
    log(f"encoder: {enc}")
    vis = asyncio.run(vision_compare(args.runs, args.run_s))
    dec = asyncio.run(decoded_compare(args.runs, args.run_s))
    print(json.dumps({"encoder": enc, "vision": vis["summary"], "vision_runs": vis["runs"],
                      "decoded_640x480": dec["summary"], "decoded_runs": dec["runs"],
                      "machine_note": "2 cores shared with other work; compare the on/off medians of one run"}))


if __name__ == "__main__":
    main()
