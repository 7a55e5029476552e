"""Control: velocity command types and the SE(3)-log visual-servo law (issue 6)."""

from companion.control.servo import ServoController, ServoGains, ServoLaw
from companion.control.types import VelocityCommand

__all__ = ["ServoController", "ServoGains", "ServoLaw", "VelocityCommand"]
