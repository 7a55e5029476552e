"""The safety manager's bookkeeping (debounces, latches, last action and faults, pending events) and the
helpers its failsafe rules, its command filter and its dispatch share: the event log and the battery text."""

from __future__ import annotations

from companion.safety.config import SafetyConfig
from companion.safety.readings import _Debounce
from companion.safety.types import Fault, SafetyAction, SafetyEvent, SafetyInputs, SafetyState

__all__ = ["ManagerState"]


class ManagerState:
    """State of a `SafetyManager` (see `__init__`), shared by the failsafe-rule and command-filter mixins."""

    def __init__(self, config: SafetyConfig | None = None) -> None:
        self.config = config if config is not None else SafetyConfig()
        c = self.config
        self._low = _Debounce(c.battery_low_debounce_s)
        self._critical = _Debounce(c.battery_critical_debounce_s)
        self._gcs_hover = False
        self._gcs_land = False
        self._vision_hover = False
        self._vision_land = False
        self._vision_fresh_since_s: float | None = None
        self._gcs_back_since_s: float | None = None
        self._faults: frozenset[Fault] = frozenset()
        self._action = SafetyAction.NONE
        self._state = SafetyState.NOMINAL
        self._events: list[SafetyEvent] = []
        self._clamping: frozenset[Fault] = frozenset()
        self._blocked = False
        self._last_inputs: SafetyInputs | None = None
        self._last_step_s: float | None = None

    @staticmethod
    def _battery_text(inputs: SafetyInputs) -> str:
        parts = []
        if inputs.battery_v is not None:
            parts.append(f"{inputs.battery_v:.2f} V")
        if inputs.battery_pct is not None:
            parts.append(f"{inputs.battery_pct:.0f} %")
        return " / ".join(parts) if parts else "unknown"

    # ------------------------------------------------------------------ events
    def _emit(self, now_s: float, kind: Fault | str, message: str, severity: str = "warning",
              action: SafetyAction | None = None) -> None:
        self._events.append(SafetyEvent(time_s=float(now_s), kind=str(kind), action=action or self._action,
                                        message=message, severity=severity))
