"""Start and stop a real ArduCopter SITL (the binary in ../shared/ardupilot/) for tests and recordings.

The binary is found at `$COMPANION_ARDUPILOT_SITL` (the `arducopter` file or its folder) or at
`../shared/ardupilot/arducopter` beside the repository. Each `ArduPilotSitl` runs a fresh instance
in its own temporary folder with the project's external-navigation preset (`extnav.parm` beside
this file) loaded after the copter defaults, on the first instance number whose MAVLink port
(TCP 5760 + 10 N, 127.0.0.1) is free, and is stopped by its PID.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
EXTNAV_PARM = HERE / "extnav.parm"
REPO = HERE.parents[1]


def sitl_binary() -> Path | None:
    """The ArduCopter SITL binary, or None when there is none on this machine."""
    env = os.environ.get("COMPANION_ARDUPILOT_SITL")
    candidates = []
    if env:
        p = Path(env)
        candidates.append(p / "arducopter" if p.is_dir() else p)
    # ../shared beside the repository; a git worktree (e.g. /work/wt/NAME) looks one level further up
    candidates += [parent / "shared" / "ardupilot" / "arducopter" for parent in REPO.parents[:2]]
    for c in candidates:
        if c.is_file() and os.access(c, os.X_OK):
            return c
    return None


def _port_free(port: int) -> bool:
    # the SITL binds 0.0.0.0 on 5760+10N .. 5763+10N: all of them must be free
    for p in (port, port + 2, port + 3):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("0.0.0.0", p))
            except OSError:
                return False
    return True


def free_instance(first: int = 0, last: int = 60) -> int:
    """The first SITL instance number whose TCP ports are free."""
    for n in range(first, last):
        if _port_free(5760 + 10 * n):
            return n
    raise RuntimeError(f"no free ArduPilot SITL instance between {first} and {last}")


@dataclass
class ArduPilotSitl:
    """One ArduCopter SITL process (real time). Use as a context manager."""

    binary: Path
    extra_params: dict[str, float] = field(default_factory=dict)
    instance: int | None = None
    home: str | None = None  # "lat,lon,alt_m,heading_deg"; None = the SITL's default home
    proc: subprocess.Popen[bytes] | None = None
    workdir: Path | None = None

    @property
    def port(self) -> int:
        assert self.instance is not None
        return 5760 + 10 * self.instance

    @property
    def url(self) -> str:
        """The MAVLink URL a client connects to (SERIAL0; the SITL boots on that first connection)."""
        return f"tcp:127.0.0.1:{self.port}"

    def start(self) -> ArduPilotSitl:
        self.workdir = Path(tempfile.mkdtemp(prefix="apsitl-"))
        parms = [str(self.binary.parent / "copter.parm"), str(EXTNAV_PARM)]
        if self.extra_params:
            extra = self.workdir / "extra.parm"
            extra.write_text("".join(f"{k} {v}\n" for k, v in self.extra_params.items()))
            parms.append(str(extra))
        # a race on the port between the check and the bind is retried with the next instance
        for _attempt in range(5):
            self.instance = free_instance(0 if self.instance is None else self.instance)
            args = [str(self.binary), "--model", "+", "--speedup", "1", "-I", str(self.instance), "-w",
                    "--defaults", ",".join(parms)]
            if self.home:
                args += ["--home", self.home]
            log = open(self.workdir / "sitl.log", "wb")  # noqa: SIM115 - closed with the process
            self.proc = subprocess.Popen(args, cwd=self.workdir, stdout=log, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
            log.close()
            if self._wait_listening(10.0):
                return self
            self.stop(keep_dir=True)
            self.instance += 1
        raise RuntimeError(f"ArduPilot SITL did not start; log in {self.workdir}")

    def _wait_listening(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc is None or self.proc.poll() is not None:
                return False
            text = (self.workdir / "sitl.log").read_text(errors="replace") if self.workdir else ""
            if "Waiting for connection" in text:
                return True
            time.sleep(0.05)
        return False

    def log_text(self) -> str:
        if self.workdir is None or not (self.workdir / "sitl.log").exists():
            return ""
        return (self.workdir / "sitl.log").read_text(errors="replace")

    def stop(self, keep_dir: bool = False) -> None:
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
        if not keep_dir and self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None

    def __enter__(self) -> ArduPilotSitl:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
