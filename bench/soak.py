"""Soak: minutes of simulated flight through the whole daemon; latency and memory must not grow.

The daemon, the fake autopilot and the synthetic camera run on a `ManualClock` (accelerated: time
advances as fast as the machine computes), vision inline, over real loopback sockets (the
`sitl_tests.daemon_harness` rig). The vehicle flies laps between two goals over the rack for
``--minutes`` of simulated time. Per simulated minute it records the wall-clock capture -> send
latency of the per-frame pipeline (frame handed to the daemon -> pose handed to the link), the
process RSS and Python's traced-free object count proxy (gc objects). Prints ONE JSON object.

    python bench/soak.py [--minutes 10] [--fps 10]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.mission import State
from sitl_tests.daemon_harness import mission, rig


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def laps_mission(laps: int) -> Any:
    body = ['<takeoff id="takeoff" height="1.0"/>']
    for k in range(laps):
        body.append(f'<servo id="out{k}" pipe="3" height="2.0" y="3.0" yaw="0" timeout="60"/>')
        body.append(f'<servo id="back{k}" pipe="3" height="2.0" y="0.8" yaw="0" timeout="60"/>')
    return mission("\n".join(body), name="soak", timeout_s=60.0)


async def soak(minutes: float, fps: float) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="soak-"))
    per_minute: list[dict[str, Any]] = []
    # the fake autopilot keeps a bounded record of what it received (its own memory is not the daemon's)
    async with rig(tmp, fps=fps, overrides={"logging": {"health_period_s": 5.0}}, max_records=5000) as r:
        lat_ms: list[float] = []
        received: dict[int, float] = {}
        d = r.daemon

        def on_frame(fr: Any) -> None:
            if fr.sent and fr.seq in received:
                lat_ms.append((fr.sent_perf_s - received.pop(fr.seq)) * 1e3)
            received.clear()

        orig_next = r.camera.next_frame

        async def timed_next(timeout_s: float | None = None) -> Any:
            frame = await orig_next(timeout_s)
            if frame is not None:
                received[frame.seq] = time.perf_counter()
            return frame

        r.camera.next_frame = timed_next  # type: ignore[method-assign]
        d.frame_observers.append(on_frame)
        await r.start_mission(laps_mission(400))
        ex = d.executor
        assert ex is not None
        t0_wall = time.perf_counter()
        for minute in range(int(np.ceil(minutes))):
            span = min(60.0, minutes * 60.0 - minute * 60.0)
            await r.advance(span, step_s=0.02)
            gc.collect()
            lat = np.asarray(lat_ms) if lat_ms else np.zeros(1)
            per_minute.append({
                "minute": minute + 1,
                "frames": len(lat_ms),
                "latency_p50_ms": round(float(np.percentile(lat, 50)), 3),
                "latency_p99_ms": round(float(np.percentile(lat, 99)), 3),
                "rss_mb": round(rss_mb(), 1),
                "gc_objects": len(gc.get_objects()),
                "mission_state": str(ex.state),
                "actions_done": len(ex.results),
            })
            lat_ms.clear()
            if ex.state is not State.RUNNING:
                break
        wall_s = time.perf_counter() - t0_wall
        poses = d.counters.poses_sent
    # minute 1 warms caches up; compare the median of the first three later minutes with the last three
    steady = per_minute[1:] if len(per_minute) > 1 else per_minute
    head, tail = steady[:3], steady[-3:]

    def med(rows: list[dict[str, Any]], key: str) -> float:
        return float(np.median([row[key] for row in rows]))

    rss_growth = med(tail, "rss_mb") - med(head, "rss_mb")
    lat_growth = med(tail, "latency_p50_ms") - med(head, "latency_p50_ms")
    lat_ref = med(head, "latency_p50_ms")
    last = per_minute[-1]
    return {
        "benchmark": "soak",
        "sim_minutes": len(per_minute),
        "wall_s": round(wall_s, 1),
        "fps": fps,
        "poses_sent": poses,
        "mission_state": last["mission_state"],
        "per_minute": per_minute,
        "rss_growth_mb_after_warmup": round(rss_growth, 1),
        "latency_p50_growth_ms_after_warmup": round(lat_growth, 3),
        "no_growth": bool(rss_growth < 20.0 and lat_growth < max(3.0, 0.3 * lat_ref)),
        "note": "wall-clock latency on a shared, loaded machine; time is a ManualClock advanced as fast as possible",
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--fps", type=float, default=10.0)
    args = p.parse_args()
    logging.basicConfig(level=logging.CRITICAL)
    print(json.dumps(asyncio.run(soak(args.minutes, args.fps))))


if __name__ == "__main__":
    main()
