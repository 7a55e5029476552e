"""The companion daemon: the asyncio service that wires camera, vision, filter, MAVLink, missions and safety.

    from companion.daemon import Daemon, DaemonOptions, run_daemon

See `companion.daemon.app` for the tasks and the shutdown path, `companion.daemon.flight` for the
flight folder, `companion.daemon.pipeline` for the per-frame vision pipeline and
`companion.daemon.replay` for `companion replay`.
"""

from companion.daemon.app import Daemon, DaemonOptions, FrameRecord, run_daemon

__all__ = ["Daemon", "DaemonOptions", "FrameRecord", "run_daemon"]
