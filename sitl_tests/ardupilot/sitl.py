"""The real ArduCopter SITL for the tests: re-exported from `companion.sim.ardupilot_sitl`."""

from companion.sim.ardupilot_sitl import (
    ArduPilotSitl,
    SitlError,
    SitlObserver,
    extnav_parm,
    free_instance,
    sitl_binary,
)

EXTNAV_PARM = extnav_parm()

__all__ = ["EXTNAV_PARM", "ArduPilotSitl", "SitlError", "SitlObserver", "extnav_parm", "free_instance",
           "sitl_binary"]
