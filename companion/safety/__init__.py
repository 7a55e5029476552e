"""Safety manager: pure watchdog and command filter (issue 6)."""

from companion.safety.manager import (
    Fault,
    SafetyAction,
    SafetyConfig,
    SafetyEvent,
    SafetyInputs,
    SafetyManager,
    SafetyOutput,
    SafetyState,
)

__all__ = [
    "Fault",
    "SafetyAction",
    "SafetyConfig",
    "SafetyEvent",
    "SafetyInputs",
    "SafetyManager",
    "SafetyOutput",
    "SafetyState",
]
