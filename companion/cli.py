"""The `companion` command line (argparse only; the work is delegated).

Subcommands (DESIGN.md "Command line")::

    companion sim [--mission FILE] [--autopilot ardupilot|px4] [--fault SPEC]... [--headless] [--out DIR]
                  [--start-error M,DEG] [--seed-true-pose]
    companion fake-autopilot --listen URL [--profile ardupilot|px4]
    companion run --config FILE
    companion check-config [--offline] FILE
    companion calibrate (--camera CONFIG | --images DIR | --video FILE) --board ... --out FILE.yaml
    companion mission validate FILE [--config FILE]
    companion mission upload|list|start|pause|resume|abort|status ...
    companion status
    companion replay FOLDER

Exit codes: 0 success; 1 the operation ran and failed (e.g. the simulated
mission did not complete, the daemon is unreachable); 2 bad input (unknown
option, invalid file), always with one line on stderr and never a traceback;
130 interrupted.
"""

from __future__ import annotations

import os

# The daemon already runs its own threads (capture, vision worker, asyncio loop, and in the
# simulator the renderer); a BLAS thread pool on top of them oversubscribes the 2-4 cores of a
# companion computer (a 360x240 synthetic frame took 40 ms instead of 11 ms). Set before numpy loads.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, NoReturn  # noqa: E402

from companion.errors import CompanionError, ConfigError, InputError, MissionError  # noqa: E402

__all__ = ["main"]

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

DEFAULT_CONFIG = Path("/etc/companion/companion.toml")


class UsageError(CompanionError):
    """Bad command-line input (exit 2)."""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line on stderr and exit code 2."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{self.prog}: {message} (try '{self.prog} --help')")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _fail(message: str, code: int) -> int:
    print(f"companion: error: {_one_line(message)}", file=sys.stderr)
    return code


# ---------------------------------------------------------------------------------------------- handlers


def _keep_freed_memory() -> None:
    """The vision loop's processes keep freed heap memory for the next frame (`drivers/allocator.py`)."""
    from drivers.allocator import keep_freed_memory

    keep_freed_memory()


def _cmd_sim(args: argparse.Namespace) -> int:
    from companion.sim.config_set import merge_overrides, parse_config_sets
    from companion.sim.ground_station import ground_station_overrides
    from companion.sim.run import SimOptions, parse_fault_spec, run_sim_cli
    from companion.sim.start_error import parse_start_error

    faults = [parse_fault_spec(spec) for spec in args.fault]
    start_error = parse_start_error(args.start_error) if args.start_error is not None else None
    _setup_logging(args.verbose)
    _keep_freed_memory()
    options = SimOptions(
        mission_path=Path(args.mission) if args.mission else None,
        autopilot=args.autopilot,
        faults=tuple(faults),
        headless=bool(args.headless),
        out_dir=Path(args.out),
        max_duration_s=float(args.duration) if args.duration is not None else None,
        seed=int(args.seed),
        wind=not args.no_wind,
        speed=float(args.speed),
        config_overrides=merge_overrides(ground_station_overrides(args), parse_config_sets(args.set)),
        start_error=start_error,
        seed_true_pose=bool(args.seed_true_pose),
        appearance=str(args.appearance),
    )
    return run_sim_cli(options)


def _cmd_fake_autopilot(argv: list[str]) -> int:
    try:
        from companion.sim.autopilot.cli import main as autopilot_main
    except ImportError as exc:
        return _fail(f"the fake autopilot is not available ({exc})", EXIT_FAILED)
    result = autopilot_main(argv)
    return int(result) if result is not None else EXIT_OK


def _load_config(path: Path) -> Any:
    from companion.config import load_config

    return load_config(path)


def _cmd_check_config(args: argparse.Namespace) -> int:
    from companion.config import check_config_cli

    code, message = check_config_cli(args.file, offline=bool(args.offline))
    print(message, file=sys.stdout if code == 0 else sys.stderr)
    return int(code)


def _cmd_run(args: argparse.Namespace) -> int:
    import asyncio

    from companion.daemon.app import run_daemon

    path = Path(args.config)
    if not path.is_file():
        raise InputError(f"{path}: no such file (pass --config FILE)")
    config = _load_config(path)
    from companion.config_checks import validate_for_run

    validate_for_run(config)  # what check-config checks, before any flight folder is made
    _setup_logging(args.verbose)
    _keep_freed_memory()
    return asyncio.run(run_daemon(config, config_path=path, record_frames=True if args.record_frames else None))


def _cmd_mission(args: argparse.Namespace) -> int:
    if args.mission_command == "validate":
        from companion.mission import validate_cli

        limits = None  # the parser's defaults
        if args.config:
            from companion.config import mission_limits

            limits = mission_limits(_load_config(Path(args.config)))  # the limits the daemon's upload check uses
        code, message = validate_cli(args.file, limits)
        print(message, file=sys.stdout if code == 0 else sys.stderr)
        return int(code)
    from drivers.api import mission_cli

    return int(mission_cli(args))


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from companion.calibration_cli import run_calibrate_cli

    return run_calibrate_cli(args)


def _cmd_status(args: argparse.Namespace) -> int:
    from drivers.api import status_cli

    return int(status_cli(args))


def _cmd_replay(args: argparse.Namespace) -> int:
    from companion.daemon.replay import run_replay_cli

    _setup_logging(args.verbose)
    _keep_freed_memory()
    return run_replay_cli(
        folder=Path(args.folder),
        config_path=Path(args.config) if args.config else None,
        out_dir=Path(args.out) if args.out else None,
        overlay=not args.no_overlay,
    )


def _setup_logging(verbose: int) -> None:
    level = logging.DEBUG if verbose > 1 else logging.INFO if verbose == 1 else logging.ERROR
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)


# ---------------------------------------------------------------------------------------------- parser


def _add_client_arguments(p: argparse.ArgumentParser) -> None:
    try:
        from drivers.api import add_client_arguments
    except ImportError:  # the API client is missing from this installation: the command reports it when run
        return
    add_client_arguments(p)


def _add_api_subcommands(msub: Any) -> None:
    try:
        from drivers.api import add_mission_subcommands
    except ImportError:
        return
    add_mission_subcommands(msub)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="companion", description="Companion computer for GPS-denied inspection drones.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    p = sub.add_parser("sim", help="fly a mission in the simulator and write a report")
    p.add_argument("--mission", metavar="FILE", help="mission XML (default: the example rack inspection)")
    p.add_argument("--autopilot", choices=("ardupilot", "px4", "ardupilot-sitl"), default="ardupilot",
                   help="the fake autopilot's ArduPilot or PX4 profile, or the real ArduCopter SITL "
                   "(../shared/ardupilot or $COMPANION_ARDUPILOT_SITL; real time)")
    p.add_argument(
        "--fault", action="append", default=[], metavar="SPEC",
        help="KIND@SECONDS[:DURATION]; KIND one of battery-sag, battery-critical, gcs-loss, vision-loss, "
        "link-loss, camera-unplug, ceiling (repeatable)",
    )
    p.add_argument("--headless", action="store_true", help="no live progress display, log lines only")
    p.add_argument("--out", metavar="DIR", default="sim-out", help="output folder (default ./sim-out)")
    p.add_argument("--duration", metavar="SECONDS", type=float, default=None,
                   help="give up after this many simulated seconds (default: sum of the action timeouts)")
    p.add_argument("--seed", type=int, default=1, help="seed of the wind and the renderer noise")
    p.add_argument("--no-wind", action="store_true", help="fly without Dryden wind")
    p.add_argument("--appearance", choices=("default", "field"), default="default",
                   help="the rack's rendering: default, or field (sparse spots, high-contrast ground, JPEG)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="simulated seconds per wall second (default 1 = real time; < 1 for slow or loaded machines)")
    p.add_argument("--start-error", metavar="M,DEG", default=None,
                   help="boot the vehicle up to M metres and DEG degrees away from the configured start (seeded); "
                   "the daemon must find the rack in the image")
    p.add_argument("--seed-true-pose", action="store_true", help="hand the daemon the true start pose")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override the embedded configuration (a TOML value; a bare word is a string), e.g. "
                   "vision.rack_verify_start=report or vision.rack_tracker.ground_points=0 (repeatable)")
    p.add_argument("-v", "--verbose", action="count", default=0, help="daemon log lines on stderr")
    from companion.sim.ground_station import add_ground_station_arguments

    add_ground_station_arguments(p)  # --no-video, --video-port, --api-port, --token-file
    p.set_defaults(handler=_cmd_sim)

    p = sub.add_parser("fake-autopilot", help="the simulator's autopilot on its own (real time)", add_help=False)
    p.set_defaults(handler=None)

    p = sub.add_parser("run", help="run the daemon (what systemd starts)")
    p.add_argument("--config", metavar="FILE", default=str(DEFAULT_CONFIG))
    p.add_argument("--record-frames", action="store_true", help="keep the camera frames for `companion replay`")
    p.add_argument("-v", "--verbose", action="count", default=1)
    p.set_defaults(handler=_cmd_run)

    p = sub.add_parser("check-config", help="check a configuration as `companion run` does (exit 0, or 2 + the key)")
    p.add_argument("file", metavar="FILE")
    p.add_argument("--offline", action="store_true",
                   help="check the file alone (away from the drone): missing files and devices are warnings")
    p.set_defaults(handler=_cmd_check_config)

    p = sub.add_parser("calibrate", help="calibrate the camera from board views (folder, video or live camera)")
    from companion.calibration_args import add_calibrate_arguments

    add_calibrate_arguments(p)
    p.set_defaults(handler=_cmd_calibrate)

    p = sub.add_parser("mission", help="validate missions and talk to a running daemon")
    msub = p.add_subparsers(dest="mission_command", metavar="ACTION", parser_class=_Parser)
    msub.required = True
    q = msub.add_parser("validate", help="validate a mission file (exit 0, or 2 naming line and field)")
    q.add_argument("file", metavar="FILE")
    q.add_argument("--config", metavar="CONFIG", default=None,
                   help="check against this configuration's ceiling, speed and geofence (default: built-in limits)")
    _add_api_subcommands(msub)
    p.set_defaults(handler=_cmd_mission)

    p = sub.add_parser("status", help="daemon, link, camera, estimator, mission and safety state")
    _add_client_arguments(p)
    p.set_defaults(handler=_cmd_status)

    p = sub.add_parser("replay", help="re-run vision on a recorded flight folder")
    p.add_argument("folder", metavar="FOLDER")
    p.add_argument("--config", metavar="FILE", default=None, help="configuration (default: the folder's copy)")
    p.add_argument("--out", metavar="DIR", default=None, help="output folder (default FOLDER/replay)")
    p.add_argument("--no-overlay", action="store_true", help="do not write the overlay video")
    p.add_argument("-v", "--verbose", action="count", default=0)
    p.set_defaults(handler=_cmd_replay)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `companion` console script; returns the exit code."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    try:
        if args_list and args_list[0] == "fake-autopilot":
            return _cmd_fake_autopilot(args_list[1:])
        parser = build_parser()
        try:
            args = parser.parse_args(args_list)
        except SystemExit as exc:  # --help / --version
            return int(exc.code) if isinstance(exc.code, int) else EXIT_OK
        return int(args.handler(args))
    except KeyboardInterrupt:
        return _fail("interrupted", EXIT_INTERRUPTED)
    except (UsageError, InputError, ConfigError, MissionError) as exc:
        return _fail(str(exc), EXIT_USAGE)
    except ValueError as exc:  # e.g. a malformed file a parser reports as ValueError
        return _fail(str(exc), EXIT_USAGE)
    except CompanionError as exc:
        return _fail(str(exc), EXIT_FAILED)
    except ImportError as exc:
        return _fail(f"a component is missing from this installation: {exc}", EXIT_FAILED)
    except OSError as exc:
        return _fail(str(exc), EXIT_FAILED)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
