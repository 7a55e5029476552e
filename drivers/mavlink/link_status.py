"""What the link reports about itself: `LinkHealth` (connection state) and `LinkStats` (cumulative counters)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["LinkHealth", "LinkStats"]


class LinkHealth(enum.Enum):
    DISCONNECTED = "disconnected"  # transport not open
    CONNECTED = "connected"  # transport open, no autopilot heard yet
    AUTOPILOT_OK = "autopilot_ok"
    AUTOPILOT_LOST = "autopilot_lost"  # heard once, silent for longer than autopilot_timeout_s


@dataclass(frozen=True)
class LinkStats:
    """Counters of the link (cumulative since it was opened)."""

    bytes_in: int = 0
    bytes_out: int = 0
    messages_in: int = 0
    frames_out: int = 0
    garbage_bytes: int = 0
    bad_frames: int = 0
    unknown_messages: int = 0
    mavlink1_rejected: int = 0
    parser_errors: int = 0
    poses_sent: int = 0
    poses_rejected_stale: int = 0
    poses_held_for_timesync: int = 0
    frames_dropped_queue: int = 0
    frames_expired: int = 0
    write_failures: int = 0  # frames the transport could not take (closed, no peer yet, buffer full)
    transport_errors: int = 0  # socket errors reported by the transport (e.g. ICMP port unreachable)
    setpoints_sent: int = 0
    commands_sent: int = 0
    command_retries: int = 0
    command_timeouts: int = 0
    commands_denied: int = 0
    interval_requests_failed: int = 0
    origin_requests_sent: int = 0
    timesync_answered: int = 0
    timesync_samples: int = 0
    autopilot_lost: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    callback_errors: int = 0
    forwarded_to_gcs: int = 0
    forwarded_to_autopilot: int = 0
    tlog_records: int = 0
