"""Benchmark of the MAVLink link: decode throughput and pose send latency. Prints ONE JSON object.

- decode: a recorded-like stream of autopilot telemetry (ATTITUDE, HIGHRES_IMU, LOCAL_POSITION_NED,
  SYS_STATUS, DISTANCE_SENSOR, HEARTBEAT, ...) in UDP-sized datagrams goes through the link's reader
  path (FrameParser + StateTracker, the code the transport callback runs): messages/s.
- socket: the same datagrams sent over loopback UDP by a sender thread to a live `MavLink` (udpin):
  messages decoded per second of wall time, end to end.
- pose latency: `link.send_pose(pose)` -> the datagram read by a receiver thread on loopback
  (an upper bound on "estimate ready -> bytes on the socket": it includes the kernel hop and the
  receiver's wake-up).
Medians of several runs; the machine is shared, so treat the numbers as indicative.

Run: ``python bench/link_throughput.py`` (prints exactly one JSON object on stdout).
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `python bench/link_throughput.py` from anywhere

from drivers.mavlink import LinkConfig, MavLink, PoseOut
from drivers.mavlink.state import StateTracker
from drivers.mavlink.wire import FrameParser

RUNS = 5


def telemetry_datagrams(n_messages: int, per_datagram: int = 8) -> list[bytes]:
    mav = mavlink.MAVLink(None, 1, 1)
    rng = np.random.default_rng(0)
    frames: list[bytes] = []
    for i in range(n_messages):
        k = i % 8
        t_ms = i
        if k == 0:
            m = mav.heartbeat_encode(2, 3, 81, 4, 4)
        elif k in (1, 5):
            m = mav.highres_imu_encode(t_ms * 1000, *rng.normal(size=6), 0, 0, 0, 0, 0, 0, 0, 0xFFFF, 0)
        elif k == 2:
            m = mav.attitude_encode(t_ms, *rng.normal(size=6) * 0.1)
        elif k == 3:
            m = mav.local_position_ned_encode(t_ms, *rng.normal(size=6))
        elif k == 4:
            m = mav.sys_status_encode(0, 0, 0, 0, 12600, 1500, 80, 0, 0, 0, 0, 0, 0)
        elif k == 6:
            m = mav.distance_sensor_encode(t_ms, 10, 4000, 250, 0, 0, 25, 0)
        else:
            m = mav.battery_status_encode(0, 0, 0, 2500, [4200, 4200, 4200] + [65535] * 7, 1500, 0, 0, 80)
        frames.append(bytes(m.pack(mav)))
        mav.seq = (mav.seq + 1) % 256
    return [b"".join(frames[i : i + per_datagram]) for i in range(0, len(frames), per_datagram)]


def bench_decode(datagrams: list[bytes], n_messages: int) -> float:
    parser = FrameParser()
    tracker = StateTracker()
    t0 = time.perf_counter()
    now = 0.0
    count = 0
    for d in datagrams:
        for msg in parser.feed(d, datagram=True):
            tracker.apply(msg, now)
            count += 1
    dt = time.perf_counter() - t0
    assert count == n_messages, (count, n_messages)
    tracker.snapshot()
    return n_messages / dt


async def bench_socket(datagrams: list[bytes], n_messages: int) -> float:
    async with MavLink(LinkConfig(url="udpin:127.0.0.1:0", timesync_period_s=0.0)) as link:
        addr = link.local_address
        assert addr is not None
        done = threading.Event()

        def sender() -> None:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            for i, d in enumerate(datagrams):
                s.sendto(d, addr)
                if i % 32 == 31:
                    time.sleep(0.0005)  # stay below the socket buffer, the reader is the bottleneck
            s.close()
            done.set()

        start_in = link.stats.messages_in
        t0 = time.perf_counter()
        th = threading.Thread(target=sender)
        th.start()
        last_change = time.perf_counter()
        last = start_in
        while True:
            await asyncio.sleep(0.001)
            n = link.stats.messages_in
            if n != last:
                last, last_change = n, time.perf_counter()
            if n - start_in >= n_messages or (done.is_set() and time.perf_counter() - last_change > 0.2):
                break
        t_end = last_change
        th.join()
        received = link.stats.messages_in - start_in
        return received / (t_end - t0)


async def bench_pose_latency(n_poses: int = 200) -> list[float]:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    port = rx.getsockname()[1]
    arrivals: dict[int, float] = {}
    stop = threading.Event()
    ap = mavlink.MAVLink(None, 1, 1)

    def receiver() -> None:
        parser = FrameParser()
        next_beat = 0.0
        while not stop.is_set():
            try:
                data, peer_addr = rx.recvfrom(65536)
            except TimeoutError:
                continue
            t = time.perf_counter()
            if t >= next_beat:  # an autopilot heartbeat every 0.5 s keeps the link from timing out
                next_beat = t + 0.5
                rx.sendto(bytes(ap.heartbeat_encode(2, 3, 0, 4, 3).pack(ap)), peer_addr)
                ap.seq = (ap.seq + 1) % 256
            for m in parser.feed(data, datagram=True):
                if m.get_type() == "VISION_POSITION_ESTIMATE":
                    arrivals[int(m.usec)] = t

    th = threading.Thread(target=receiver)
    th.start()
    sent: dict[int, float] = {}
    try:
        cfg = LinkConfig(url=f"udpout:127.0.0.1:{port}", timesync_period_s=0.0, send_vision_speed=False)
        async with MavLink(cfg) as link:
            await link.wait_autopilot(5.0)
            await asyncio.sleep(0.2)  # interval requests and their retries settle
            cov = np.diag([0.01, 0.01, 0.02, 0.001, 0.001, 0.004])
            T = np.eye(4)
            for i in range(n_poses):
                T[0, 3] = 0.01 * i
                t0 = time.perf_counter()  # estimate ready: wrapping it in PoseOut (validation) is on the clock
                stamp = time.monotonic()
                pose = PoseOut(stamp, T, cov, reset_counter=0)
                assert link.send_pose(pose)
                sent[round(stamp * 1e6)] = t0
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.1)
    finally:
        stop.set()
        th.join()
        rx.close()
    return [(arrivals[u] - t0) * 1e3 for u, t0 in sent.items() if u in arrivals]


async def main() -> dict[str, Any]:
    n = 20_000
    datagrams = telemetry_datagrams(n)
    decode = [bench_decode(datagrams, n) for _ in range(RUNS)]
    sock = [await bench_socket(datagrams, n) for _ in range(3)]
    lat_runs = [await bench_pose_latency() for _ in range(RUNS)]
    medians = [statistics.median(r) for r in lat_runs]
    all_lat = sorted(x for r in lat_runs for x in r)
    return {
        "benchmark": "mavlink_link",
        "decode_messages_per_s": round(statistics.median(decode)),
        "decode_runs": [round(x) for x in decode],
        "socket_messages_per_s": round(statistics.median(sock)),
        "socket_runs": [round(x) for x in sock],
        "pose_latency_ms_median": round(statistics.median(medians), 4),
        "pose_latency_ms_run_medians": [round(x, 4) for x in medians],
        "pose_latency_ms_p99": round(all_lat[int(0.99 * (len(all_lat) - 1))], 4),
        "poses_received": len(all_lat),
        "poses_sent": 200 * RUNS,
        "targets": {"decode_messages_per_s": ">= 2000", "pose_latency_ms_median": "<= 1"},
        "pass": bool(statistics.median(decode) >= 2000 and statistics.median(medians) <= 1.0),
        "note": "medians of several runs on a shared 2-core machine; latency is an upper bound (includes "
        "the loopback hop and the receiver thread's wake-up)",
    }


if __name__ == "__main__":
    logging.disable(logging.WARNING)  # timeouts of the bare receiver are expected; stdout is the JSON only
    print(json.dumps(asyncio.run(main())))
