"""Scriptable faults of the fake autopilot: what, when, for how long, with which parameters.

`Fault(kind, at_s, duration_s=None, **params)`; `at_s` is seconds after the
autopilot started (its boot time), `duration_s=None` means until the end.

Kinds and parameters (defaults in brackets):

- ``battery-sag``: voltage_v [3.4 V per cell]; the terminal voltage is forced down to `voltage_v`.
- ``battery-critical``: remaining_pct [5.0], voltage_v [3.3 V per cell]; remaining charge and voltage
  forced to critical; the battery failsafe lands the vehicle.
- ``link-loss``: silence, nothing is sent and everything received is dropped.
- ``message-loss``: percent [10.0], direction ["both" | "in" | "out"]; each message dropped with that probability.
- ``latency``: ms [100.0], direction ["both" | "in" | "out"]; messages delayed by `ms`.
- ``corrupt``: percent [10.0]; that share of outgoing frames get a random byte flipped (CRC fails).
- ``command-reject``: commands [None = all; else MAV_CMD ids, 11 = SET_MODE],
  result ["denied" | "failed" | "temporarily_rejected" | "timeout"]; COMMAND_LONG/INT and SET_MODE
  are refused with that result ("timeout": not answered at all).
- ``gcs-loss``: the built-in GCS heartbeat source stops.
- ``ceiling``: height_m [3.0]; an upward rangefinder reports a ceiling `height_m` above ground and the
  vehicle cannot climb through it.
- ``vision-reject``: incoming vision poses are ignored (the EKF loses its position source).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from companion.errors import InputError

__all__ = ["FAULT_KINDS", "Fault", "active_faults"]

FAULT_KINDS: dict[str, dict[str, Any]] = {
    "battery-sag": {"voltage_v": None},
    "battery-critical": {"remaining_pct": 5.0, "voltage_v": None},
    "link-loss": {},
    "message-loss": {"percent": 10.0, "direction": "both"},
    "latency": {"ms": 100.0, "direction": "both"},
    "corrupt": {"percent": 10.0},
    "command-reject": {"commands": None, "result": "denied"},
    "gcs-loss": {},
    "ceiling": {"height_m": 3.0},
    "vision-reject": {},
}

_DIRECTIONS = ("both", "in", "out")
_RESULTS = ("denied", "failed", "temporarily_rejected", "timeout")


@dataclass(frozen=True, init=False)
class Fault:
    """One scripted fault: `kind` (see FAULT_KINDS), start `at_s` (s after boot), `duration_s` (None = forever),
    `params` (kind-specific, defaults filled in)."""

    kind: str
    at_s: float
    duration_s: float | None
    params: dict[str, Any] = field(hash=False, compare=True)

    def __init__(self, kind: str, at_s: float, duration_s: float | None = None, **params: Any) -> None:
        if kind not in FAULT_KINDS:
            raise InputError(f"unknown fault kind {kind!r}; known: {sorted(FAULT_KINDS)}")
        if not (math.isfinite(at_s) and at_s >= 0.0):
            raise InputError(f"Fault.at_s must be finite and >= 0, got {at_s!r}")
        if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0.0):
            raise InputError(f"Fault.duration_s must be > 0 or None, got {duration_s!r}")
        defaults = FAULT_KINDS[kind]
        unknown = set(params) - set(defaults)
        if unknown:
            raise InputError(f"fault {kind!r} has no parameter(s) {sorted(unknown)}; known: {sorted(defaults)}")
        merged = {**defaults, **params}
        if "direction" in merged and merged["direction"] not in _DIRECTIONS:
            raise InputError(f"fault {kind!r}: direction must be one of {_DIRECTIONS}, got {merged['direction']!r}")
        if "percent" in merged and not 0.0 <= float(merged["percent"]) <= 100.0:
            raise InputError(f"fault {kind!r}: percent must be in [0, 100], got {merged['percent']!r}")
        if "result" in merged and merged["result"] not in _RESULTS:
            raise InputError(f"fault {kind!r}: result must be one of {_RESULTS}, got {merged['result']!r}")
        if kind == "command-reject" and merged["commands"] is not None:
            merged["commands"] = tuple(int(c) for c in merged["commands"])
        object.__setattr__(self, "kind", kind)
        object.__setattr__(self, "at_s", float(at_s))
        object.__setattr__(self, "duration_s", None if duration_s is None else float(duration_s))
        object.__setattr__(self, "params", merged)

    @property
    def end_s(self) -> float:
        """End time (s after boot); infinity when the fault lasts forever."""
        return math.inf if self.duration_s is None else self.at_s + self.duration_s

    def active(self, elapsed_s: float) -> bool:
        """True while the fault is in effect at `elapsed_s` seconds after boot."""
        return self.at_s <= elapsed_s < self.end_s

    @classmethod
    def parse(cls, spec: str) -> Fault:
        """Parse the CLI form ``KIND@SECONDS[:DURATION]`` (e.g. ``gcs-loss@20:10``)."""
        try:
            kind, _, when = spec.partition("@")
            start, _, duration = when.partition(":")
            return cls(kind.strip(), float(start), float(duration) if duration else None)
        except ValueError as exc:
            raise InputError(f"bad fault spec {spec!r}: expected KIND@SECONDS[:DURATION]") from exc


def active_faults(faults: list[Fault] | tuple[Fault, ...], elapsed_s: float, kind: str) -> list[Fault]:
    """The faults of `kind` in effect at `elapsed_s`."""
    return [f for f in faults if f.kind == kind and f.active(elapsed_s)]
