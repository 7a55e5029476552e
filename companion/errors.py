"""The one exception tree of the project.

Every error the product raises on purpose derives from `CompanionError`, so an
integrator's script (or the daemon's top level) can catch them all in one place
and tell them apart by type. Input-shape errors also derive from `ValueError`
so generic numerical code that expects ValueError keeps working.
"""

from __future__ import annotations


class CompanionError(Exception):
    """Base class of every error raised on purpose by companion."""


class InputError(CompanionError, ValueError):
    """An argument has the wrong shape, type or value (names the argument)."""


class ConfigError(CompanionError):
    """The configuration file or a configuration value is invalid (names the key)."""


class MissionError(CompanionError):
    """A mission file is invalid or a mission cannot run (names line and field)."""


class LinkError(CompanionError):
    """The MAVLink link failed: transport, protocol or autopilot refusal."""


class CommandDenied(LinkError):
    """The autopilot answered a command with a non-accepted COMMAND_ACK."""


class CommandTimeout(LinkError):
    """No COMMAND_ACK arrived for a command after all retries."""


class CameraError(CompanionError):
    """A camera could not be opened, configured or read, or its calibration is bad."""


class TrackingError(CompanionError):
    """A vision tracker or odometer was misused or its model is invalid."""


class EstimationError(CompanionError):
    """The navigation filter received inconsistent inputs."""


class SafetyError(CompanionError):
    """A command was refused by the safety manager."""
