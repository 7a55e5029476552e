"""The real ArduCopter SITL as a peer: start it, watch it, script its world.

`ArduPilotSitl` runs one ArduCopter SITL process (the prebuilt binary in ``../shared/ardupilot/``,
or ``$COMPANION_ARDUPILOT_SITL``) in real time, in a fresh temporary folder, with the copter
defaults and the project's external-navigation preset (``companion/data/ardupilot/extnav.parm``:
vision pose and yaw, barometer height, no GPS, no compass, SITL rangefinder down). SERIAL0
(TCP 5760 + 10 N) is the flight controller's telemetry port the daemon connects to; the SITL
boots on that first connection. It is stopped by its PID.

`SitlObserver` is a second MAVLink client on SERIAL1 (TCP 5762 + 10 N) in a background thread:
it records what the autopilot reports (HEARTBEAT mode/armed, LOCAL_POSITION_NED,
EKF_STATUS_REPORT, STATUSTEXT, HOME_POSITION, EXTENDED_SYS_STATE, SIM_STATE truth), plays the
ground station (GCS heartbeats that can be switched off), and sets SIM_* parameters to script
faults (battery voltage, ...). This is test and rehearsal tooling; nothing here runs on a drone.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.data import data_path
from companion.errors import CompanionError
from companion.geometry import frames

__all__ = ["ArduPilotSitl", "ObservedMessage", "SitlError", "SitlObserver", "extnav_parm", "free_instance",
           "sitl_binary"]

_REPO = Path(__file__).resolve().parents[2]


class SitlError(CompanionError):
    """The SITL binary is missing, did not start, or did not answer."""


def extnav_parm() -> Path:
    """The project's ArduCopter external-navigation parameter preset."""
    return data_path("ardupilot/extnav.parm")


def sitl_binary() -> Path | None:
    """The ArduCopter SITL binary: ``$COMPANION_ARDUPILOT_SITL`` (file or folder), else
    ``../shared/ardupilot/arducopter`` beside the source tree or the working directory; None if absent."""
    candidates: list[Path] = []
    env = os.environ.get("COMPANION_ARDUPILOT_SITL")
    if env:
        p = Path(env)
        candidates.append(p / "arducopter" if p.is_dir() else p)
    for base in (_REPO, Path.cwd()):  # ../shared beside the tree; from a git worktree one level further up
        candidates += [parent / "shared" / "ardupilot" / "arducopter" for parent in (base.parent, base.parent.parent)]
    for c in candidates:
        if c.is_file() and os.access(c, os.X_OK):
            return c.resolve()
    return None


def _ports_free(port: int) -> bool:
    # the SITL binds 0.0.0.0 on 5760+10N, 5762+10N and 5763+10N: all must be free
    for p in (port, port + 2, port + 3):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("0.0.0.0", p))
            except OSError:
                return False
    return True


def free_instance(first: int = 0, last: int = 60) -> int:
    """The first SITL instance number (ports 5760 + 10 N ...) whose TCP ports are all free."""
    for n in range(first, last):
        if _ports_free(5760 + 10 * n):
            return n
    raise SitlError(f"no free ArduPilot SITL instance between {first} and {last}")


@dataclass
class ArduPilotSitl:
    """One real-time ArduCopter SITL process (use as a context manager, or start()/stop()).

    ``home``: "lat,lon,alt_m,heading_deg" (None: the SITL's default home, heading 353 deg).
    ``extra_params``: loaded after the extnav preset (later wins).
    """

    binary: Path
    home: str | None = None
    extra_params: dict[str, float] = field(default_factory=dict)
    instance: int | None = None
    proc: subprocess.Popen[bytes] | None = None
    workdir: Path | None = None

    @property
    def port(self) -> int:
        """SERIAL0's TCP port (the flight controller's telemetry port)."""
        if self.instance is None:
            raise SitlError("the SITL is not started")
        return 5760 + 10 * self.instance

    @property
    def url(self) -> str:
        """MAVLink URL of SERIAL0 for the daemon (`drivers.mavlink` syntax)."""
        return f"tcp:127.0.0.1:{self.port}"

    @property
    def observer_url(self) -> str:
        """MAVLink URL of SERIAL1, for a second client (pymavlink syntax)."""
        return f"tcp:127.0.0.1:{self.port + 2}"

    def start(self) -> ArduPilotSitl:
        self.workdir = Path(tempfile.mkdtemp(prefix="apsitl-"))
        parms = [str(self.binary.parent / "copter.parm"), str(extnav_parm())]
        if self.extra_params:
            extra = self.workdir / "extra.parm"
            extra.write_text("".join(f"{k} {v}\n" for k, v in self.extra_params.items()), encoding="utf-8")
            parms.append(str(extra))
        first = 0 if self.instance is None else self.instance
        for _attempt in range(5):  # a port taken between the check and the bind: next instance
            self.instance = free_instance(first)
            args = [str(self.binary), "--model", "+", "--speedup", "1", "-I", str(self.instance), "-w",
                    "--defaults", ",".join(parms)]
            if self.home:
                args += ["--home", self.home]
            with open(self.workdir / "sitl.log", "wb") as log:
                self.proc = subprocess.Popen(args, cwd=self.workdir, stdout=log, stderr=subprocess.STDOUT,
                                             stdin=subprocess.DEVNULL, start_new_session=True)
            if self._wait_listening(10.0):
                return self
            self._kill()
            first = self.instance + 1
        raise SitlError(f"ArduPilot SITL did not start: {self.log_text()[-500:]}")

    def _wait_listening(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc is None or self.proc.poll() is not None:
                return False
            if "Waiting for connection" in self.log_text():
                return True
            time.sleep(0.05)
        return False

    def log_text(self) -> str:
        """What the SITL printed so far."""
        if self.workdir is None or not (self.workdir / "sitl.log").exists():
            return ""
        return (self.workdir / "sitl.log").read_text(errors="replace")

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def _kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=5.0)
        self.proc = None

    def stop(self) -> None:
        """Stop the process (by PID) and remove its folder."""
        self._kill()
        if self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None

    def __enter__(self) -> ArduPilotSitl:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


@dataclass(frozen=True)
class ObservedMessage:
    """A message the observer received: monotonic receive time (s), type name, decoded fields."""

    time_s: float
    type: str
    fields: dict[str, Any]


def _deg(value: float) -> float:
    return value * 1e-7 if abs(value) > 360.0 else value


_STREAMS_HZ = {  # what the observer asks for on its own channel
    "SIM_STATE": 25.0, "LOCAL_POSITION_NED": 10.0, "EKF_STATUS_REPORT": 4.0, "EXTENDED_SYS_STATE": 4.0,
    "SYS_STATUS": 2.0, "BATTERY_STATUS": 2.0, "ATTITUDE": 10.0,
}
_MSG_IDS = {"SIM_STATE": 108, "LOCAL_POSITION_NED": 32, "EKF_STATUS_REPORT": 193, "EXTENDED_SYS_STATE": 245,
            "SYS_STATUS": 1, "BATTERY_STATUS": 147, "ATTITUDE": 30, "HOME_POSITION": 242}


class SitlObserver:
    """A MAVLink client on the SITL's SERIAL1 that records, plays the GCS and sets parameters.

    ``origin_deg``: (lat, lon, alt_m) of the local NED frame for `truth_T_ned_body` (the EKF
    origin the daemon sets). Times are `time.monotonic()` seconds.
    """

    def __init__(self, url: str, origin_deg: tuple[float, float, float], *, gcs_heartbeat: bool = True,
                 system_id: int = 255, component_id: int = 190) -> None:
        self.url = url
        self.origin_deg = origin_deg
        self.gcs_heartbeat = gcs_heartbeat
        self._ids = (system_id, component_id)
        self._lock = threading.Lock()
        self._messages: list[ObservedMessage] = []
        self._latest: dict[str, ObservedMessage] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._conn: Any = None

    def __enter__(self) -> SitlObserver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self, timeout_s: float = 30.0) -> SitlObserver:
        os.environ["MAVLINK20"] = "1"  # MAVLink 2 frames make ArduPilot answer in MAVLink 2 (with extensions)
        from pymavlink import mavutil

        mavutil.set_dialect("ardupilotmega")

        deadline = time.monotonic() + timeout_s
        while True:  # SERIAL1 opens once the SITL has booted (after SERIAL0's first client)
            try:
                self._conn = mavutil.mavlink_connection(self.url, source_system=self._ids[0],
                                                        source_component=self._ids[1], autoreconnect=True)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise SitlError(f"could not connect to the SITL at {self.url}") from None
                time.sleep(0.2)
        self._thread = threading.Thread(target=self._run, name="sitl-observer", daemon=True)
        self._thread.start()
        if not self.wait_for(lambda: self.latest("HEARTBEAT") is not None, max(1.0, deadline - time.monotonic())):
            self.stop()
            raise SitlError(f"no heartbeat from the SITL at {self.url}")
        for name, hz in _STREAMS_HZ.items():
            self.command_long(511, _MSG_IDS[name], 1e6 / hz)
        self.command_long(512, _MSG_IDS["HOME_POSITION"])
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)
            self._thread = None
        if self._conn is not None:
            with contextlib.suppress(Exception):
                self._conn.close()
            self._conn = None

    def _run(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if self.gcs_heartbeat and now >= next_hb:
                next_hb = now + 1.0
                with contextlib.suppress(Exception):
                    self._conn.mav.heartbeat_send(6, 8, 0, 0, 4)  # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, active
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.1)
            except Exception:
                time.sleep(0.1)
                continue
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            if (msg.get_srcSystem(), msg.get_srcComponent()) != (1, 1):  # the autopilot only (not the daemon)
                continue
            fields = msg.to_dict()
            fields.pop("mavpackettype", None)
            rec = ObservedMessage(time.monotonic(), msg.get_type(), fields)
            with self._lock:
                self._messages.append(rec)
                self._latest[rec.type] = rec

    # -- reading ----------------------------------------------------------------------------
    def latest(self, type_name: str) -> ObservedMessage | None:
        with self._lock:
            return self._latest.get(type_name)

    def messages(self, type_name: str | None = None, since_s: float = -math.inf) -> list[ObservedMessage]:
        with self._lock:
            return [m for m in self._messages if (type_name is None or m.type == type_name) and m.time_s >= since_s]

    def statustexts(self, since_s: float = -math.inf) -> list[str]:
        return [str(m.fields["text"]) for m in self.messages("STATUSTEXT", since_s)]

    def wait_for(self, predicate: Any, timeout_s: float, poll_s: float = 0.05) -> bool:
        """Wait (real time) until `predicate()` is true; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(poll_s)
        return bool(predicate())

    @property
    def mode(self) -> str | None:
        from pymavlink import mavutil

        hb = self.latest("HEARTBEAT")
        if hb is None:
            return None
        names = mavutil.mode_mapping_bynumber(2) or {}
        return str(names.get(int(hb.fields["custom_mode"]), hb.fields["custom_mode"]))

    @property
    def armed(self) -> bool:
        hb = self.latest("HEARTBEAT")
        return hb is not None and bool(int(hb.fields["base_mode"]) & 128)

    @property
    def landed_state(self) -> int | None:
        m = self.latest("EXTENDED_SYS_STATE")
        return None if m is None else int(m.fields["landed_state"])

    def truth_T_ned_body(self, msg: ObservedMessage | None = None) -> FloatArray | None:
        """The simulator's true pose of body in the local NED frame of `origin_deg` (from SIM_STATE)."""
        from drivers.mavlink.state import ned_from_geodetic

        m = msg or self.latest("SIM_STATE")
        if m is None:
            return None
        f = m.fields
        # ArduPilot fills the float lat/lon with degE7; the int extensions exist in MAVLink 2 only
        lat = f["lat_int"] * 1e-7 if f.get("lat_int") else _deg(float(f["lat"]))
        lon = f["lon_int"] * 1e-7 if f.get("lon_int") else _deg(float(f["lon"]))
        T = np.eye(4)
        T[:3, :3] = frames.rotation_from_quaternion_wxyz(np.array([f["q1"], f["q2"], f["q3"], f["q4"]], float))
        T[:3, 3] = ned_from_geodetic(lat, lon, float(f["alt"]), *self.origin_deg)
        return T

    def truth_track(self, since_s: float = -math.inf) -> tuple[FloatArray, FloatArray]:
        """(times (N,), positions NED (N, 3)) of SIM_STATE since `since_s`."""
        msgs = self.messages("SIM_STATE", since_s)
        if not msgs:
            return np.zeros(0), np.zeros((0, 3))
        pos = np.array([np.asarray(self.truth_T_ned_body(m))[:3, 3] for m in msgs])
        return np.array([m.time_s for m in msgs]), pos

    # -- acting -----------------------------------------------------------------------------
    def command_long(self, command: int, *params: float) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self._conn.mav.command_long_send(1, 1, command, 0, *p)

    def set_param(self, name: str, value: float, timeout_s: float = 5.0) -> bool:
        """PARAM_SET, waiting for the PARAM_VALUE echo; True when it came back with `value`."""
        since = time.monotonic()
        self._conn.mav.param_set_send(1, 1, name.encode(), float(value), 9)  # MAV_PARAM_TYPE_REAL32

        def echoed() -> bool:
            return any(m.fields["param_id"] == name and abs(float(m.fields["param_value"]) - value) < 1e-3
                       for m in self.messages("PARAM_VALUE", since))

        return self.wait_for(echoed, timeout_s)
