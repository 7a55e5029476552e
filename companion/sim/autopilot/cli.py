"""`companion fake-autopilot`: the simulator's autopilot on its own, in real time.

    companion fake-autopilot --listen URL [--profile ardupilot|px4] [--gps] [--wind W20] [--seed N]
                             [--fault KIND@SECONDS[:DURATION]]... [--gcs-heartbeat] [--duration S]

Only argument parsing and the asyncio entry point live here; `main(argv)` returns the exit code
(0 after a clean stop: --duration elapsed, SIGINT or SIGTERM; 2 for a bad argument).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys
from collections.abc import Sequence

from companion.clock import SystemClock
from companion.errors import CompanionError
from companion.sim.autopilot.autopilot import FakeAutopilot, FakeAutopilotConfig
from companion.sim.autopilot.faults import FAULT_KINDS, Fault
from companion.sim.autopilot.wind import DrydenConfig

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of `companion fake-autopilot`."""
    parser = argparse.ArgumentParser(
        prog="companion fake-autopilot",
        description="Run the scripted fake autopilot (a real MAVLink endpoint) in real time.",
    )
    parser.add_argument(
        "--listen",
        required=True,
        metavar="URL",
        help="udpin:HOST:PORT (clients use udpout:HOST:PORT), tcpin:HOST:PORT (clients use tcp:HOST:PORT) "
        "or udpout:HOST:PORT (send to a client listening there)",
    )
    parser.add_argument("--profile", choices=("ardupilot", "px4"), default="ardupilot")
    parser.add_argument(
        "--gps", action="store_true", help="GPS-like configuration: no vision pose needed to arm and fly"
    )
    parser.add_argument(
        "--wind", type=float, default=0.0, metavar="W20", help="wind speed at 20 ft (m/s), Dryden gusts"
    )
    parser.add_argument("--wind-from", type=float, default=0.0, metavar="RAD", help="direction the wind blows from")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--system-id", type=int, default=1)
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="SPEC",
        help=f"KIND@SECONDS[:DURATION], KIND one of {', '.join(sorted(FAULT_KINDS))}",
    )
    parser.add_argument("--gcs-heartbeat", action="store_true", help="also emit GCS heartbeats (sysid 255)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    return parser


async def _serve(config: FakeAutopilotConfig, duration_s: float | None) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    try:
        async with FakeAutopilot(config, clock=SystemClock()) as ap:
            print(f"fake autopilot ({config.profile}) on {config.listen}; connect with {ap.url_for_client}", flush=True)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), duration_s)
            print(f"stopping: mode {ap.mode}, armed {ap.armed}, received {ap.stats['received']} messages", flush=True)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.remove_signal_handler(sig)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `companion fake-autopilot`; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        faults = tuple(Fault.parse(spec) for spec in args.fault)
        config = FakeAutopilotConfig(
            profile=args.profile,
            listen=args.listen,
            system_id=args.system_id,
            require_vision=not args.gps,
            seed=args.seed,
            wind=DrydenConfig(w20_m_s=args.wind, from_rad=args.wind_from),
            faults=faults,
            gcs_heartbeat=args.gcs_heartbeat,
            max_records=100_000,
        )
        asyncio.run(_serve(config, args.duration))
    except CompanionError as exc:
        print(f"companion fake-autopilot: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
